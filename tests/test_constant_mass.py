r"""State-independent mass matrices: detected while tracing, inverted once, same results.

``jaxlag.constant_mass`` decides from the jaxpr of ``M(q, q̇, t, args)`` whether ``M`` depends on
the state. These tests check the decision on the cases that matter (Cartesian particles, masses
in ``args``, ``M(q)`` of angles, jitted helpers, loops, closures over traced values) and that the
fast path changes nothing but speed: every trajectory is compared with the same system forced
onto the general path (a term ``0·q₀·|q̇|²`` that makes ``M`` depend on ``q`` structurally but not
numerically), to 1e-12 — both runs take identical steps, so only rounding of the different
``M⁻¹`` evaluation separates them.
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxlag as jl
from jaxlag._mechanics.constant_mass import ConstantMass, constant_mass, mass_dependence, with_constant_mass
from jaxlag._mechanics.kkt import accelerations_and_multipliers

jax.config.update("jax_enable_x64", True)

G = 9.81
TS = jnp.linspace(0.0, 2.0, 21)
T0 = jnp.asarray(0.0)


def particles(q, qd):
    return 0.5 * jnp.sum(qd**2) - G * jnp.sum(q[1::2])


def particles_with_masses(q, qd, args):
    return 0.5 * jnp.sum(jnp.repeat(args["m"], 2) * qd**2) - G * jnp.sum(args["m"] * q[1::2])


def chain(q):
    p = q.reshape(-1, 2)
    d = p - jnp.concatenate([jnp.zeros((1, 2)), p[:-1]])
    return jnp.sum(d**2, axis=1) - 1.0


def general_path(lagrangian):
    """The same Lagrangian with a structural (numerically zero) dependence of M on q."""

    def wrapped(q, qd, *rest, **kw):
        return lagrangian(q, qd, *rest, **kw) + 0.0 * q[0] * jnp.sum(qd**2)

    import inspect

    wrapped.__signature__ = inspect.signature(lagrangian)
    return wrapped


def chain_state(n):
    theta = 0.6 + 0.25 * jnp.sin(1.3 * jnp.arange(n, dtype=float))
    omega = 0.3 * jnp.cos(0.7 * jnp.arange(n, dtype=float))
    d = jnp.stack([jnp.sin(theta), -jnp.cos(theta)], axis=1)
    w = omega[:, None] * jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=1)
    return jnp.cumsum(d, axis=0).reshape(-1), jnp.cumsum(w, axis=0).reshape(-1)


# ----------------------------------------------------------------------------- the decision
def test_cartesian_particles_give_a_concrete_diagonal_inverse():
    q, qd = chain_state(3)
    found = constant_mass(jl.System(particles, chain), q, qd, T0, None)
    assert isinstance(found, ConstantMass)
    assert isinstance(found.inverse_diagonal, np.ndarray) and found.inverse is None
    np.testing.assert_array_equal(found.matrix, np.eye(6))


def test_coupled_constant_mass_gives_a_dense_inverse():
    def lagrangian(q, qd):
        return 0.5 * (2.0 * qd[0] ** 2 + qd[1] ** 2) + 0.3 * qd[0] * qd[1] - jnp.cos(q[0])

    q, qd = jnp.array([0.1, 0.2]), jnp.array([0.0, 0.0])
    found = constant_mass(jl.System(lagrangian), q, qd, T0, None)
    mass = np.array([[2.0, 0.3], [0.3, 1.0]])
    np.testing.assert_allclose(found.inverse, np.linalg.inv(mass), rtol=1e-14)
    assert found.inverse_diagonal is None


def test_dependence_on_state_parameters_and_helpers():
    q, qd = jnp.array([0.3, 0.1]), jnp.array([0.2, -0.1])

    def angles(q, qd):  # M(q) of a double-pendulum-like form
        return 0.5 * qd[0] ** 2 + 0.5 * (1.0 + jnp.cos(q[0])) * qd[1] ** 2

    assert mass_dependence(jl.System(angles), q, qd, T0, None) == (True, False)

    def time_varying(q, qd, t):  # a mass that grows: M(t)
        return 0.5 * (1.0 + t) * jnp.sum(qd**2)

    assert mass_dependence(jl.System(time_varying), q, qd, T0, None)[0]

    def masses(q, qd, args):
        return 0.5 * jnp.sum(args * qd**2) - jnp.sum(q)

    assert mass_dependence(jl.System(masses), q, qd, T0, jnp.ones(2)) == (False, True)

    @jax.jit
    def kinetic(v):  # a jitted helper is followed into its body
        return 0.5 * jnp.sum(v**2)

    def with_helper(q, qd):
        return kinetic(qd) - jnp.sum(jnp.cos(q))

    assert mass_dependence(jl.System(with_helper), q, qd, T0, None) == (False, False)

    def with_loop(q, qd):  # a loop is not followed: conservatively "depends"
        def body(carry, x):
            return carry + 0.5 * x**2, None

        return jax.lax.scan(body, jnp.zeros(()), qd)[0] - jnp.sum(q)

    assert mass_dependence(jl.System(with_loop), q, qd, T0, None)[0]


# --------------------------------------------------------------- same results, every path
@pytest.mark.parametrize("projection", [None, jl.Projection()])
def test_constant_path_matches_general_path(projection):
    q0, qd0 = chain_state(4)
    fast = jl.simulate(jl.System(particles, chain), q0, qd0, TS, projection=projection)
    slow = jl.simulate(jl.System(general_path(particles), chain), q0, qd0, TS, projection=projection)
    np.testing.assert_allclose(fast.q, slow.q, atol=1e-12)
    np.testing.assert_allclose(fast.multipliers, slow.multipliers, atol=1e-10)
    if projection is not None:  # index-1 alone drifts at the tolerance (3e-10 here)
        assert float(jnp.max(jnp.abs(jax.vmap(chain)(fast.q)))) < 1e-13


def test_masses_in_args_inverted_once_and_differentiable():
    q0, qd0 = chain_state(3)
    args = {"m": jnp.array([1.0, 2.0, 0.5])}
    fast_system = jl.System(particles_with_masses, chain)
    slow_system = jl.System(general_path(particles_with_masses), chain)
    found = constant_mass(fast_system, q0, qd0, T0, args)
    np.testing.assert_allclose(found.inverse, np.diag(1.0 / np.repeat(args["m"], 2)), atol=1e-15)

    def loss(system, m):
        traj = jl.simulate(system, q0, qd0, TS, args={"m": m})
        return jnp.sum(traj.q[-1] ** 2)

    np.testing.assert_allclose(loss(fast_system, args["m"]), loss(slow_system, args["m"]), rtol=1e-12)
    grad_fast = jax.grad(lambda m: loss(fast_system, m))(args["m"])
    grad_slow = jax.grad(lambda m: loss(slow_system, m))(args["m"])
    np.testing.assert_allclose(grad_fast, grad_slow, rtol=1e-9)
    # Gravity and inertia scale together here, so only the constraint coupling makes the masses
    # matter; finite differences confirm the gradient is not the trivially zero one.
    h = 1e-5
    fd = [
        (loss(fast_system, args["m"].at[i].add(h)) - loss(fast_system, args["m"].at[i].add(-h))) / (2 * h)
        for i in range(3)
    ]
    np.testing.assert_allclose(grad_fast, fd, rtol=1e-5, atol=1e-8)
    assert float(jnp.max(jnp.abs(grad_fast))) > 1e-3


def test_vmap_and_traced_closure():
    q0, qd0 = chain_state(2)

    def run(g):  # g closed over by the Lagrangian: traced, but M does not depend on it
        system = jl.System(lambda q, qd: 0.5 * jnp.sum(qd**2) - g * jnp.sum(q[1::2]), chain)
        return jl.simulate(system, q0, qd0, TS).q[-1]

    gs = jnp.array([9.0, 9.81, 10.5])
    batched = jax.jit(jax.vmap(run))(gs)
    # The reference: the general path with g in args, so that one compiled program serves every g.
    reference = jl.System(
        general_path(lambda q, qd, args: 0.5 * jnp.sum(qd**2) - args * jnp.sum(q[1::2])), chain
    )
    for i, g in enumerate(gs):
        np.testing.assert_allclose(batched[i], jl.simulate(reference, q0, qd0, TS, args=g).q[-1], atol=1e-12)

    def run_mass(m):  # the mass itself closed over and traced: inverted once per run
        system = jl.System(lambda q, qd: 0.5 * m * jnp.sum(qd**2) - m * G * jnp.sum(q[1::2]), chain)
        return jl.simulate(system, q0, qd0, TS).q[-1]

    # The same motion as unit masses at g = G (gs[1]), already computed: no further compilation.
    np.testing.assert_allclose(jax.jit(run_mass)(2.0), batched[1], atol=1e-12)


def test_unilateral_constraint_uses_the_constant_path():
    # A particle on top of a sphere of radius R (Cartesian), released at cos θ = (2/3) cos θ0.
    radius, theta0 = 1.0, 0.2

    def lagrangian(q, qd):
        return 0.5 * jnp.sum(qd**2) - G * q[1]

    def sphere(q):
        return jnp.array([jnp.sqrt(q[0] ** 2 + q[1] ** 2) - radius])

    system = jl.System(lagrangian, sphere, unilateral=0)
    q0 = radius * jnp.array([jnp.sin(theta0), jnp.cos(theta0)])
    traj = jl.simulate(system, q0, jnp.zeros(2), jnp.linspace(0.0, 3.0, 31))
    t_release = float(traj.events.time[0])
    q_release = traj.events.q[0]
    cos_release = float(q_release[1] / jnp.linalg.norm(q_release))
    np.testing.assert_allclose(cos_release, (2.0 / 3.0) * np.cos(theta0), rtol=1e-10)
    assert t_release > 0


def test_singular_constant_mass_is_reported_without_the_initial_check():
    degenerate = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * jnp.sum(q**2))
    with pytest.raises(ValueError, match="singular or not positive definite"):
        jl.simulate(degenerate, jnp.ones(2), jnp.zeros(2), TS, checks=jl.Checks(initial_state=False))


def test_constant_step_solver_and_forward_mode():
    q0, qd0 = chain_state(3)
    system = jl.System(particles_with_masses, chain)
    kwargs = dict(
        t0=0.0,
        t1=1.0,
        dt0=0.01,
        saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=diffrax.ConstantStepSize(),
        adjoint=diffrax.ForwardMode(),
    )

    def final(m):
        return jl.simulate(system, q0, qd0, args={"m": m}, **kwargs).q[-1]

    m = jnp.array([1.0, 1.5, 2.0])
    jac = jax.jacfwd(final)(m)
    h = 1e-6
    fd = jnp.stack([(final(m.at[i].add(h)) - final(m.at[i].add(-h))) / (2 * h) for i in range(3)], axis=1)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-8)


def test_args_with_keys_and_integers():
    # Non-float leaves in args (a PRNG key, an integer array) neither break the analysis nor the
    # once-per-call evaluation; the trajectory is the closed-form free fall y = 1 − g t²/2.
    def lagrangian(q, qd, args):
        noise = 0.0 * jax.random.normal(args["key"], ()) * args["count"][0].astype(float)
        return 0.5 * jnp.sum(qd**2) - args["g"] * q[1] + noise

    args = {"g": 9.81, "key": jax.random.key(0), "count": jnp.array([3])}
    ts = jnp.linspace(0.0, 1.0, 3)
    traj = jl.simulate(jl.System(lagrangian), jnp.array([0.0, 1.0]), jnp.zeros(2), ts, args=args)
    np.testing.assert_allclose(traj.q[:, 1], 1.0 - 0.5 * 9.81 * ts**2, atol=1e-12)
    found = constant_mass(
        jl.System(lagrangian),
        jnp.zeros(2),
        jnp.zeros(2),
        T0,
        {"g": jnp.asarray(9.81), "key": jax.random.key(0), "count": jnp.array([3])},
    )
    assert found is not None and found.inverse_diagonal is not None


@settings(max_examples=15, deadline=None)
@given(
    n=st.integers(1, 4),
    seed=st.integers(0, 2**31 - 1),
    state_dependent=st.booleans(),
    gyroscopic=st.booleans(),
)
def test_decision_and_equations_over_random_lagrangians(n, seed, state_dependent, gyroscopic):
    """L = ½q̇ᵀ(A + s·diag(1 + sin²q))q̇ + g(q)·q̇ − V(q) with a random SPD A: M depends on the
    state exactly when s ≠ 0 (a gyroscopic term b(q)·q̇ never changes M), the constant M found is
    A, and the constrained accelerations and multipliers equal the general path's to 1e-12."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, n))
    a = jnp.asarray(a @ a.T + n * np.eye(n))
    b = jnp.asarray(rng.normal(size=(n, n)))
    k = jnp.asarray(rng.uniform(0.5, 2.0, size=n))

    def lagrangian(q, qd):
        kinetic = 0.5 * qd @ a @ qd
        if state_dependent:
            kinetic = kinetic + 0.5 * jnp.sum((1.0 + jnp.sin(q) ** 2) * qd**2)
        magnetic = jnp.tanh(b @ q) @ qd if gyroscopic else 0.0
        return kinetic + magnetic - 0.5 * jnp.sum(k * q**2) - jnp.sum(jnp.cos(q))

    def constraint(q):
        return jnp.array([jnp.sum(q**2) - 1.0])

    system = jl.System(lagrangian, constraint)
    q = jnp.asarray(rng.normal(size=n))
    q = q / jnp.linalg.norm(q)
    qd = jnp.asarray(rng.normal(size=n))
    on_state, on_parameters = mass_dependence(system, q, qd, T0, None)
    assert on_state == state_dependent and not on_parameters
    found = constant_mass(system, q, qd, T0, None)
    if state_dependent:
        assert found is None
        return
    np.testing.assert_allclose(found.matrix, a, rtol=1e-13)
    fast = with_constant_mass(system, q, qd, T0, None)
    fast_out = accelerations_and_multipliers(fast, q, qd, T0, None)
    slow_out = accelerations_and_multipliers(system, q, qd, T0, None)
    for x, y in zip(fast_out, slow_out):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)


