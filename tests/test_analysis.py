r"""Equilibria, linearization, normal modes and conservation laws against closed forms.

Closed forms (re-derived in the comments from the library's sign convention
``M q̈ = F + Jᵀλ``; seeds 001 and 002 for the rotating wire and the cone):

* pendulum: ``ω = √(g/l)``; double pendulum with equal masses and lengths
  ``ω² = (2 ∓ √2) g/l`` with shapes ``θ₂/θ₁ = ±√2``;
* cone of half-angle α: circular orbit ``r₀ = (l_z²/(m² g sin²α cos α))^{1/3}``, oscillation
  ``Ω = √(3 g cos α / r₀)``;
* bead on ``z = c r²`` spinning at ω: ``r̈(1 + 4c²r²) + 4c²rṙ² + (2gc − ω²) r = 0``, so
  ``r = 0`` oscillates at ``√(2gc − ω²)`` for ``ω² < 2gc``, grows at ``√(ω² − 2gc)`` for
  ``ω² > 2gc``, and every radius is steady at ``ω² = 2gc``;
* Noether: ``L_z`` of a spherical pendulum, the linear momentum of a free chain.

Tolerances: equilibria and linearizations are computed from exact derivatives (autodiff) and a
Newton solve to round-off, so frequencies agree with closed forms to ~1e-13 relative; we assert
1e-11 (a few hundred ulps of the O(10) numbers involved, leaving room for the eigen-solvers).
Quantities along simulated trajectories (default rtol = atol = 1e-10) are asserted to 1e-8.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
import scipy.linalg

import jaxlag as jl
import jaxlag.systems as systems
from jaxlag import analysis

jax.config.update("jax_enable_x64", True)

G = 9.81
PENDULUM = {"generalized": systems.simple_pendulum(), "cartesian": systems.simple_pendulum("cartesian")}
DOUBLE = {"generalized": systems.double_pendulum(), "cartesian": systems.double_pendulum("cartesian")}
CONE = systems.particle_on_cone()
CONE_SPHERICAL = systems.particle_on_cone("spherical")
PARABOLA = systems.bead_on_rotating_parabola()
PARABOLA_CYLINDRICAL = systems.bead_on_rotating_parabola("cylindrical")
SPHERICAL_PENDULUM = systems.spherical_pendulum("cartesian")


def cone_closed_form(m, g, alpha, lz):
    r0 = (lz**2 / (m**2 * g * math.sin(alpha) ** 2 * math.cos(alpha))) ** (1 / 3)
    return r0, math.sqrt(3 * g * math.cos(alpha) / r0)


# --------------------------------------------------------------------------------------------
# Pendulums: normal modes
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("form, guess", [("generalized", [0.4]), ("cartesian", [0.5, -1.8])])
def test_pendulum_normal_mode(form, guess):
    system, args = PENDULUM[form], {"l": 2.0}
    eq = analysis.equilibrium(system, jnp.array(guess), args=args)
    expected_q = [0.0] if form == "generalized" else [0.0, -2.0]
    np.testing.assert_allclose(eq.q, expected_q, atol=1e-12)
    modes = analysis.normal_modes(system, eq.q, args=args)
    # In the Cartesian form the restoring stiffness is entirely the constraint curvature λ∇²f.
    np.testing.assert_allclose(modes.frequencies, [math.sqrt(G / 2.0)], rtol=1e-12)
    lin = analysis.linearize(system, eq.q, args=args)
    assert lin.reduced_state_matrix.shape == (2, 2)  # one degree of freedom either way
    np.testing.assert_allclose(lin.frequencies, [math.sqrt(G / 2.0)], rtol=1e-12)
    assert lin.stability() == "stable" and bool(modes.is_stable())


@pytest.mark.parametrize("form, rest", [("generalized", [0.0, 0.0]), ("cartesian", [0.0, -1.5, 0.0, -3.0])])
def test_double_pendulum_normal_modes(form, rest):
    # Equal masses and lengths: M = m l² [[2, 1], [1, 1]], K = m g l [[2, 0], [0, 1]];
    # det(K − ω²M) = 0 gives ω² = (2 ∓ √2) g/l, with θ₂/θ₁ = +√2 (slow) and −√2 (fast).
    system, args = DOUBLE[form], {"l1": 1.5, "l2": 1.5, "m1": 0.7, "m2": 0.7}
    rest = jnp.array(rest)  # hanging straight down
    modes = analysis.normal_modes(system, rest, args=args)
    expected = np.sqrt(np.array([2 - math.sqrt(2), 2 + math.sqrt(2)]) * G / 1.5)
    np.testing.assert_allclose(modes.frequencies, expected, rtol=1e-11)
    np.testing.assert_allclose(analysis.linearize(system, rest, args=args).frequencies, expected, rtol=1e-11)
    shapes = np.asarray(modes.shapes)
    if form == "cartesian":  # small angles: θ₁ ≈ x₁/l, θ₂ ≈ (x₂ − x₁)/l
        shapes = np.stack([shapes[0], shapes[2] - shapes[0]])
    np.testing.assert_allclose(shapes[1] / shapes[0], [math.sqrt(2), -math.sqrt(2)], rtol=1e-10)


def test_n_link_normal_modes_match_hand_built_eigenproblem():
    # Chain of point masses, absolute angles: T = ½ Σ_ij M_ij θ̇_i θ̇_j with
    # M_ij = l_i l_j Σ_{k ≥ max(i,j)} m_k and V ≈ ½ Σ_i g l_i (Σ_{k ≥ i} m_k) θ_i².
    m, l = np.array([1.0, 0.5, 2.0]), np.array([0.7, 1.1, 0.4])
    tail = np.cumsum(m[::-1])[::-1]
    mass = np.outer(l, l) * tail[np.maximum.outer(np.arange(3), np.arange(3))]
    stiffness = np.diag(G * l * tail)
    expected = np.sqrt(scipy.linalg.eigh(stiffness, mass, eigvals_only=True))
    system = systems.n_link_pendulum(3)
    modes = analysis.normal_modes(system, jnp.zeros(3), args={"m": m, "l": l})
    np.testing.assert_allclose(modes.frequencies, expected, rtol=1e-11)
    # Shapes are M-orthonormal.
    np.testing.assert_allclose(modes.shapes.T @ mass @ modes.shapes, np.eye(3), atol=1e-12)


# --------------------------------------------------------------------------------------------
# Cone: circular orbits (steady motion with a prescribed momentum)
# --------------------------------------------------------------------------------------------


def test_cone_circular_orbit_and_its_oscillation_frequency():
    m, alpha, lz = 1.3, 0.5, 2.0
    args = {"m": m, "g": G, "alpha": alpha}
    r0, omega = cone_closed_form(m, G, alpha, lz)
    # (r, φ): φ is cyclic (fixed, its rate found from p_φ = l_z).
    eq = analysis.equilibrium(
        CONE, jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0]), args=args, fixed=(1,), momenta={1: lz}
    )
    np.testing.assert_allclose(eq.q[0], r0, rtol=1e-12)
    np.testing.assert_allclose(eq.qd[1], lz / (m * r0**2 * math.sin(alpha) ** 2), rtol=1e-12)
    lin = analysis.linearize(CONE, eq.q, eq.qd, args=args)
    # Spectrum ±iΩ and a double zero (shift of φ; change of l_z along the family of orbits).
    np.testing.assert_allclose(lin.frequencies, [0.0, omega], rtol=1e-11, atol=1e-7)
    assert lin.stability() == "marginal"
    # The same orbit in spherical coordinates with the constraint θ = α.
    eq_s = analysis.equilibrium(
        CONE_SPHERICAL,
        jnp.array([1.0, 0.4, 0.0]),
        jnp.array([0.0, 0.0, 1.0]),
        args=args,
        fixed=(2,),
        momenta={2: lz},
    )
    np.testing.assert_allclose(eq_s.q[:2], [r0, alpha], rtol=1e-12)
    lin_s = analysis.linearize(CONE_SPHERICAL, eq_s.q, eq_s.qd, args=args)
    assert lin_s.reduced_state_matrix.shape == (4, 4)  # 2·3 − 2 (θ = α and θ̇ = 0)
    np.testing.assert_allclose(lin_s.frequencies, [0.0, omega], rtol=1e-11, atol=1e-7)


def test_cone_frequency_matches_a_simulated_perturbation():
    # Start at r₀(1 + ε) with the same l_z: r oscillates about r₀ with period 2π/Ω + O(ε²).
    m, alpha, lz, eps = 1.3, 0.5, 2.0, 1e-4
    args = {"m": m, "g": G, "alpha": alpha}
    r0, omega = cone_closed_form(m, G, alpha, lz)
    lin = analysis.linearize(
        CONE, jnp.array([r0, 0.0]), jnp.array([0.0, lz / (m * r0**2 * math.sin(alpha) ** 2)]), args=args
    )
    period = 2 * math.pi / float(lin.frequencies[1])
    r_start = r0 * (1 + eps)
    qd0 = jnp.array([0.0, lz / (m * r_start**2 * math.sin(alpha) ** 2)])
    ts = jnp.concatenate([jnp.zeros(1), jnp.linspace(0.97 * period, 1.03 * period, 301)])
    traj = jl.simulate(CONE, jnp.array([r_start, 0.0]), qd0, ts, args=args)
    rdot = np.asarray(traj.qd[1:, 0])
    i = int(np.flatnonzero((rdot[:-1] > 0) & (rdot[1:] <= 0))[0])  # back at the maximum
    t = np.asarray(ts[1:])
    measured = t[i] - rdot[i] * (t[i + 1] - t[i]) / (rdot[i + 1] - rdot[i])
    # ε = 1e-4 puts the amplitude correction at ~ε² = 1e-8; integration error ~1e-10.
    np.testing.assert_allclose(measured, 2 * math.pi / omega, rtol=1e-7)
    np.testing.assert_allclose(measured, period, rtol=1e-7)


def test_cone_orbit_radius_jit_vmap_and_grad():
    # jax.grad of the orbit radius through the root find (implicit differentiation), batched
    # over the cone angle with vmap and compiled with jit, all in one program.
    # Closed form: r₀ ∝ m^{−2/3} so ∂r₀/∂m = −⅔ r₀/m; ∂r₀/∂α is autodiff of the closed-form
    # formula written out independently.
    lz, m = 2.0, 1.3

    def radius(params):
        eq = analysis.equilibrium(
            CONE, jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0]), args=params, fixed=(1,), momenta={1: lz}
        )
        return eq.q[0]

    def closed(alpha):
        return (lz**2 / (m**2 * G * jnp.sin(alpha) ** 2 * jnp.cos(alpha))) ** (1 / 3)

    alphas = jnp.array([0.3, 0.5, 0.9])
    values, grads = jax.jit(jax.vmap(lambda a: jax.value_and_grad(radius)({"m": m, "g": G, "alpha": a})))(
        alphas
    )
    np.testing.assert_allclose(values, jax.vmap(closed)(alphas), rtol=1e-12)
    np.testing.assert_allclose(grads["m"], -2 / 3 * values / m, rtol=1e-10)
    np.testing.assert_allclose(grads["alpha"], jax.vmap(jax.grad(closed))(alphas), rtol=1e-10)


# --------------------------------------------------------------------------------------------
# Bead on the rotating parabolic wire (seed 001)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("omega", [2.0, 5.0])
def test_parabola_axis_equilibrium_on_either_side_of_the_critical_spin(omega):
    c = 1.0
    args = {"c": c, "g": G, "omega": omega}
    eq = analysis.equilibrium(PARABOLA, jnp.array([0.3]), args=args)
    np.testing.assert_allclose(eq.q, [0.0], atol=1e-12)  # the only equilibrium off ω² = 2gc
    lin = analysis.linearize(PARABOLA, eq.q, args=args)
    detuning = 2 * G * c - omega**2
    if detuning > 0:
        assert lin.stability() == "stable"
        np.testing.assert_allclose(lin.frequencies, [math.sqrt(detuning)], rtol=1e-12)
    else:
        assert lin.stability() == "unstable" and not bool(lin.is_stable())
        np.testing.assert_allclose(lin.growth_rate, math.sqrt(-detuning), rtol=1e-12)


def test_parabola_critical_spin_is_sqrt_2gc():
    # The spin at which r = 0 loses stability: the root of ω² ↦ (lowest mode's ω²), found by
    # Newton through normal_modes (differentiable in the parameters).
    c = 0.8

    def lowest(omega, _):
        return analysis.normal_modes(
            PARABOLA, jnp.zeros(1), args={"c": c, "g": G, "omega": omega}
        ).frequencies_squared[0]

    sol = optx.root_find(lowest, optx.Newton(rtol=1e-13, atol=1e-13), jnp.asarray(3.0))
    np.testing.assert_allclose(sol.value, math.sqrt(2 * G * c), rtol=1e-12)


def test_parabola_steady_circle_exactly_at_omega_squared_2gc():
    # Cylindrical form (r, φ, z), f = (z − c r², φ − ωt): hold the bead at r = R on the wire.
    # At ω² = 2gc the state is a steady motion (every radius is): the multiplier of the wire's
    # shape balances gravity, λ₁ = m g, and the drive needs no torque, λ₂ = 0.
    c, R, t = 1.0, 0.7, 0.3
    omega = math.sqrt(2 * G * c)
    args = {"c": c, "g": G, "omega": omega}
    eq = analysis.equilibrium(
        PARABOLA_CYLINDRICAL,
        jnp.array([R, 0.0, 0.0]),
        jnp.array([0.0, omega, 0.0]),
        t=t,
        args=args,
        fixed=(0,),
    )
    np.testing.assert_allclose(eq.q, [R, omega * t, c * R**2], rtol=1e-12)
    np.testing.assert_allclose(eq.multipliers, [G, 0.0], atol=1e-12)
    lin = analysis.linearize(PARABOLA_CYLINDRICAL, eq.q, eq.qd, t=t, args=args)
    assert lin.reduced_state_matrix.shape == (2, 2)  # one degree of freedom along the wire
    # Neutral: δr̈ = 0 (a double zero eigenvalue), the family of steady circles.
    assert lin.stability() == "marginal"
    # Off the critical spin the same radius is not steady, and the error says why.
    with pytest.raises(ValueError, match="not steady"):
        analysis.equilibrium(
            PARABOLA_CYLINDRICAL,
            jnp.array([R, 0.0, 0.0]),
            jnp.array([0.0, 2.0, 0.0]),
            t=t,
            args={**args, "omega": 2.0},
            fixed=(0,),
        )


def test_rotating_hoop_bifurcation():
    # θ from the bottom: L = ½ m R² (θ̇² + ω² sin²θ) + m g R cos θ. For ω² > g/R the bottom is
    # unstable (ω²_mode = g/R − ω² < 0) and cos θ* = g/(Rω²) is stable at ω sin θ*.
    hoop = systems.bead_on_hoop()
    R, omega = 0.5, 6.0
    args = {"R": R, "omega": omega}
    bottom = analysis.normal_modes(hoop, jnp.zeros(1), args=args)
    np.testing.assert_allclose(bottom.frequencies_squared, [G / R - omega**2], rtol=1e-12)
    assert not bool(bottom.is_stable())
    eq = analysis.equilibrium(hoop, jnp.array([1.0]), args=args)
    theta = math.acos(G / (R * omega**2))
    np.testing.assert_allclose(eq.q, [theta], rtol=1e-12)
    modes = analysis.normal_modes(hoop, eq.q, args=args)
    np.testing.assert_allclose(modes.frequencies, [omega * math.sin(theta)], rtol=1e-12)


def test_cart_pole_state_space_matrices():
    # Uniform pole on a cart, θ from upright: M = [[M+m, ½ml], [½ml, ⅓ml²]], V = ½ m g l cos θ,
    # so about θ = 0: M δq̈ − diag(0, ½ m g l) δq = (u, 0).
    M, m, l = 1.0, 0.3, 0.8
    args = {"M": M, "m": m, "l": l, "g": G, "force": 0.0}
    mass = np.array([[M + m, 0.5 * m * l], [0.5 * m * l, m * l**2 / 3]])
    a = np.zeros((4, 4))
    a[:2, 2:] = np.eye(2)
    a[2:, :2] = np.linalg.solve(mass, np.diag([0.0, 0.5 * m * G * l]))
    b = np.concatenate([np.zeros(2), np.linalg.solve(mass, [1.0, 0.0])])[:, None]
    lin = analysis.linearize(systems.cart_pole(), jnp.zeros(2), args=args, inputs=lambda p: p["force"])
    np.testing.assert_allclose(lin.state_matrix, a, atol=1e-12)
    np.testing.assert_allclose(lin.input_matrix, b, atol=1e-12)
    assert lin.stability() == "unstable"
    np.testing.assert_allclose(lin.growth_rate, np.max(np.linalg.eigvals(a).real), rtol=1e-12)


# --------------------------------------------------------------------------------------------
# Conservation laws
# --------------------------------------------------------------------------------------------


def _simulate(system, q0, qd0, args):
    # The options of tests/test_systems.py (exact initial states, no projection over 1 s at
    # rtol 1e-10), so that both files share one compiled simulation per model.
    return jl.simulate(
        system,
        jnp.asarray(q0),
        jnp.asarray(qd0),
        jnp.linspace(0.0, 1.0, 5),
        args=args,
        checks=jl.Checks(initial_state=False),
        projection=None,
    )


def _spherical_pendulum_state(th, ph, thd, phd, l=1.0):
    # Position l(sinθ cosφ, sinθ sinφ, −cosθ) and its velocity.
    x = l * np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)])
    v = l * (
        thd * np.array([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), np.sin(th)])
        + phd * np.sin(th) * np.array([-np.sin(ph), np.cos(ph), 0.0])
    )
    return jnp.asarray(x), jnp.asarray(v)


def test_noether_angular_momentum_of_spherical_pendulum():
    m = 1.7
    args = {"m": m, "l": 1.0}
    q, qd = _spherical_pendulum_state(0.8, 0.3, 0.5, 1.4)
    lz = analysis.rotation_generator([0.0, 0.0, 1.0])
    np.testing.assert_allclose(
        analysis.noether_charge(SPHERICAL_PENDULUM, lz, q, qd, args=args),
        m * (q[0] * qd[1] - q[1] * qd[0]),
        rtol=1e-14,
    )
    # A symmetry: the charge's rate (δL plus the constraint force's torque) vanishes.
    assert abs(analysis.noether_rate(SPHERICAL_PENDULUM, lz, q, qd, args=args)) < 1e-12
    # Rotation about x is not: dL_x/dt is gravity's torque (r × F)_x = y F_z = −m g y (the rod's
    # force is radial and has no torque).
    lx = analysis.rotation_generator([1.0, 0.0, 0.0])
    np.testing.assert_allclose(
        analysis.noether_rate(SPHERICAL_PENDULUM, lx, q, qd, args=args), -m * G * q[1], rtol=1e-12
    )

    traj = _simulate(SPHERICAL_PENDULUM, q, qd, args)
    report = analysis.conservation_report(traj, {"L_z": lz}, ignorable=())
    assert set(report) == {"energy", "L_z"}
    assert report["L_z"].max_deviation < 1e-8 and report["energy"].max_deviation < 1e-8
    assert "L_z" in analysis.format_report(report)


def test_ignorable_coordinate_of_spherical_pendulum_in_angles():
    system = systems.spherical_pendulum()
    q0, qd0 = jnp.array([0.8, 0.3]), jnp.array([0.5, 1.4])
    assert analysis.ignorable_coordinates(system, q0, qd0) == (1,)  # φ, with p_φ = L_z
    # No Cartesian coordinate of the same pendulum is ignorable (the rod constraint acts on all).
    cartesian_state = _spherical_pendulum_state(0.8, 0.3, 0.5, 1.4)
    assert analysis.ignorable_coordinates(SPHERICAL_PENDULUM, *cartesian_state) == ()
    # Momenta and the energy function at a state, m = l = 1, θ from the downward vertical:
    # p = (θ̇, sin²θ φ̇), h = ½ (θ̇² + sin²θ φ̇²) − g cos θ.
    np.testing.assert_allclose(analysis.momenta(system, q0, qd0), [0.5, math.sin(0.8) ** 2 * 1.4], rtol=1e-14)
    np.testing.assert_allclose(
        analysis.energy(system, q0, qd0),
        0.5 * (0.25 + math.sin(0.8) ** 2 * 1.4**2) - G * math.cos(0.8),
        rtol=1e-14,
    )
    traj = _simulate(system, q0, qd0, {"m": 1.0, "l": 1.0})
    report = analysis.conservation_report(traj)
    # p_φ = m l² sin²θ φ̇ (m = l = 1 by default).
    np.testing.assert_allclose(report["p[1]"].initial, math.sin(0.8) ** 2 * 1.4, rtol=1e-14)
    assert report["p[1]"].relative_deviation < 1e-9
    assert report["energy"].relative_deviation < 1e-9


def test_noether_linear_momentum_of_free_chain():
    # Three unit masses, two unit links, moving freely in the plane (g = 2 pulls along −y).
    chain = systems.free_chain(3)
    args = {"g": 2.0}
    q0 = jnp.array([0.0, 0.0, 1.0, 0.0, 1.0, 1.0])
    qd0 = jnp.array([0.3, 0.1, 0.3, -0.5, 1.0, -0.5])  # rigid-compatible: links keep length
    px, py = analysis.translation_generator([1.0, 0.0]), analysis.translation_generator([0.0, 1.0])
    np.testing.assert_allclose(analysis.noether_charge(chain, px, q0, qd0, args=args), 1.6, rtol=1e-14)
    assert abs(analysis.noether_rate(chain, px, q0, qd0, args=args)) < 1e-12
    # Gravity breaks the vertical translation: dP_y/dt = −Σ m g = −6.
    np.testing.assert_allclose(analysis.noether_rate(chain, py, q0, qd0, args=args), -6.0, rtol=1e-12)
    traj = _simulate(chain, q0, qd0, args)
    report = analysis.conservation_report(traj, {"P_x": px, "P_y": py}, ignorable=())
    assert report["P_x"].max_deviation < 1e-8
    np.testing.assert_allclose(report["P_y"].values, -0.9 - 6.0 * traj.t, atol=1e-8)


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------


def test_bad_input_errors():
    q, qd = _spherical_pendulum_state(0.8, 0.3, 0.5, 1.4)
    with pytest.raises(ValueError, match="must return a vector like q"):
        analysis.noether_charge(SPHERICAL_PENDULUM, lambda q: jnp.ones(2), q, qd)
    with pytest.raises(ValueError, match="3-vector"):
        analysis.rotation_generator([0.0, 1.0])
    with pytest.raises(ValueError, match="not a layout"):
        analysis.noether_charge(
            SPHERICAL_PENDULUM, analysis.translation_generator([1.0, 0.0]), jnp.ones(3), jnp.ones(3)
        )
    with pytest.raises(ValueError, match="out of range"):
        analysis.equilibrium(CONE, jnp.array([1.0, 0.0]), fixed=(5,))
    with pytest.raises(ValueError, match="not an equilibrium"):
        analysis.normal_modes(PENDULUM["generalized"], jnp.array([0.3]))
    with pytest.raises(ValueError, match="velocity"):
        analysis.normal_modes(systems.knife_edge(), jnp.zeros(3))
    with pytest.raises(ValueError, match="scalar or a 1-D array"):
        analysis.linearize(
            systems.cart_pole(lambda q, qd, args: -jnp.sum(args["gain"]) * qd[0]),
            jnp.zeros(2),
            args={"gain": jnp.ones((2, 2))},
            inputs=lambda a: a["gain"],
        )


def test_root_find_failure_is_reported():
    # The Kepler force k/r² never vanishes: there is no equilibrium to converge to.
    kepler = systems.kepler()
    with pytest.raises(ValueError, match="did not converge"):
        analysis.equilibrium(kepler, jnp.array([1.0, 0.0]), fixed=(1,), max_steps=16)
    with pytest.raises(Exception, match="did not converge"):
        jax.jit(lambda r: analysis.equilibrium(kepler, jnp.stack([r, 0.0]), fixed=(1,), max_steps=16).q)(
            1.0
        ).block_until_ready()
    eq = analysis.equilibrium(kepler, jnp.array([1.0, 0.0]), fixed=(1,), max_steps=16, throw=False)
    assert eq.result != optx.RESULTS.successful


def test_nonholonomic_tangent_space():
    # Knife edge (n = 3, one velocity constraint): the state manifold has dimension 2·3 − 1 = 5.
    skate = systems.knife_edge()
    q, qd = jnp.array([0.0, 0.0, 0.4]), jnp.array([math.cos(0.4), math.sin(0.4), 1.0])
    lin = analysis.linearize(skate, q, qd)
    assert lin.basis.shape == (6, 5)
    # The basis is tangent: the constraint's linearization −δẋ sinθ + δẏ cosθ − (ẋ cosθ + ẏ sinθ) δθ
    # vanishes on it.
    row = np.array(
        [0.0, 0.0, -(qd[0] * math.cos(0.4) + qd[1] * math.sin(0.4)), -math.sin(0.4), math.cos(0.4), 0.0]
    )
    np.testing.assert_allclose(row @ np.asarray(lin.basis), 0.0, atol=1e-14)
