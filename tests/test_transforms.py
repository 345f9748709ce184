"""jit, vmap and grad through jaxlag, and no recompilation across calls."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import jaxlag as jl

TS = jnp.linspace(0.0, 2.0, 21)


def pendulum(q, qd, args):
    return 0.5 * args["l"] ** 2 * qd[0] ** 2 + args["g"] * args["l"] * jnp.cos(q[0])


SYSTEM = jl.System(pendulum)
ARGS = {"g": 9.81, "l": 1.3}


def test_vmap_over_initial_states_equals_loop():
    q0s = jnp.array([[0.1], [0.7], [1.5], [2.9]])
    batched = jax.vmap(lambda q0: jl.simulate(SYSTEM, q0, jnp.zeros(1), TS, args=ARGS))(q0s)
    assert batched.q.shape == (4, 21, 1)
    for i, q0 in enumerate(q0s):
        single = jl.simulate(SYSTEM, q0, jnp.zeros(1), TS, args=ARGS)
        # Same program on the same inputs: agreement to round-off (batched kernels may reorder).
        np.testing.assert_allclose(batched.q[i], single.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batched.energy[i], single.energy, rtol=1e-13)


def test_vmap_over_parameters_equals_loop():
    gs = jnp.array([1.0, 9.81, 20.0])
    batched = jax.vmap(
        lambda g: jl.simulate(SYSTEM, jnp.array([1.0]), jnp.zeros(1), TS, args={"g": g, "l": 1.3})
    )(gs)
    assert batched.energy.shape == (3, 21)
    for i, g in enumerate(gs):
        single = jl.simulate(SYSTEM, [1.0], [0.0], TS, args={"g": g, "l": 1.3})
        np.testing.assert_allclose(batched.q[i], single.q, atol=1e-12)


def test_jit_returns_a_trajectory_with_derived_quantities():
    run = jax.jit(lambda a: jl.simulate(SYSTEM, jnp.array([1.0]), jnp.zeros(1), TS, args=a))
    traj = run(ARGS)
    assert traj.q.shape == (21, 1)
    assert jnp.max(jnp.abs(traj.energy - traj.energy[0])) < 1e-8


def test_grad_wrt_parameter_matches_central_differences_fixed_step():
    # With fixed steps the discrete solution is a smooth function of g, so the central difference
    # error is O(h²) ~ 1e-10 relative and autodiff is exact for the discrete map.
    def loss(g):
        traj = jl.simulate(
            SYSTEM,
            [1.0],
            [0.0],
            TS,
            args={"g": g, "l": 1.3},
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=0.01,
        )
        return jnp.sum(traj.q[:, 0] ** 2)

    g = 9.81
    h = 1e-5 * g
    fd = (loss(g + h) - loss(g - h)) / (2 * h)
    ad = jax.grad(loss)(g)
    assert abs(ad - fd) / abs(fd) < 1e-8


def test_grad_wrt_parameter_and_initial_state_adaptive():
    # Adaptive steps at rtol 1e-12: finite differences carry step-selection noise of about
    # tol/h ≈ 1e-9 and truncation ≈ h² ≈ 1e-8 relative, so 1e-6 is a safe bound.
    tight = diffrax.PIDController(rtol=1e-12, atol=1e-12)

    def loss(g, theta0):
        traj = jl.simulate(
            SYSTEM, jnp.array([theta0]), jnp.zeros(1), TS, args={"g": g, "l": 1.3}, stepsize_controller=tight
        )
        return jnp.sum(jnp.sin(traj.q[:, 0]))

    dg, dth = jax.grad(loss, argnums=(0, 1))(9.81, 0.8)
    h = 1e-4
    fd_g = (loss(9.81 + h, 0.8) - loss(9.81 - h, 0.8)) / (2 * h)
    fd_th = (loss(9.81, 0.8 + h) - loss(9.81, 0.8 - h)) / (2 * h)
    assert abs(dg - fd_g) / abs(fd_g) < 1e-6
    assert abs(dth - fd_th) / abs(fd_th) < 1e-6


def test_closure_over_traced_values_works():
    def final_angle(g):
        system = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 + g * jnp.cos(q[0]))
        return jl.simulate(system, [1.0], [0.0], TS).q[-1, 0]

    def with_args(g):
        system = jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 + args * jnp.cos(q[0]))
        return jl.simulate(system, [1.0], [0.0], TS, args=g).q[-1, 0]

    np.testing.assert_allclose(jax.grad(final_angle)(9.81), jax.grad(with_args)(9.81), rtol=1e-10)
    np.testing.assert_allclose(jax.jit(final_angle)(9.81), with_args(9.81), rtol=1e-12)


def test_second_call_with_new_values_does_not_recompile():
    traces = []

    def counted(q, qd, args):
        traces.append(1)
        return pendulum(q, qd, args)

    system = jl.System(counted)
    jl.simulate(system, [1.0], [0.0], TS, args={"g": 9.81, "l": 1.0})
    first = len(traces)
    jl.simulate(system, [0.5], [0.2], TS, args={"g": 3.0, "l": 2.0})
    jl.simulate(system, np.array([0.3]), np.array([0.0]), TS, args={"g": np.float64(5.0), "l": 2.0})
    assert len(traces) == first


def test_vmap_of_grad():
    def loss(g):
        return jl.simulate(SYSTEM, [1.0], [0.0], TS, args={"g": g, "l": 1.3}).q[-1, 0]

    gs = jnp.array([5.0, 9.81])
    batched = jax.vmap(jax.grad(loss))(gs)
    np.testing.assert_allclose(batched, [jax.grad(loss)(g) for g in gs], rtol=1e-10)
