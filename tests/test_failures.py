"""Issue 16's fault catalogue as regression tests: each case in eager, jit and vmap modes.

Eager calls raise plain Python exceptions (``ValueError`` for bad input, ``TypeError`` for a
wrong call, :class:`jaxlag.SimulationError` for a run that cannot complete); inside ``jit`` /
``vmap`` the compiled program raises a static message that names the same cause (the numbers
stay in the returned object: ``throw=False`` and ``traj.raise_if_failed()`` outside the
transformation give the full message), so those modes match on the cause only.
"""

import subprocess
import sys
import textwrap

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import ellipk

import jaxlag as jl

MODES = ("eager", "jit", "vmap")
TS = jnp.linspace(0.0, 1.0, 11)


def run_in(mode, fn, x):
    """``fn(x)`` eagerly, under ``jax.jit``, or under ``jax.vmap`` over a batch of one."""
    if mode == "eager":
        return jax.block_until_ready(fn(x))
    if mode == "jit":
        return jax.block_until_ready(jax.jit(fn)(x))
    return jax.block_until_ready(jax.vmap(fn)(x[None]))


def raises(mode, eager_type, match, compiled):
    """Eager: the exact exception type and the message with the numbers. Compiled: a runtime
    error with the static message of the cause (``compiled``)."""
    if mode == "eager":
        return pytest.raises(eager_type, match=match)
    return pytest.raises(Exception, match=compiled)


def free_pendulum(q, qd, args):
    return 0.5 * qd[0] ** 2 + args["g"] * jnp.cos(q[0])


def cartesian_lagrangian(q, qd, args):
    return 0.5 * qd @ qd - args["g"] * q[1]


def rod(q, args):
    return jnp.array([q @ q - args["l"] ** 2])


PENDULUM = jl.System(free_pendulum)
CARTESIAN = jl.System(cartesian_lagrangian, holonomic=rod)
POWER = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - q[0] ** 1.5)  # V = q^1.5: NaN for q < 0
SINGULAR = jl.System(lambda q, qd: 0.5 * q[0] ** 2 * qd[0] ** 2)  # M = q², q(t) = √(1 − 2t)


# ----------------------------------------------------------------------------- 1. events
@pytest.mark.parametrize("mode", MODES)
def test_event_on_an_unconstrained_system(mode):
    """A pendulum released at θ0 crosses θ = 0 after a quarter period, K(sin²(θ0/2))/√g."""
    event = [jl.Event(lambda q, qd: q[0])]

    def first_event(g):
        traj = jl.simulate(PENDULUM, jnp.array([0.3]), jnp.zeros(1), TS, args={"g": g}, events=event)
        return traj.events.time[..., 0]

    g = 9.81
    expected = ellipk(np.sin(0.15) ** 2) / np.sqrt(g)
    np.testing.assert_allclose(run_in(mode, first_event, jnp.asarray(g)).reshape(()), expected, rtol=1e-9)
    # d t/d g = −t/(2g) through the event time.
    np.testing.assert_allclose(jax.grad(first_event)(g), -expected / (2 * g), rtol=1e-7)


def test_recorded_event_and_multipliers_keyword_on_an_unconstrained_system():
    """A non-terminal event is logged and the run goes on; `multipliers` is empty (no λ)."""
    event = jl.Event(lambda q, qd, multipliers: q[0] + 0.0 * jnp.sum(multipliers), terminal=False)
    traj = jl.simulate(PENDULUM, jnp.array([0.3]), jnp.zeros(1), TS, args={"g": 9.81}, events=event)
    quarter = ellipk(np.sin(0.15) ** 2) / np.sqrt(9.81)
    assert traj.events.kinds()[:2] == ["user", "end"]
    np.testing.assert_allclose(traj.events.time[0], quarter, rtol=1e-9)
    assert bool(jnp.all(jnp.isfinite(traj.q)))


# ----------------------------------------------------------------------------- 2. non-finite values
@pytest.mark.parametrize("mode", MODES)
def test_nan_parameter_is_named(mode):
    def run(g):
        return jl.simulate(CARTESIAN, jnp.array([1.0, 0.0]), jnp.zeros(2), TS, args={"g": g, "l": 1.0}).q

    with raises(
        mode, ValueError, r"not finite \(NaN or inf\): args\['g'\]", "A parameter in args is not finite"
    ):
        run_in(mode, run, jnp.asarray(jnp.nan))


