"""The ensemble integrator (simulate_batch(method=jl.Ensemble())): one loop for the whole batch.

Checked against diffrax per member (same tableau, constant steps), against closed forms and
jl.simulate (adaptive), on the constraint manifold, in Pallas's interpreter, under jit/vmap/grad,
with gradients against central differences, and sharded over two (forced host) devices.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxlag as jl

jax.config.update("jax_enable_x64", True)

CONSTANT = diffrax.ConstantStepSize()


def oscillator(q, qd, args):
    return 0.5 * qd[0] ** 2 - 0.5 * args["w"] ** 2 * q[0] ** 2


OSCILLATOR = jl.System(oscillator)
DOUBLE = jl.systems.double_pendulum()


def cartesian_pendulum(q, qd, args):
    return 0.5 * (qd[0] ** 2 + qd[1] ** 2) - args["g"] * q[1]


def rod(q, args):
    return jnp.array([q[0] ** 2 + q[1] ** 2 - args["l"] ** 2])


PENDULUM_XY = jl.System(cartesian_pendulum, holonomic=rod)
LENGTHS = jnp.array([0.5, 1.0, 2.0])
ANGLES = jnp.array([0.3, 1.2, 2.5])


def on_rod():
    q0 = jnp.stack([LENGTHS * jnp.sin(ANGLES), -LENGTHS * jnp.cos(ANGLES)], axis=1)
    qd0 = jnp.stack([LENGTHS * jnp.cos(ANGLES), LENGTHS * jnp.sin(ANGLES)], axis=1) * 0.7
    return q0, qd0


def double_states(batch):
    s = jnp.linspace(0.0, 1.0, batch)
    return (
        jnp.stack([2.0 - 1.5 * s, -0.5 + jnp.sin(7.0 * s)], axis=1),
        jnp.stack([0.3 * jnp.cos(5.0 * s), -1.1 + 0.5 * s], axis=1),
    )


@pytest.mark.parametrize("solver", [diffrax.Tsit5(), jl.RK4()], ids=["Tsit5", "RK4"])
def test_constant_steps_equal_diffrax_per_member(solver):
    q0, qd0 = double_states(3)
    ts = jnp.linspace(0.0, 1.0, 5)
    options = dict(solver=solver, stepsize_controller=CONSTANT, dt0=0.01)
    batch = jl.simulate_batch(DOUBLE, q0, qd0, ts, method=jl.Ensemble(), **options)
    assert batch.q.shape == (3, 5, 2) and batch.t.shape == (3, 5)
    np.testing.assert_array_equal(batch.stats["num_steps"], [100, 100, 100])
    for i in range(3):
        single = jl.simulate(DOUBLE, q0[i], qd0[i], ts, **options)  # diffrax.diffeqsolve
        np.testing.assert_allclose(batch.q[i], single.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.qd[i], single.qd, rtol=0, atol=1e-12)


@settings(max_examples=6, deadline=None)
@given(st.lists(st.floats(-2.5, 2.5), min_size=12, max_size=12))
def test_random_members_equal_diffrax_and_conserve_energy(values):
    # Same shapes as the test above: one compiled program for every example.
    x = jnp.asarray(values).reshape(3, 4)
    q0, qd0 = x[:, :2], x[:, 2:]
    ts = jnp.linspace(0.0, 1.0, 5)
    options = dict(solver=diffrax.Tsit5(), stepsize_controller=CONSTANT, dt0=0.01)
    batch = jl.simulate_batch(DOUBLE, q0, qd0, ts, method=jl.Ensemble(), **options)
    single = jl.simulate(DOUBLE, q0[0], qd0[0], ts, **options)
    np.testing.assert_allclose(batch.q[0], single.q, rtol=0, atol=1e-12)
    energy = batch.energy
    # Tsit5 at h = 0.01: local error ~ h⁶ |y⁽⁶⁾|, energy drift well below 1e-6 relative.
    assert jnp.max(jnp.abs(energy - energy[:, :1])) <= 1e-6 * (1 + jnp.max(jnp.abs(energy)))


def test_adaptive_members_take_their_own_steps_and_match_the_closed_form():
    ws = jnp.array([1.0, 50.0])
    ts = jnp.linspace(0.0, 2.0, 9)
    tol = 1e-8
    batch = jl.simulate_batch(
        OSCILLATOR,
        jnp.ones((2, 1)),
        jnp.zeros((2, 1)),
        ts,
        args={"w": ws},
        args_axes=0,
        method=jl.Ensemble(),
        stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
    )
    dopri = jl.simulate_batch(
        OSCILLATOR,
        jnp.ones((2, 1)),
        jnp.zeros((2, 1)),
        ts,
        args={"w": ws},
        args_axes=0,
        method=jl.Ensemble(),
        solver=diffrax.Dopri5(),
        stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
    )
    exact = jnp.cos(ws[:, None] * ts[None, :])
    assert jnp.max(jnp.abs(dopri.q[0, :, 0] - exact[0])) < 10 * tol
    assert jnp.max(jnp.abs(dopri.q[1, :, 0] - exact[1])) < 200 * tol
    error = jnp.max(jnp.abs(batch.q[..., 0] - exact), axis=1)
    steps = np.asarray(batch.stats["num_accepted_steps"])
    print(
        "accepted steps per member (w = 1, 50):",
        steps,
        "rejected:",
        np.asarray(batch.stats["num_rejected_steps"]),
        "max error:",
        error,
    )
    assert steps[1] > 10 * steps[0]
    # Global error ≈ tolerance × the number of steps (local errors add up); 100 periods at w = 50.
    assert error[0] < 10 * tol and error[1] < 200 * tol
    for i in range(2):
        single = jl.simulate(
            OSCILLATOR,
            jnp.ones(1),
            jnp.zeros(1),
            ts,
            args={"w": ws[i]},
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
        )
        assert jnp.max(jnp.abs(batch.q[i] - single.q)) < 2 * max(error[i], tol) + 1e-12


def test_constrained_members_stay_on_the_manifold():
    q0, qd0 = on_rod()
    ts = jnp.linspace(0.0, 3.0, 7)
    args = {"g": 9.81, "l": LENGTHS}
    for controller, dt0 in ((diffrax.PIDController(rtol=1e-9, atol=1e-9), None), (CONSTANT, 0.01)):
        batch = jl.simulate_batch(
            PENDULUM_XY,
            q0,
            qd0,
            ts,
            args=args,
            args_axes={"l": 0, "g": None},
            method=jl.Ensemble(),
            stepsize_controller=controller,
            dt0=dt0,
        )
        f, f_dot, _ = batch.constraint_residuals
        assert jnp.max(jnp.abs(f)) <= 1e-10 and jnp.max(jnp.abs(f_dot)) <= 1e-10
        if dt0 is not None:  # same steps, same projection: diffrax's result to rounding
            for i in range(3):
                single = jl.simulate(
                    PENDULUM_XY,
                    q0[i],
                    qd0[i],
                    ts,
                    dt0=dt0,
                    args={"g": 9.81, "l": LENGTHS[i]},
                    stepsize_controller=controller,
                )
                np.testing.assert_allclose(batch.q[i], single.q, rtol=0, atol=1e-12)


def test_second_call_with_new_values_does_not_recompile():
    from test_batch import CompileCounter

    ts = jnp.linspace(0.0, 1.0, 3)
    options = dict(args_axes=0, method=jl.Ensemble(), stepsize_controller=CONSTANT, dt0=0.01)
    jl.simulate_batch(
        OSCILLATOR, jnp.ones((2, 1)), jnp.zeros((2, 1)), ts, args={"w": jnp.array([1.0, 2.0])}, **options
    )
    q0, qd0, ws = jnp.full((2, 1), 0.5, dtype=jnp.float64), jnp.zeros((2, 1)), jnp.array([3.0, 4.0])
    with CompileCounter() as counter:
        again = jl.simulate_batch(OSCILLATOR, q0, qd0, ts, args={"w": ws}, **options)
    assert counter.count == 0
    np.testing.assert_allclose(again.q[:, -1, 0], 0.5 * jnp.cos(jnp.array([3.0, 4.0])), atol=1e-9)


def test_velocity_constraints_knife_edge_matches_the_closed_form():
    skate = jl.systems.knife_edge()
    omegas = jnp.array([1.0, 2.0])
    ts = jnp.linspace(0.0, 2.0, 5)
    qd0 = jnp.stack([jnp.zeros(2), jnp.zeros(2), omegas], axis=1)
    batch = jl.simulate_batch(
        skate,
        jnp.zeros(3),
        qd0,
        ts,
        method=jl.Ensemble(),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
    )
    p = jl.systems.knife_edge.defaults
    scale = p["g"] * np.sin(p["alpha"]) / (2 * omegas[:, None] ** 2)
    wt = omegas[:, None] * ts[None, :]
    np.testing.assert_allclose(batch.q[..., 0], scale * jnp.sin(wt) ** 2, atol=1e-8)
    np.testing.assert_allclose(batch.q[..., 1], scale * (wt - 0.5 * jnp.sin(2 * wt)), atol=1e-8)
    _, _, g = batch.constraint_residuals
    assert jnp.max(jnp.abs(g)) <= 1e-10


def test_per_member_save_times_and_shared_initial_state():
    ts = jnp.array([[0.0, 0.5, 1.0], [0.0, 0.25, 2.0]])
    batch = jl.simulate_batch(
        OSCILLATOR,
        jnp.ones(1),
        jnp.zeros(1),
        ts,
        args={"w": 2.0},
        method=jl.Ensemble(),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
    )
    np.testing.assert_array_equal(batch.t, ts)
    np.testing.assert_allclose(batch.q[..., 0], jnp.cos(2.0 * ts), atol=1e-8)


def test_pallas_interpret_equals_the_xla_loop(monkeypatch):
    import jaxlag.experimental._ensemble.pallas as kernel

    monkeypatch.setattr(kernel, "BLOCK", 2)  # 3 members: two programs, one padded member
    lanewise = []
    original = kernel.lanes_integrate
    monkeypatch.setattr(kernel, "lanes_integrate", lambda *a, **k: lanewise.append(1) or original(*a, **k))
    q0, qd0 = on_rod()
    args = {"g": 9.81, "l": LENGTHS}
    options = dict(args=args, args_axes={"l": 0, "g": None}, stepsize_controller=CONSTANT, dt0=0.05)
    # Shared save times: the lane-wise kernel (KKT solve and projection as column code);
    # per-member save times: the kernel on (block, n) arrays.
    for ts in (jnp.linspace(0.0, 1.0, 3), jnp.array([[0.0, 0.5, 1.0], [0.0, 0.3, 1.0], [0.0, 0.5, 0.9]])):
        xla = jl.simulate_batch(PENDULUM_XY, q0, qd0, ts, method=jl.Ensemble(backend="xla"), **options)
        pallas = jl.simulate_batch(
            PENDULUM_XY, q0, qd0, ts, method=jl.Ensemble(backend="pallas-interpret"), **options
        )
        np.testing.assert_allclose(pallas.q, xla.q, rtol=0, atol=1e-14)
        np.testing.assert_allclose(pallas.qd, xla.qd, rtol=0, atol=1e-14)
        np.testing.assert_array_equal(pallas.stats["num_steps"], xla.stats["num_steps"])
    assert len(lanewise) == 1
    if jax.default_backend() == "cpu":  # no compiled Pallas on CPU: a warning and the XLA loop
        with pytest.warns(RuntimeWarning, match="did not lower.*XLA loop"):
            fallback = jax.jit(
                lambda q: (
                    jl.simulate_batch(
                        PENDULUM_XY, q, qd0, ts, method=jl.Ensemble(backend="pallas"), **options
                    ).q
                )
            )(q0)
        # The same loop compiled inside a user jit (returning q only): rounding may differ by an ulp.
        np.testing.assert_allclose(fallback, xla.q, rtol=0, atol=1e-14)


def test_gradients_match_closed_form_and_central_differences():
    ts = jnp.linspace(0.0, 1.0, 3)
    adaptive = diffrax.PIDController(rtol=1e-10, atol=1e-10)

    def loss(w, controller, adjoint=None):
        traj = jl.simulate_batch(
            OSCILLATOR,
            jnp.ones((2, 1)),
            jnp.zeros((2, 1)),
            ts,
            args={"w": w},
            args_axes=0,
            method=jl.Ensemble(),
            max_steps=500,
            stepsize_controller=controller,
            adjoint=adjoint,
            dt0=0.01 if controller is CONSTANT else None,
        )
        return jnp.sum(traj.q[..., 0] ** 2 * jnp.array([0.0, 2.0, 1.0])[None, :])  # every save counts

    w = jnp.array([1.0, 3.0])
    # d/dw Σ_k c_k cos²(w t_k) = −Σ_k c_k t_k sin(2 w t_k), t = (0, 0.5, 1), c = (0, 2, 1)
    exact = -(2.0 * 0.5 * jnp.sin(w) + jnp.sin(2 * w))
    eps = 1e-5
    for controller in (CONSTANT, adaptive):
        fd = jnp.array(
            [
                (loss(w.at[i].add(eps), controller) - loss(w.at[i].add(-eps), controller)) / (2 * eps)
                for i in range(2)
            ]
        )
        # reverse: scan of checkpointed steps / equinox's checkpointed while loop
        reverse = jax.jit(jax.grad(loss), static_argnums=1)(w, controller)
        # forward: jvp through the scan / the lax while loop
        forward = jax.jacfwd(loss)(w, controller, diffrax.ForwardMode())
        print(
            type(controller).__name__, "reverse", reverse, "forward", forward, "central", fd, "exact", exact
        )
        np.testing.assert_allclose(reverse, exact, rtol=1e-7)
        # Adaptive: central differences also see the step sizes change with w (O(tol / eps)).
        np.testing.assert_allclose(reverse, fd, rtol=1e-8 if controller is CONSTANT else 1e-5)
        # Same discrete solver differentiated two ways: equal to rounding at constant steps. With
        # adaptive steps the two programs round differently, which can flip a step acceptance
        # near the threshold: then they differ like two solutions within rtol = 1e-10 (~1e-8).
        np.testing.assert_allclose(forward, reverse, rtol=1e-11 if controller is CONSTANT else 1e-7)


def scaled_oscillator(q, qd, args):
    # Builds an array from Python floats while tracing (as jl.systems' models do with their
    # masses): inside the Pallas kernel such constants must become kernel inputs.
    weights = jnp.stack([1.0, 0.5])
    return weights[1] * qd[0] ** 2 - weights[1] * args["w"] ** 2 * q[0] ** 2 * weights[0]


def test_pallas_kernel_is_differentiable():
    system = jl.System(scaled_oscillator)
    ts = jnp.linspace(0.0, 1.0, 3)

    def loss(w, backend):
        traj = jl.simulate_batch(
            system,
            jnp.ones((2, 1)),
            jnp.zeros((2, 1)),
            ts,
            args={"w": w},
            args_axes=0,
            method=jl.Ensemble(backend=backend),
            stepsize_controller=CONSTANT,
            dt0=0.05,
        )
        return jnp.sum(traj.q[:, -1] ** 2)

    w = jnp.array([1.0, 2.0])
    np.testing.assert_allclose(loss(w, "pallas-interpret"), loss(w, "xla"), rtol=1e-14)
    pallas = jax.jit(jax.grad(loss), static_argnums=1)(w, "pallas-interpret")
    exact = -2 * jnp.cos(w) * jnp.sin(w)  # d/dw cos²(w t) at t = 1
    np.testing.assert_allclose(pallas, jax.grad(loss)(w, "xla"), rtol=1e-12)
    np.testing.assert_allclose(pallas, exact, rtol=1e-6)


def test_vmap_over_the_ensemble_call():
    ts = jnp.linspace(0.0, 1.0, 3)

    def run(w):
        return jl.simulate_batch(
            OSCILLATOR,
            jnp.ones((2, 1)),
            jnp.zeros((2, 1)),
            ts,
            args={"w": jnp.stack([w, 2 * w])},
            args_axes=0,
            method=jl.Ensemble(),
            stepsize_controller=CONSTANT,
            dt0=0.01,
        ).q[..., 0]

    out = jax.vmap(run)(jnp.array([1.0, 3.0]))
    ws = jnp.array([[1.0, 2.0], [3.0, 6.0]])
    np.testing.assert_allclose(out, jnp.cos(ws[..., None] * ts[None, None, :]), atol=1e-9)


def test_auto_is_vmap_on_cpu_and_unchanged():
    ts = jnp.linspace(0.0, 1.0, 3)
    q0, qd0 = double_states(2)
    auto = jl.simulate_batch(
        OSCILLATOR, q0[:, :1], qd0[:, :1], ts, args={"w": 2.0}, stepsize_controller=CONSTANT, dt0=0.05
    )
    vmapped = jl.simulate_batch(
        OSCILLATOR,
        q0[:, :1],
        qd0[:, :1],
        ts,
        args={"w": 2.0},
        stepsize_controller=CONSTANT,
        dt0=0.05,
        method=jl.Vmap(),
    )
    np.testing.assert_array_equal(auto.q, vmapped.q)


def test_bad_input_gets_a_clear_error():
    ts = jnp.linspace(0.0, 1.0, 3)
    q0, qd0 = double_states(2)
    with pytest.raises(TypeError, match=r"Butcher tableau.*method=jl\.Vmap\(\)"):
        jl.simulate_batch(
            DOUBLE,
            q0,
            qd0,
            ts,
            method=jl.Ensemble(),
            solver=diffrax.ReversibleHeun(),
            stepsize_controller=CONSTANT,
            dt0=0.1,
        )
    with pytest.raises(ValueError, match=r"Event.*method=jl\.Vmap\(\)"):
        jl.simulate_batch(DOUBLE, q0, qd0, ts, method=jl.Ensemble(), events=[jl.Event(lambda q, qd: q[0])])
    sphere = jl.systems.particle_on_sphere(unilateral=True)
    with pytest.raises(ValueError, match=r"unilateral.*method=jl\.Vmap\(\)"):
        jl.simulate_batch(sphere, jnp.array([[2.0, 0.1]]), jnp.zeros((1, 2)), ts, method=jl.Ensemble())
    with pytest.raises(ValueError, match=r"RK4 has no embedded method.*ConstantStepSize\(\) with a step dt0"):
        jl.simulate_batch(DOUBLE, q0, qd0, ts, method=jl.Ensemble(), solver=jl.RK4())
    with pytest.raises(ValueError, match="need 1000 steps, more than max_steps=10"):
        jl.simulate_batch(
            DOUBLE, q0, qd0, ts, method=jl.Ensemble(), stepsize_controller=CONSTANT, dt0=1e-3, max_steps=10
        )
    ones = jnp.ones((2, 1))
    with pytest.raises(jl.SimulationError, match=r"Member \[0\]: The simulation reached max_steps = 5 steps"):
        jl.simulate_batch(OSCILLATOR, ones, ones, ts, args={"w": 1.0}, method=jl.Ensemble(), max_steps=5)
    partial = jl.simulate_batch(
        OSCILLATOR, ones, ones, ts, args={"w": 1.0}, method=jl.Ensemble(), max_steps=5, throw=False
    )
    assert not jnp.any(partial.result == diffrax.RESULTS.successful)
    assert jnp.all(partial.stats["num_steps"] == 5)
    # Saves an unfinished member did not reach are inf, as diffrax and method=jl.Vmap() give them
    # (they were 0.0). The start is always reached.
    vmapped = jl.simulate_batch(
        OSCILLATOR, ones, ones, ts, args={"w": 1.0}, method=jl.Vmap(), max_steps=5, throw=False
    )
    for traj in (partial, vmapped):
        assert np.all(np.isinf(traj.q[:, 1:])) and np.all(np.isinf(traj.qd[:, 1:]))
        np.testing.assert_array_equal(traj.q[:, 0], ones)
        np.testing.assert_array_equal(traj.failure.code, [2, 2])  # max_steps
    with pytest.raises(TypeError, match=r"method must be jl\.Vmap\(\), jl\.Ensemble\(\.\.\.\) or None"):
        jl.simulate_batch(DOUBLE, q0, qd0, ts, method="loop")


def test_sharded_over_two_devices_equals_unsharded():
    """A mesh of two of the suite's four CPU devices (conftest: jax_num_cpu_devices)."""
    mesh = jax.sharding.Mesh(np.array(jax.devices()[:2]), ("batch",))
    system = jl.systems.simple_pendulum()
    q0 = jnp.linspace(0.1, 3.0, 4)[:, None]
    qd0 = jnp.zeros((4, 1))
    ts = jnp.linspace(0.0, 1.0, 3)
    kw = dict(method=jl.Ensemble(), stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9))
    one = jl.simulate_batch(system, q0, qd0, ts, **kw)
    two = jl.simulate_batch(system, q0, qd0, ts, sharding=mesh, **kw)
    assert len(two.q.sharding.device_set) == 2, two.q.sharding
    np.testing.assert_allclose(two.q, one.q, rtol=0, atol=1e-12)


