"""Solves posed on the unit interval (`jaxlag._solver.unit_time`): diffrax integrates
``s ∈ [0, 1]`` while the solver steps real time ``t = t0 + s (t1 − t0)``. The results are the
real-time solve's (closed forms, the same solve in real time, the failure record's times)."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
from jaxlag._solver import unit_time

jax.config.update("jax_enable_x64", True)

# A driven oscillator, q̈ = −q + sin 3t: q(t) = A cos t + B sin t − sin(3t)/8.
DRIVEN = jl.System(lambda q, qd, t, args: 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2 + q[0] * jnp.sin(3 * t))


def _closed_form(ts, t0, q0, v0):
    # q(t) = a cos(t − t0) + b sin(t − t0) − sin(3t)/8, from q(t0) = q0, q̇(t0) = v0.
    a = q0 + np.sin(3 * t0) / 8
    b = v0 + 3 * np.cos(3 * t0) / 8
    return a * np.cos(ts - t0) + b * np.sin(ts - t0) - np.sin(3 * ts) / 8


def _driven_run(**options):
    ts = np.linspace(5.0, 7.5, 26)
    return ts, jl.simulate(DRIVEN, jnp.array([0.3]), jnp.array([-0.2]), ts, **options)


def test_a_time_dependent_run_off_zero_matches_its_closed_form():
    ts, traj = _driven_run()
    np.testing.assert_array_equal(np.asarray(traj.t), ts)  # the save times themselves
    # rtol = atol = 1e-10 per step (the float64 default) over ~40 steps: 1e-9 globally.
    np.testing.assert_allclose(np.asarray(traj.q[:, 0]), _closed_form(ts, 5.0, 0.3, -0.2), atol=2e-9)


def test_the_unit_interval_solve_equals_the_real_time_solve():
    _, unit = _driven_run()
    # A ClipStepSizeController (here without breakpoints) is solved in the run's time.
    real_time = diffrax.ClipStepSizeController(diffrax.PIDController(rtol=1e-10, atol=1e-10))
    _, real = _driven_run(stepsize_controller=real_time)
    assert int(unit.stats["num_steps"]) != 0 and int(real.stats["num_steps"]) != 0
    # The same steps up to the first step size (diffrax's start heuristic is not scale
    # invariant): the two differ by the integration error, not more.
    np.testing.assert_allclose(np.asarray(unit.q), np.asarray(real.q), atol=2e-9)
    np.testing.assert_allclose(np.asarray(unit.qd), np.asarray(real.qd), atol=2e-9)


def test_which_solves_take_the_unit_interval():
    from jaxlag._solver.guard import guard

    pid = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    saves = diffrax.SaveAt(t1=True)
    forward = diffrax.ForwardMode()
    assert unit_time.unit_time_applies(diffrax.Tsit5(), guard(pid), saves, forward, None)
    assert unit_time.unit_time_applies(jl.RK4(), guard(diffrax.ConstantStepSize()), saves, forward, None)
    step_to = diffrax.StepTo(jnp.linspace(0, 1, 3))
    assert unit_time.unit_time_applies(diffrax.Tsit5(), step_to, saves, forward, None)
    # Breakpoints (input tables), a diffrax event, dense output, another adjoint: real time.
    clipped = guard(diffrax.ClipStepSizeController(pid, jump_ts=jnp.array([0.5])))
    assert not unit_time.unit_time_applies(diffrax.Tsit5(), clipped, saves, forward, None)
    event = diffrax.Event(lambda t, y, args, **kwargs: t - 0.5)
    assert not unit_time.unit_time_applies(diffrax.Tsit5(), guard(pid), saves, forward, event)
    # Save times of a saveat= of your own are diffrax's (in the run's time): real time.
    own_times = diffrax.SaveAt(ts=jnp.linspace(0, 1, 3))
    assert not unit_time.unit_time_applies(diffrax.Tsit5(), guard(pid), own_times, forward, None)
    dense = diffrax.SaveAt(dense=True)
    assert not unit_time.unit_time_applies(diffrax.Tsit5(), guard(pid), dense, forward, None)
    backsolve = diffrax.BacksolveAdjoint()
    assert not unit_time.unit_time_applies(diffrax.Tsit5(), guard(pid), saves, backsolve, None)


def test_a_saveat_with_times_of_its_own():
    # diffrax saves at these times itself: the solve stays in the run's time.
    ts = jnp.linspace(5.0, 7.5, 11)
    traj = jl.simulate(
        DRIVEN, jnp.array([0.3]), jnp.array([-0.2]), None, t0=5.0, t1=7.5, saveat=diffrax.SaveAt(ts=ts)
    )
    np.testing.assert_array_equal(np.asarray(traj.t), np.asarray(ts))
    expected = _closed_form(np.asarray(ts), 5.0, 0.3, -0.2)
    np.testing.assert_allclose(np.asarray(traj.q[:, 0]), expected, atol=2e-9)


def test_constant_steps_in_unit_time():
    options = dict(solver=jl.RK4(), stepsize_controller=diffrax.ConstantStepSize(), dt0=0.01)
    ts = np.linspace(5.0, 6.0, 11)
    traj = jl.simulate(DRIVEN, jnp.array([0.3]), jnp.array([-0.2]), ts, **options)
    assert int(traj.stats["num_steps"]) == 100
    # RK4 with h = 0.01: local error ~ h⁵, global ~ 1e-10 over 100 steps.
    np.testing.assert_allclose(np.asarray(traj.q[:, 0]), _closed_form(ts, 5.0, 0.3, -0.2), atol=1e-9)


def test_a_failure_is_recorded_at_its_real_time():
    # The force turns NaN at t = 6.3: the run stops there, and says so in the run's time.
    system = jl.System(
        lambda q, qd: 0.5 * qd[0] ** 2,
        forces=lambda q, qd, t: jnp.where(t > 6.3, jnp.nan, 0.0) * jnp.ones(1),
    )
    traj = jl.simulate(system, jnp.zeros(1), jnp.ones(1), np.linspace(5.0, 8.0, 31), throw=False)
    failure = traj.failure
    assert int(failure.code) == jl.FailureCode.NONFINITE
    assert 6.3 - 1e-9 < float(failure.t) <= 6.3
    assert float(failure.t0) == 5.0 and float(failure.t1) == 8.0
    np.testing.assert_allclose(float(failure.q[0]), float(failure.t) - 5.0, rtol=1e-12)  # q = t − 5
    with pytest.raises(Exception, match="6.3"):
        traj.raise_if_failed()


_COMPILES = [0]


def _count(event, duration, **kwargs):
    if event == "/jax/core/compile/backend_compile_duration":
        _COMPILES[0] += 1


jax.monitoring.register_event_duration_secs_listener(_count)


def test_a_new_horizon_compiles_nothing():
    # The run's times are inputs of the program (diffrax's own end time is the constant 1).
    counts = []
    for end in (2.0, 7.0):
        ts = np.linspace(1.0, end, 21)
        jax.block_until_ready(jl.simulate(DRIVEN, jnp.array([0.3]), jnp.array([-0.2]), ts).q)
        counts.append(_COMPILES[0])
    assert counts[1] == counts[0]


def test_a_gradient_off_zero_matches_the_closed_form():
    # q̈ = −k q + sin 3t from t0 = 5: d q(7.5) / dk by jax.grad (forward sensitivities, solved on
    # the unit interval) against a central difference of the closed form.
    system = jl.System(
        lambda q, qd, t, args: 0.5 * qd[0] ** 2 - 0.5 * args["k"] * q[0] ** 2 + q[0] * jnp.sin(3 * t)
    )
    ts = np.linspace(5.0, 7.5, 6)

    def closed_form(k):
        w, t0, q0, v0 = np.sqrt(k), 5.0, 0.3, -0.2
        particular = lambda t: np.sin(3 * t) / (k - 9)  # noqa: E731
        a = q0 - particular(t0)
        b = (v0 - 3 * np.cos(3 * t0) / (k - 9)) / w
        return a * np.cos(w * (ts[-1] - t0)) + b * np.sin(w * (ts[-1] - t0)) + particular(ts[-1])

    def final(k):
        return jl.simulate(system, jnp.array([0.3]), jnp.array([-0.2]), ts, args={"k": k}).q[-1, 0]

    np.testing.assert_allclose(float(final(1.0)), closed_form(1.0), atol=2e-9)
    h = 1e-5  # the closed form's central difference: truncation ~h², round-off ~1e-16/h
    expected = (closed_form(1.0 + h) - closed_form(1.0 - h)) / (2 * h)
    # The tangents ride on the states' steps (rtol = atol = 1e-10): measured 4e-11 off, as q is.
    np.testing.assert_allclose(float(jax.grad(final)(1.0)), expected, atol=1e-9)


def test_the_end_time_is_differentiable():
    # d q(t1) / d t1 = q̇(t1): the derivative flows through t(s) = t0 + s (t1 − t0), under grad,
    # jit(grad) and vmap. Both sides carry the solver's error (rtol = atol = 1e-10): measured 1.4e-10.
    pendulum = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 + 9.81 * jnp.cos(q[0]))

    def run(end):
        return jl.simulate(pendulum, jnp.array([0.5]), jnp.zeros(1), None, t0=1.0, t1=end)

    def final(end):
        return run(end).q[-1, 0]

    velocity = float(run(2.3).qd[-1, 0])
    np.testing.assert_allclose(float(jax.grad(final)(2.3)), velocity, atol=2e-9)
    np.testing.assert_allclose(float(jax.jit(jax.grad(final))(2.3)), velocity, atol=2e-9)
    batched = jax.vmap(final)(jnp.array([2.0, 2.3]))
    np.testing.assert_allclose(np.asarray(batched), [float(final(2.0)), float(final(2.3))], atol=1e-12)