@pytest.mark.parametrize("mode", MODES)
def test_nan_length_is_a_parameter_error_not_off_manifold(mode):
    def run(l):
        return jl.simulate(CARTESIAN, jnp.array([1.0, 0.0]), jnp.zeros(2), TS, args={"g": 9.81, "l": l}).q

    with raises(mode, ValueError, r"args\['l'\]", "A parameter in args is not finite"):
        run_in(mode, run, jnp.asarray(jnp.nan))


def power_crossing_time():
    """q(0) = 1, q̇(0) = −3 under V = q^1.5: the time at which q reaches 0 (energy E = 5.5)."""
    return quad(lambda q: 1.0 / np.sqrt(2 * (5.5 - q**1.5)), 0.0, 1.0, epsabs=1e-13)[0]


@pytest.mark.parametrize("mode", MODES)
def test_nan_mid_run_is_reported_where_it_happens(mode):
    crossing = np.floor(power_crossing_time() * 1e6) / 1e6  # the digits the message must show

    def run(q0):
        return jl.simulate(POWER, q0, jnp.array([-3.0]), TS).q

    with raises(
        mode,
        jl.SimulationError,
        rf"non-finite \(NaN or inf\) at t = {crossing:.6f}",
        r"equations of motion became non-finite",
    ):
        run_in(mode, run, jnp.array([1.0]))


def test_nan_mid_run_stops_at_once_and_diagnoses():
    traj = jl.simulate(POWER, jnp.array([1.0]), jnp.array([-3.0]), TS, throw=False)
    assert int(traj.failure.code) == 1
    assert int(traj.failure.num_steps) < 300  # not 65,536 rejected steps
    np.testing.assert_allclose(traj.failure.t, power_crossing_time(), atol=1e-9)
    np.testing.assert_allclose(traj.failure.q, 0.0, atol=1e-9)
    saved = np.asarray(traj.t) <= power_crossing_time()
    assert np.all(np.isfinite(traj.q[saved])) and np.all(np.isinf(traj.q[~saved]))
    with pytest.raises(jl.SimulationError, match="one step dt further.*the Lagrangian L is non-fin"):
        traj.raise_if_failed()


def test_nan_with_constant_steps_stops_at_the_first_nan_step():
    traj = jl.simulate(
        POWER,
        jnp.array([1.0]),
        jnp.array([-3.0]),
        TS,
        throw=False,
        stepsize_controller=diffrax.ConstantStepSize(),
        dt0=0.01,
    )
    assert int(traj.failure.code) == 1
    assert 0.3 <= float(traj.failure.t) <= power_crossing_time()
    with pytest.raises(jl.SimulationError, match="non-finite"):
        jl.simulate(
            POWER,
            jnp.array([1.0]),
            jnp.array([-3.0]),
            TS,
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=0.01,
        )


@pytest.mark.parametrize("mode", MODES)
def test_singular_mass_matrix_mid_run(mode):
    """M = q² vanishes at t = 1/2 (q = √(1 − 2t)): the step size collapses there."""

    def run(q0):
        return jl.simulate(SINGULAR, q0, jnp.array([-1.0]), TS).q

    with raises(
        mode,
        jl.SimulationError,
        r"step size collapsed .* at t = 0\.4999999|at t = 0\.5 ",
        r"step size collapsed to round-off",
    ):
        run_in(mode, run, jnp.array([1.0]))


def test_one_failing_batch_member():
    q0s = jnp.array([[1.0], [5.0], [2.0]])
    qd0s = jnp.array([[-3.0], [1.0], [-9.0]])
    with pytest.raises(jl.SimulationError, match=r"2 of 3 batch members failed \(first: member \[0\]\)"):
        jl.simulate_batch(POWER, q0s, qd0s, TS)
    traj = jl.simulate_batch(POWER, q0s, qd0s, TS, throw=False)
    np.testing.assert_array_equal(traj.failure.code, [1, 0, 1])
    # The public enumeration names the codes, also inside jit.
    np.testing.assert_array_equal(traj.failure.code == jl.FailureCode.NONFINITE, [True, False, True])
    completed = jax.jit(lambda f: f.code == jl.FailureCode.COMPLETED)(traj.failure)
    np.testing.assert_array_equal(completed, [False, True, False])
    assert [jl.FailureCode(int(c)).name for c in traj.failure.code] == ["NONFINITE", "COMPLETED", "NONFINITE"]
    assert "equations of motion became non-finite" in jl.FailureCode.NONFINITE.message
    assert jl.FailureCode.COMPLETED.message == ""
    assert np.all(np.isfinite(traj.q[1]))
    alone = jl.simulate(POWER, q0s[1], qd0s[1], TS)
    np.testing.assert_allclose(traj.q[1], alone.q, rtol=0, atol=1e-12)