def test_lanewise_equations_equal_vmap_for_a_nine_link_chain():
    # Cumulative sums, unstacking and the Cholesky-based solve of an n = 9 mass matrix, all as
    # column code (what the Pallas kernel runs).
    from jaxlag.experimental._ensemble import lanes

    field = jl.EquationsOfMotion(jl.systems.n_link_pendulum(9))  # 9 > UNROLL_MAX: LAPACK calls

    def one(q, qd):
        return field(0.0, (q, qd), None)

    q = 0.3 * jnp.sin(jnp.arange(36.0)).reshape(4, 9)
    qd = jnp.cos(jnp.arange(36.0)).reshape(4, 9)
    run = lanes.lanewise(one, q[0], qd[0])

    @jax.jit
    def by_columns(q, qd):
        out = run(lanes.columns(q), lanes.columns(qd))
        return [jnp.stack([jnp.broadcast_to(e, (4,)) for e in part], axis=1) for part in out]

    for got, expected in zip(by_columns(q, qd), jax.vmap(one)(q, qd)):
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- failed members


def quartic(q, qd, args):
    # V = q²/2 − a q⁴. a = 0: the harmonic oscillator, q = cos t from (1, 0). a = 1: from q = 1,
    # q̈ = −q + 4q³ ≥ 3 and q reaches infinity in finite time (t ≈ 1.001).
    return 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2 + args["a"] * q[0] ** 4


