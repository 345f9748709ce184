r"""Lagrangians built from particle positions (``jaxlag.coordinates``).

The kinetic energy ``T = ½ Σ m |ẋ|²`` is formed from a position map by a forward-mode jvp; every
test compares it with a Lagrangian written out by hand (re-derived in the comments), so the
expected values are independent of the code under test. Pointwise identities are compared at
``1e-12`` relative: a handful of float64 operations on O(1) numbers, far above rounding (~1e-15)
and far below any modelling error.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxlag as jl
from jaxlag import analysis, coordinates

jax.config.update("jax_enable_x64", True)

finite = st.floats(-2.0, 2.0, allow_nan=False)


def test_coordinate_maps():
    r, th, ph, z = 1.7, 0.4, -1.1, 0.3
    np.testing.assert_allclose(coordinates.polar(r, th), [r * math.cos(th), r * math.sin(th)], rtol=1e-15)
    np.testing.assert_allclose(
        coordinates.cylindrical(r, ph, z), [r * math.cos(ph), r * math.sin(ph), z], rtol=1e-15
    )
    np.testing.assert_allclose(
        coordinates.spherical(r, th, ph),
        [r * math.sin(th) * math.cos(ph), r * math.sin(th) * math.sin(ph), r * math.cos(th)],
        rtol=1e-15,
    )
    # Broadcasting: a batch of points keeps the coordinate axis last.
    assert coordinates.spherical(jnp.ones(4), 0.3, jnp.zeros(4)).shape == (4, 3)
    chain = coordinates.planar_chain(jnp.array([0.0, math.pi / 2]), jnp.array([1.0, 2.0]))
    np.testing.assert_allclose(chain, [[0.0, -1.0], [2.0, -1.0]], atol=1e-15)


@settings(max_examples=5, deadline=None)
@given(st.tuples(*[finite] * 6), st.floats(0.1, 3.0))
def test_spherical_kinetic_energy_matches_hand_derivation(state, m):
    # T = ½ m (ṙ² + r² θ̇² + r² sin²θ φ̇²), V = m g r cos θ (z = r cos θ up).
    r, th, ph, rd, thd, phd = state
    r = abs(r) + 0.5
    args = {"m": m, "g": 9.81}
    lagrangian = coordinates.lagrangian_from_positions(
        lambda q: coordinates.spherical(q[0], q[1], q[2]),
        masses=lambda a: a["m"],
        gravity=lambda a: a["g"],
    )
    q, qd = jnp.array([r, th, ph]), jnp.array([rd, thd, phd])
    by_hand = 0.5 * m * (rd**2 + r**2 * thd**2 + r**2 * math.sin(th) ** 2 * phd**2) - m * 9.81 * r * math.cos(
        th
    )
    np.testing.assert_allclose(lagrangian(q, qd, 0.0, args), by_hand, rtol=1e-12, atol=1e-12)


def test_time_dependent_map_gives_the_rotating_wire_lagrangian():
    # Seed 001: bead on z = c r² spinning at ω; x = (r cos ωt, r sin ωt, c r²) gives
    # L = ½ m (ṙ² + 4c²r²ṙ² + r²ω²) − m g c r² (the ∂x/∂t terms come from the jvp in t).
    m, c, g, w = 0.7, 1.3, 9.81, 2.1

    def wire(q, t):
        return coordinates.cylindrical(q[0], w * t, c * q[0] ** 2)

    lagrangian = coordinates.lagrangian_from_positions(wire, m, gravity=g)
    rng = np.random.default_rng(0)
    for _ in range(3):
        r, rd, t = rng.normal(size=3)
        by_hand = 0.5 * m * (rd**2 + 4 * c**2 * r**2 * rd**2 + r**2 * w**2) - m * g * c * r**2
        np.testing.assert_allclose(lagrangian(jnp.array([r]), jnp.array([rd]), t), by_hand, rtol=1e-12)


def test_potential_and_several_masses():
    # Two masses on a line joined by a spring: L = ½ m₁ẋ₁² + ½ m₂ẋ₂² − ½ k (x₂ − x₁ − a)².
    def positions(q):
        return q[:, None]  # (2, 1): two points in 1-D

    def spring(q, args):
        return 0.5 * args["k"] * (q[1] - q[0] - args["a"]) ** 2

    lagrangian = coordinates.lagrangian_from_positions(positions, jnp.array([1.0, 3.0]), spring)
    args = {"k": 2.0, "a": 0.5}
    q, qd = jnp.array([0.1, 0.9]), jnp.array([0.3, -0.2])
    expected = 0.5 * 0.3**2 + 1.5 * 0.2**2 - 0.5 * 2.0 * (0.8 - 0.5) ** 2
    np.testing.assert_allclose(lagrangian(q, qd, 0.0, args), expected, rtol=1e-14)
    # Normal modes of the free two-body spring: ω = 0 (translation) and √(k (1/m₁ + 1/m₂)).
    system = jl.System(lagrangian)
    modes = analysis.normal_modes(system, jnp.array([0.0, 0.5]), args=args)
    # Compare ω², the eigenvalues themselves. The zero eigenvalue comes out as round-off of size
    # up to ~eps·|ω²_max|: exactly 0 on this CPU, but ω₀ = 4e-9 (ω₀² ≈ 1.6e-17 ≈ 0.03 eps·ω²_max) on
    # an H100, where a test of ω against atol 1e-12 failed: it tested the square root of round-off.
    # A backward-stable symmetric eigensolver gives every eigenvalue to a small multiple of
    # eps·‖M⁻¹K‖; 64 eps leaves room for the reduction to the standard problem.
    omega_squared = 2.0 * (1 + 1 / 3)
    np.testing.assert_allclose(
        modes.frequencies_squared,
        [0.0, omega_squared],
        rtol=0,
        atol=64 * np.finfo(np.float64).eps * omega_squared,
    )
    # The frequencies then agree to √(64 eps ω²_max) at zero (square root of a round-off value) and
    # to round-off relative to the non-zero one.
    np.testing.assert_allclose(modes.frequencies[1], math.sqrt(omega_squared), rtol=1e-13)
    assert abs(modes.frequencies[0]) <= math.sqrt(64 * np.finfo(np.float64).eps * omega_squared)


def test_rigid_body_physical_pendulum():
    # A uniform rod (mass m, length l) pivoted at one end; angle θ from the downward vertical.
    # Centre at (½l sinθ, −½l cosθ), I_c = m l²/12, so I_pivot = m l²/3 and
    # L = ⅙ m l² θ̇² + ½ m g l cos θ: small oscillations at ω = √(3g/(2l)).
    def pose(q, args):
        half = 0.5 * args["l"]
        return jnp.stack([half * jnp.sin(q[0]), -half * jnp.cos(q[0]), q[0]])

    rod = coordinates.RigidBody2D(pose, mass=lambda a: a["m"], inertia=lambda a: a["m"] * a["l"] ** 2 / 12)
    lagrangian = coordinates.lagrangian_from_positions(None, gravity=lambda a: a["g"], bodies=[rod])
    args = {"m": 2.0, "l": 1.5, "g": 9.81}
    th, thd = 0.4, -1.2
    by_hand = 2.0 * 1.5**2 * thd**2 / 6 + 0.5 * 2.0 * 9.81 * 1.5 * math.cos(th)
    np.testing.assert_allclose(lagrangian(jnp.array([th]), jnp.array([thd]), 0.0, args), by_hand, rtol=1e-13)
    modes = analysis.normal_modes(jl.System(lagrangian), jnp.zeros(1), args=args)
    np.testing.assert_allclose(modes.frequencies, [math.sqrt(3 * 9.81 / (2 * 1.5))], rtol=1e-13)


def test_parameters_are_differentiable():
    # ∂L/∂m = T/m − g y for a single particle with masses=lambda a: a["m"].
    lagrangian = coordinates.lagrangian_from_positions(
        lambda q: q, lambda a: a["m"], gravity=lambda a: a["g"]
    )
    q, qd = jnp.array([0.3, -0.4]), jnp.array([1.0, 2.0])
    grads = jax.jit(jax.grad(lambda a: lagrangian(q, qd, 0.0, a)))({"m": 1.5, "g": 9.81})
    np.testing.assert_allclose(grads["m"], 0.5 * 5.0 - 9.81 * (-0.4), rtol=1e-14)
    np.testing.assert_allclose(grads["g"], -1.5 * (-0.4), rtol=1e-14)


def test_bad_input_is_reported():
    q, qd = jnp.zeros(2), jnp.zeros(2)
    with pytest.raises(ValueError, match=r"shape \(N, d\)"):
        coordinates.lagrangian_from_positions(lambda q: jnp.zeros((2, 2, 2)))(q, qd)
    with pytest.raises(ValueError, match="one entry per point"):
        coordinates.lagrangian_from_positions(lambda q: q.reshape(2, 1), jnp.ones(3))(q, qd)
    with pytest.raises(ValueError, match=r"\(x_c, y_c, angle\)"):
        body = coordinates.RigidBody2D(lambda q: q, 1.0, 1.0)
        coordinates.lagrangian_from_positions(None, bodies=[body])(q, qd)
    with pytest.raises(TypeError, match="RigidBody2D"):
        coordinates.lagrangian_from_positions(lambda q: q, bodies=[object()])
    with pytest.raises(ValueError, match="potential must return a scalar"):
        coordinates.lagrangian_from_positions(lambda q: q, potential=lambda q: q)(q, qd)
    with pytest.raises(ValueError, match="position map, rigid bodies"):
        coordinates.lagrangian_from_positions(None)
    with pytest.raises(TypeError, match="position map"):
        coordinates.lagrangian_from_positions(lambda: None)