def test_batch_member_with_a_bad_initial_state_is_named():
    q0s = jnp.array([[1.0, 0.0], [jnp.nan, 0.0], [0.0, -1.0]])
    args = {"g": 9.81, "l": 1.0}
    with pytest.raises(
        ValueError,
        match=r"1 of 3 batch members failed \(first: member \[1\]\).*"
        r"initial state is not finite",
    ):
        jl.simulate_batch(CARTESIAN, q0s, jnp.zeros(2), TS, args=args)


def _falling(q, qd):
    return 0.5 * qd[0] ** 2 - 9.81 * q[0]


def bad_bounce(q, qd):  # q̇ < 0 at the floor: √q̇ is NaN
    return q, jnp.sqrt(qd)


BAD_BOUNCE = jl.Events(jl.Event(lambda q, qd: q[0], terminal=False, direction=False, reset=bad_bounce))


@pytest.mark.parametrize("mode", MODES)
def test_reset_returning_nan_is_named(mode):
    """Before: the next segment started from NaN and the run ended in "max_steps ... stiff or
    singular near this state". Now the segment loop checks the reset's output (FailureCode.RESET),
    and the message names the event and its reset, at the landing √(2h/g)."""

    def run(h):
        return jl.simulate(jl.System(_falling), h, jnp.zeros(1), TS, events=BAD_BOUNCE).q

    landing = np.floor(np.sqrt(2 / 9.81) * 1e6) / 1e6
    with raises(
        mode,
        jl.SimulationError,
        rf"reset of event 0 \(bad_bounce\).*at t = {landing:.6f}.*q̇⁺ = \[nan\]",
        r"the reset of a jl.Event .* returned a non-finite state",
    ):
        run_in(mode, run, jnp.array([1.0]))
    if mode == "jit":
        traj = jax.jit(
            lambda h: jl.simulate(jl.System(_falling), h, jnp.zeros(1), TS, events=BAD_BOUNCE, throw=False)
        )(jnp.array([1.0]))
        assert int(traj.failure.code) == jl.FailureCode.RESET and int(traj.failure.index) == 0
        np.testing.assert_allclose(traj.failure.t, np.sqrt(2 / 9.81), atol=1e-12)
        saved = np.asarray(TS) < np.sqrt(2 / 9.81)  # the saves before the reset are kept
        assert np.all(np.isfinite(traj.q[saved])) and np.all(np.isinf(traj.q[~saved]))


# ----------------------------------------------------------------------------- 3. float32
FLOAT32 = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    import jaxlag as jl
    assert not jax.config.jax_enable_x64
    L = lambda q, qd: 0.5 * (qd @ qd) - 9.81 * q[1]
    s = jl.System(L, holonomic=lambda q: jnp.array([q @ q - 1.0]))
    q0 = jnp.array([jnp.sin(0.3), -jnp.cos(0.3)])
    traj = jl.simulate(s, q0, jnp.zeros(2), jnp.linspace(0, 1, 11))
    assert traj.q.dtype == jnp.float32
    np.save(__import__("sys").argv[1], np.asarray(traj.q))
    q1, qd1 = jl.consistent_initial_state(s, q0 * 1.001, jnp.ones(2))
    try:
        jl.simulate(s, q0 * 1.01, jnp.zeros(2), jnp.linspace(0, 1, 11))
    except ValueError as error:
        print("MESSAGE", error)