QUARTIC = jl.System(quartic)
TS_BLOW = jnp.linspace(0.0, 3.0, 4)
BLOW = dict(args={"a": jnp.array([1.0, 0.0])}, args_axes={"a": 0})
ONE, REST = jnp.ones((2, 1)), jnp.zeros((2, 1))


def _assert_blown_member_reported(traj):
    """Member 0 blew up between t = 1 and 2, member 1 is cos t (errors, Tsit5: 1.3e-14 at
    dt = 0.01, 3.8e-11 at the default rtol = atol = 1e-10)."""
    np.testing.assert_array_equal(np.ravel(traj.result == diffrax.RESULTS.successful), [False, True])
    assert np.all(np.isfinite(traj.q[0, :2])) and np.all(np.isinf(traj.q[0, 2:]))
    assert np.all(np.isinf(traj.qd[0, 2:]))
    np.testing.assert_allclose(traj.q[1, :, 0], np.cos(TS_BLOW), rtol=0, atol=1e-10)


@pytest.mark.parametrize("backend", ["xla", "pallas-interpret"])
def test_member_that_blows_up_with_constant_steps_fails(backend):
    # Before: the blown-up member's saves were NaN with result "successful", and throw=True
    # raised nothing. Now it fails (code 1, non-finite) like method=jl.Vmap(), with the same
    # saves (inf from the first save it did not reach), on both backends.
    options = dict(BLOW, stepsize_controller=CONSTANT, dt0=0.01, throw=False)
    traj = jl.simulate_batch(QUARTIC, ONE, REST, TS_BLOW, method=jl.Ensemble(backend), **options)
    vmapped = jl.simulate_batch(QUARTIC, ONE, REST, TS_BLOW, method=jl.Vmap(), **options)
    for run in (traj, vmapped):
        _assert_blown_member_reported(run)
        np.testing.assert_array_equal(run.failure.code, [1, 0])
    # Reported at its last finite save (vmap: at the last finite step, t = 1.01).
    assert float(traj.failure.t[0]) == 1.0 and float(traj.failure.dt[0]) == pytest.approx(0.01)
    np.testing.assert_array_equal(traj.failure.q[0], traj.q[0, 1])
    if backend == "xla":
        with pytest.raises(
            jl.SimulationError,
            match=r"1 of 2 batch members failed \(first: member \[0\]\)\. Member \[0\]: The "
            r"equations of motion became non-finite \(NaN or inf\) at t = 1 ",
        ):
            jl.simulate_batch(
                QUARTIC, ONE, REST, TS_BLOW, method=jl.Ensemble(backend), **{**options, "throw": True}
            )