def test_concrete_mass_is_one_program_and_survives_traced_closures():
    """The constant M is evaluated by one compiled program (op by op, each operation of the
    Hessian would compile a program of its own); a Lagrangian that closes over a traced value
    (on which M does not depend) still gets a concrete M, by the op-by-op fallback."""
    from jaxlag._mechanics.constant_mass import _concrete_mass

    q, qd = chain_state(2)
    from test_batch import CompileCounter

    with CompileCounter() as compiles:
        system = jl.System(lambda q, qd: 0.5 * 3.0 * jnp.sum(qd**2) - G * jnp.sum(q[1::2]), chain)
        mass = jax.jit(lambda q: jnp.asarray(_concrete_mass(system, q, qd, T0, None)))(q)
    assert compiles.count <= 2  # M's program, and the caller's own jit
    np.testing.assert_array_equal(mass, 3.0 * np.eye(4))

    def traced(g):
        closing = jl.System(lambda q, qd: 0.5 * jnp.sum(qd**2) - g * jnp.sum(q[1::2]), chain)
        found = _concrete_mass(closing, q, qd, T0, None)
        assert isinstance(found, np.ndarray)
        return jnp.asarray(found) * g

    np.testing.assert_array_equal(jax.jit(traced)(2.0), 2.0 * np.eye(4))