""")


def test_float32_runs_constrained_systems(tmp_path):
    """Without x64: the default tolerances follow the dtype (solver 100 ulps = 1.2e-5,
    constraints √ε = 3.5e-4), so the pendulum runs; errors say that x64 is off."""
    out = tmp_path / "q.npy"
    result = subprocess.run(
        [sys.executable, "-c", FLOAT32, str(out)],
        capture_output=True,
        text=True,
        env={"JAX_ENABLE_X64": "0", "PATH": "", "JAX_PLATFORMS": "cpu", "XDG_CACHE_HOME": str(tmp_path)},
        timeout=1800,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "jax_enable_x64 is off" in result.stdout
    q32 = np.load(out)
    x64 = jl.simulate(
        jl.System(lambda q, qd: 0.5 * (qd @ qd) - 9.81 * q[1], holonomic=lambda q: jnp.array([q @ q - 1.0])),
        jnp.array([np.sin(0.3), -np.cos(0.3)]),
        jnp.zeros(2),
        jnp.linspace(0, 1, 11),
    )
    # rtol 1.2e-5 per unit time over ~1 s of a pendulum: ~1e-4 absolute is the float32 budget.
    np.testing.assert_allclose(q32, x64.q, atol=2e-4)
    np.testing.assert_allclose(np.sum(q32**2, axis=1), 1.0, atol=1e-5)  # projected: round-off


# ----------------------------------------------------------------------------- 5. calls
@pytest.mark.parametrize("mode", MODES)
def test_args_missing(mode):
    def run(q0):
        return jl.simulate(CARTESIAN, q0, jnp.zeros(2), TS).q

    with pytest.raises(TypeError, match="declares `args` and failed with args=None"):
        run_in(mode, run, jnp.array([1.0, 0.0]))


@pytest.mark.parametrize("mode", MODES)
def test_repeated_save_times(mode):
    def run(ts):
        return jl.simulate(PENDULUM, jnp.array([0.3]), jnp.zeros(1), ts, args={"g": 9.81}).q

    with raises(
        mode,
        ValueError,
        r"strictly increasing and finite; ts\[1\] = 0.5 is followed by "
        r"ts\[2\] = 0.5",
        r"ts must be strictly increasing and finite",
    ):
        run_in(mode, run, jnp.array([0.0, 0.5, 0.5, 1.0]))


# ----------------------------------------------------------------------------- 6. max_steps
@pytest.mark.parametrize("mode", MODES)
def test_max_steps_says_how_many_are_needed(mode):
    ts = jnp.linspace(0.0, 20.0, 3)
    args = {"g": 9.81, "l": 1.0}

    def run(q0, max_steps=500):
        return jl.simulate(CARTESIAN, q0, jnp.zeros(2), ts, args=args, max_steps=max_steps)

    needed = int(run(jnp.array([1.0, 0.0]), 2**16).stats["num_steps"])
    if mode != "eager":
        # Compiled: the static cause; the record in the returned trajectory has the numbers.
        with pytest.raises(Exception, match="max_steps was reached"):
            run_in(mode, lambda q0: run(q0).q, jnp.array([1.0, 0.0]))
        deferred = run_in(
            mode,
            lambda q0: jl.simulate(CARTESIAN, q0, jnp.zeros(2), ts, args=args, max_steps=500, throw=False),
            jnp.array([1.0, 0.0]),
        )
        run = lambda q0: (deferred.raise_if_failed(), deferred)[1]  # noqa: E731
    estimate = None
    try:
        run_in("eager", lambda q0: run(q0).q, jnp.array([1.0, 0.0]))
    except Exception as error:  # noqa: BLE001 - the message is what is tested
        text = str(error)
        assert "max_steps = 500" in text and "Pass max_steps=" in text
        estimate = int(text.split("about ")[1].split(" steps")[0].replace(",", ""))
    assert estimate is not None
    assert abs(estimate - needed) <= 0.25 * needed  # a rate extrapolation, not an exact count


# ----------------------------------------------------------------------------- 4. compiled errors
def test_compiled_errors_name_the_cause_and_throw_false_keeps_the_numbers():
    run = jax.jit(lambda q0: jl.simulate(POWER, q0, jnp.array([-3.0]), TS, throw=False))
    traj = run(jnp.array([1.0]))
    assert int(traj.failure.code) == 1
    with pytest.raises(jl.SimulationError, match=r"at t = 0\.3135"):
        traj.raise_if_failed()
    # Reverse mode through a run that succeeds is unaffected by the compiled check.
    grad = jax.grad(lambda v: jl.simulate(POWER, jnp.array([1.0]), v, TS[:3]).q[-1, 0])
    assert np.isfinite(grad(jnp.array([-0.1])))[0]