def test_member_that_blows_up_with_adaptive_steps_fails_like_vmap():
    # Adaptive steps shrink towards the singularity until they reach round-off: the member stops
    # there (code 5, the step size collapsed) instead of spinning until max_steps, at the time
    # jl.Vmap() reports (t = 1.0010774, 10 digits), the other member unaffected.
    traj = jl.simulate_batch(QUARTIC, ONE, REST, TS_BLOW, method=jl.Ensemble(), throw=False, **BLOW)
    vmapped = jl.simulate_batch(QUARTIC, ONE, REST, TS_BLOW, method=jl.Vmap(), throw=False, **BLOW)
    for run in (traj, vmapped):
        _assert_blown_member_reported(run)
        np.testing.assert_array_equal(run.failure.code, [5, 0])
    np.testing.assert_allclose(traj.failure.t, vmapped.failure.t, rtol=1e-9)
    assert int(traj.stats["num_steps"][0]) < 2 * int(vmapped.stats["num_steps"][0])


def test_failed_members_raise_under_jit_and_are_recorded_under_vmap():
    def final(a, throw):
        args = {"a": a}
        traj = jl.simulate_batch(
            QUARTIC, ONE, REST, TS_BLOW, args=args, args_axes={"a": 0}, method=jl.Ensemble(),
            stepsize_controller=CONSTANT, dt0=0.01, throw=throw,
        )  # fmt: skip
        return traj.q[:, -1, 0], traj.failure.code

    jitted = jax.jit(final, static_argnums=1)
    q1, code = jitted(jnp.array([0.0, 0.0]), True)
    np.testing.assert_allclose(q1, np.cos(3.0), rtol=0, atol=1e-12)
    with pytest.raises(Exception, match="equations of motion became non-finite"):
        jax.block_until_ready(jitted(jnp.array([0.0, 1.0]), True))
    _, codes = jax.vmap(lambda a: final(a, False))(jnp.array([[1.0, 0.0], [0.0, 0.0]]))
    np.testing.assert_array_equal(codes, [[1, 0], [0, 0]])


