"""Mass matrix, forces, momenta and energy by autodiff against hand-derived formulas."""

import hypothesis.extra.numpy as hnp
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings

import jaxlag as jl

G = 9.81
finite = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)


def double_pendulum(q, qd, args):
    m1, m2, l1, l2 = args
    t1, t2 = q
    w1, w2 = qd
    y1 = -l1 * jnp.cos(t1)
    y2 = y1 - l2 * jnp.cos(t2)
    vx1, vy1 = l1 * jnp.cos(t1) * w1, l1 * jnp.sin(t1) * w1
    vx2, vy2 = vx1 + l2 * jnp.cos(t2) * w2, vy1 + l2 * jnp.sin(t2) * w2
    kinetic = 0.5 * m1 * (vx1**2 + vy1**2) + 0.5 * m2 * (vx2**2 + vy2**2)
    return kinetic - G * (m1 * y1 + m2 * y2)


def hand_double_pendulum(q, qd, args):
    """Textbook M(q) and F(q, q̇) of the double pendulum in absolute angles."""
    m1, m2, l1, l2 = args
    t1, t2 = q
    w1, w2 = qd
    c = jnp.cos(t1 - t2)
    s = jnp.sin(t1 - t2)
    mass = jnp.array([[(m1 + m2) * l1**2, m2 * l1 * l2 * c], [m2 * l1 * l2 * c, m2 * l2**2]])
    force = jnp.array(
        [
            -m2 * l1 * l2 * s * w2**2 - (m1 + m2) * G * l1 * jnp.sin(t1),
            m2 * l1 * l2 * s * w1**2 - m2 * G * l2 * jnp.sin(t2),
        ]
    )
    return mass, force


ARGS = (1.3, 0.7, 1.1, 0.9)
SYSTEM = jl.System(double_pendulum)


@settings(max_examples=25, deadline=None)
@given(hnp.arrays(np.float64, 2, elements=finite), hnp.arrays(np.float64, 2, elements=finite))
def test_double_pendulum_mass_matrix_and_forces(q, qd):
    mass, force = hand_double_pendulum(q, qd, ARGS)
    # Both sides are O(1-10) sums of a few products: agreement to 1e-12 is round-off level.
    np.testing.assert_allclose(SYSTEM.mass_matrix(q, qd, args=ARGS), mass, atol=1e-12)
    np.testing.assert_allclose(SYSTEM.generalized_forces(q, qd, args=ARGS), force, atol=1e-11)
    np.testing.assert_allclose(
        SYSTEM.accelerations(q, qd, args=ARGS), jnp.linalg.solve(mass, force), atol=1e-10
    )
    np.testing.assert_allclose(SYSTEM.momenta(q, qd, args=ARGS), mass @ qd, atol=1e-12)
    # For L = T − V with T quadratic in q̇, h = T + V = q̇ᵀMq̇ − L + ... = 2T − (T − V).
    kinetic = 0.5 * qd @ mass @ qd
    lagrangian = double_pendulum(q, qd, ARGS)
    np.testing.assert_allclose(SYSTEM.energy(q, qd, args=ARGS), 2 * kinetic - lagrangian, atol=1e-11)


def quadratic_lagrangian(q, qd, args):
    return 0.5 * qd @ args["A"] @ qd + (args["B"] @ q) @ qd - 0.5 * q @ q


QUADRATIC = jl.System(quadratic_lagrangian)


@settings(max_examples=25, deadline=None)
@given(
    hnp.arrays(np.float64, (3, 3), elements=finite),
    hnp.arrays(np.float64, 3, elements=finite),
    hnp.arrays(np.float64, 3, elements=finite),
    hnp.arrays(np.float64, 3, elements=finite),
)
def test_general_quadratic_lagrangian(a, b, q, qd):
    """L = ½ q̇ᵀ A q̇ + (Bq)·q̇ − ½|q|² with A SPD: M = A, F = ∂L/∂q − (∂²L/∂q̇∂q) q̇."""
    spd = a @ a.T + 3 * np.eye(3)
    skew = np.outer(b, b[::-1])
    # A and B are arrays in args, not constants closed over: one compiled program for all examples.
    args = {"A": spd, "B": skew}
    # ∂L/∂q = Bᵀ q̇ − q, ∂²L/∂q̇∂q = B, so F = Bᵀq̇ − q − B q̇.
    expected_force = skew.T @ qd - q - skew @ qd
    np.testing.assert_allclose(QUADRATIC.mass_matrix(q, qd, args=args), spd, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(QUADRATIC.generalized_forces(q, qd, args=args), expected_force, atol=1e-11)


def test_explicit_time_derivative_term():
    """L = ½ m (q̇ − v(t))², v(t) = sin t: F must contain −∂²L/∂q̇∂t = m cos t."""
    system = jl.System(lambda q, qd, t: 0.5 * 2.0 * (qd[0] - jnp.sin(t)) ** 2)
    t = 0.7
    np.testing.assert_allclose(
        system.generalized_forces(jnp.zeros(1), jnp.ones(1), t), [2.0 * np.cos(t)], rtol=1e-14
    )
    np.testing.assert_allclose(system.accelerations(jnp.zeros(1), jnp.ones(1), t), [np.cos(t)], rtol=1e-14)


def test_mechanics_functions_compose_with_jit_vmap_grad():
    qs = jnp.array([[0.1, 0.2], [1.0, -0.5], [2.0, 3.0]])
    qds = jnp.ones_like(qs)
    energies = jax.jit(jax.vmap(lambda q, v: SYSTEM.energy(q, v, args=ARGS)))(qs, qds)
    np.testing.assert_allclose(
        energies, [SYSTEM.energy(q, v, args=ARGS) for q, v in zip(qs, qds)], rtol=1e-14
    )
    # ∂h/∂q̇ = M q̇ for a natural Lagrangian.
    grad_h = jax.grad(lambda v: SYSTEM.energy(qs[1], v, args=ARGS))(qds[1])
    np.testing.assert_allclose(grad_h, SYSTEM.mass_matrix(qs[1], qds[1], args=ARGS) @ qds[1], rtol=1e-12)