def test_float32_batches_use_float32_defaults():
    # A float32 pendulum 4e-5 off its rod (round-off of float32 inputs is ~1e-7; simulate
    # accepts up to √ε = 3.5e-4). The ensemble uses simulate's float32 defaults: constraint
    # tolerance √ε and rtol = atol = 1.2e-5 (before: rtol = atol = 1e-10, below float32
    # round-off: ~2,900 steps for 1 s instead of ~10).
    th = jnp.array([0.3, 1.1])
    q0 = jnp.stack([jnp.sin(th), -jnp.cos(th)], 1) * (1 + 2e-5)
    qd0 = 0.7 * jnp.stack([jnp.cos(th), jnp.sin(th)], 1)
    ts = jnp.linspace(0.0, 1.0, 3)
    q32, qd32, ts32 = (x.astype(jnp.float32) for x in (q0, qd0, ts))
    loose = jl.Checks(constraint_tolerance=1e-4)  # float64: the same (slightly off) state
    options = dict(args={"g": 9.81, "l": 1.0}, method=jl.Ensemble())
    reference = jl.simulate_batch(PENDULUM_XY, q0, qd0, ts, checks=loose, **options)
    traj = jl.simulate_batch(PENDULUM_XY, q32, qd32, ts32, **options)
    assert traj.q.dtype == jnp.float32
    assert np.all(traj.stats["num_steps"] < 40)  # 10 and 13 measured (jl.Vmap(): 8 and 13)
    # rtol = atol = 1.2e-5 per unit time over 1 s: 4.4e-6 measured; 5e-5 allows ~4 rtol.
    np.testing.assert_allclose(traj.q, reference.q, rtol=0, atol=5e-5)
    # 1% off (|f| = 0.02) is refused, eagerly, naming the member (as jl.Vmap() does).
    with pytest.raises(
        ValueError, match=r"2 of 2 batch members failed \(first: member \[0\]\).*off the constraint"
    ):
        jl.simulate_batch(PENDULUM_XY, q32 * 1.01, qd32, ts32, **options)


def test_experimental_entry_point_equals_the_method_object():
    """jaxlag.experimental.simulate_ensemble is simulate_batch(method=jl.Ensemble(backend)):
    the same numbers; options the loop does not have are refused by name."""
    ts = jnp.linspace(0.0, 1.0, 5)
    q0, qd0 = double_states(2)
    options = dict(solver=jl.RK4(), stepsize_controller=CONSTANT, dt0=0.01)
    direct = jl.experimental.simulate_ensemble(DOUBLE, q0, qd0, ts, backend="xla", **options)
    method = jl.simulate_batch(DOUBLE, q0, qd0, ts, method=jl.Ensemble(backend="xla"), **options)
    np.testing.assert_array_equal(direct.q, method.q)
    with pytest.raises(ValueError, match=r"progress meters.*method=jl\.Vmap\(\)"):
        jl.simulate_batch(
            DOUBLE, q0, qd0, ts, method=jl.Ensemble(), progress_meter=diffrax.NoProgressMeter(), **options
        )
    with pytest.raises(TypeError, match="unexpected keyword"):
        jl.experimental.simulate_ensemble(DOUBLE, q0, qd0, ts, events=jl.Events(), **options)  # pyright: ignore[reportCallIssue]
