"""Checks under the user's ``jit``: raise (the default) or NaN and a code (``jl.NaNOnFailure()``).

With ``checks=jl.Checks(compiled=jl.NaNOnFailure())`` a jitted simulation holds no host callback:
a failed run (or one refused by its input checks) returns NaN outputs and a ``jl.FailureCode``
in ``traj.failure.code``, raises nothing, and the jitted function can be exported with
``jax.export`` and serialized. The default, ``jl.RaiseOnFailure()``, still raises from the
compiled program.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl

NAN = jl.Checks(compiled=jl.NaNOnFailure())
TS = jnp.linspace(0.0, 1.0, 11)
SPHERE_ARGS = {"m": 1.0, "g": 9.81, "R": 2.0}


def _pendulum_lagrangian(q, qd, args):
    return 0.5 * qd[0] ** 2 + args["g"] * jnp.cos(q[0])


def _polar_lagrangian(q, qd, args):  # the README's particle on a sphere
    r, th = q
    rd, thd = qd
    return 0.5 * args["m"] * (rd**2 + r**2 * thd**2) - args["m"] * args["g"] * r * jnp.cos(th)


PENDULUM = jl.System(_pendulum_lagrangian)
SPHERE = jl.System(_polar_lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]))
BALL = jl.System(
    lambda q, qd: 0.5 * qd[0] ** 2 - 9.81 * q[0],
    lambda q: q[:1],
    unilateral=jl.Unilateral(0, restitution=0.8),
)


def pendulum(x, checks=NAN, **options):
    """``x = (q0, g)``."""
    q0, g = x
    return jl.simulate(PENDULUM, q0, jnp.zeros(1), TS, args={"g": g}, checks=checks, **options)


def sphere(r, checks=NAN, **options):
    return jl.simulate(
        SPHERE, jnp.stack([r, jnp.asarray(0.3)]), jnp.zeros(2), TS, args=SPHERE_ARGS, checks=checks
    )


def ball(height, checks=NAN):
    return jl.simulate(BALL, height, jnp.zeros(1), TS, events=jl.Events(max_segments=8), checks=checks)


CASES = {
    "pendulum": (pendulum, (jnp.array([0.5]), jnp.asarray(9.81))),
    "sphere": (sphere, jnp.asarray(2.0)),
    "bouncing ball": (ball, jnp.array([1.0])),
}


def _callbacks(fn, x) -> int:
    return len(re.findall(r"callback\[", str(jax.make_jaxpr(jax.jit(fn))(x))))


@pytest.mark.parametrize("name", CASES)
def test_no_host_callback_under_jit(name):
    fn, x = CASES[name]
    assert _callbacks(lambda x: fn(x).q, x) == 0
    # ... and none in its gradient either
    assert _callbacks(jax.grad(lambda x: jnp.sum(fn(x).q)), x) == 0
    # The default compiles its checks as host callbacks (eqx.branched_error_if).
    assert _callbacks(lambda x: fn(x, checks=jl.Checks()).q, x) > 0


def test_gradient_has_no_host_callback_and_equals_the_default():
    q0, g = CASES["pendulum"][1]

    def loss(g, checks):
        return jnp.sum(pendulum((q0, g), checks).q ** 2)

    grad_nan = jax.jit(jax.grad(lambda g: loss(g, NAN)))
    assert len(re.findall(r"callback\[", str(jax.make_jaxpr(grad_nan)(g)))) == 0
    expected = jax.jit(jax.grad(lambda g: loss(g, jl.Checks())))(g)
    np.testing.assert_allclose(grad_nan(g), expected, rtol=1e-12)


def test_failed_run_is_nan_with_its_code():
    run = jax.jit(lambda x: pendulum(x, max_steps=4))
    traj = run(CASES["pendulum"][1])  # no exception
    assert int(traj.failure.code) == jl.FailureCode.MAX_STEPS
    assert bool(jnp.all(jnp.isnan(traj.q))) and bool(jnp.all(jnp.isnan(traj.qd)))
    assert float(traj.failure.t) > 0.0  # the record keeps the numbers
    # Outside jit, the returned record raises with the numbers.
    with pytest.raises(jl.SimulationError, match="max_steps = 4"):
        traj.raise_if_failed()
    # Its derivative is NaN too, not a silent zero.
    grad = jax.jit(jax.grad(lambda g: jnp.sum(pendulum((jnp.array([0.5]), g), max_steps=4).q)))
    assert bool(jnp.isnan(grad(9.81)))


def test_nan_parameter_is_refused_with_its_code():
    traj = jax.jit(pendulum)((jnp.array([0.5]), jnp.asarray(jnp.nan)))
    assert int(traj.failure.code) == jl.FailureCode.PARAMETER
    assert int(traj.failure.index) == 0  # args' only floating-point leaf
    assert bool(jnp.all(jnp.isnan(traj.q)))


def test_initial_state_off_the_manifold_is_refused_with_its_code():
    traj = jax.jit(sphere)(jnp.asarray(2.1))
    assert int(traj.failure.code) == jl.FailureCode.INITIAL_STATE
    assert int(traj.failure.index) == 9  # off the constraint manifold (FailureCode's list)
    assert bool(jnp.all(jnp.isnan(traj.q))) and bool(jnp.all(jnp.isnan(traj.multipliers)))
    np.testing.assert_array_equal(traj.failure.q, [2.1, 0.3])  # the state that was refused
    # Outside jit, the returned record is checked again on the host: the eager message.
    with pytest.raises(jl.SimulationError, match=r"off the constraint manifold.*f\(q0\) = \[0.1\]"):
        traj.raise_if_failed()
    # Under vmap each member fails on its own.
    batch = jax.jit(jax.vmap(sphere))(jnp.array([2.0, 2.1]))
    np.testing.assert_array_equal(
        batch.failure.code, [jl.FailureCode.COMPLETED, jl.FailureCode.INITIAL_STATE]
    )
    assert not bool(jnp.any(jnp.isnan(batch.q[0]))) and bool(jnp.all(jnp.isnan(batch.q[1])))


def test_save_times_and_contact_parameters_are_refused_with_their_codes():
    times = jax.jit(
        lambda ts: jl.simulate(PENDULUM, jnp.array([0.5]), jnp.zeros(1), ts, args={"g": 9.81}, checks=NAN)
    )
    traj = times(TS.at[3].set(0.1))
    assert int(traj.failure.code) == jl.FailureCode.SAVE_TIMES
    assert int(traj.failure.index) == 2 and float(traj.failure.value) == 0.2  # ts[2] > ts[3]
    assert bool(jnp.all(jnp.isnan(traj.q)))
    # A bounce below the floor, and a restitution out of [0, 1] that came in traced.
    below = jax.jit(ball)(jnp.array([-0.5]))
    assert int(below.failure.code) == jl.FailureCode.INITIAL_STATE and bool(jnp.all(jnp.isnan(below.q)))

    def bouncing(e):
        system = jl.System(
            lambda q, qd: 0.5 * qd[0] ** 2 - 9.81 * q[0],
            lambda q: q[:1],
            unilateral=jl.Unilateral(0, restitution=e),
        )
        return jl.simulate(
            system, jnp.array([1.0]), jnp.zeros(1), TS, events=jl.Events(max_segments=8), checks=NAN
        )

    elastic = jax.jit(bouncing)(jnp.asarray(1.5))
    assert int(elastic.failure.code) == jl.FailureCode.RESTITUTION and bool(jnp.all(jnp.isnan(elastic.q)))
    fine = jax.jit(ball)(jnp.array([1.0]))
    assert int(fine.failure.code) == jl.FailureCode.COMPLETED and not bool(jnp.any(jnp.isnan(fine.q)))


def test_simulate_batch_forwards_the_choice():
    run = jax.jit(
        lambda q0: jl.simulate_batch(PENDULUM, q0, jnp.zeros(1), TS, args={"g": 9.81}, checks=NAN, throw=True)
    )
    q0 = jnp.array([[0.5], [jnp.nan]])
    assert len(re.findall(r"callback\[", str(jax.make_jaxpr(run)(q0)))) == 0
    batch = run(q0)
    np.testing.assert_array_equal(
        batch.failure.code, [jl.FailureCode.COMPLETED, jl.FailureCode.INITIAL_STATE]
    )
    assert not bool(jnp.any(jnp.isnan(batch.q[0]))) and bool(jnp.all(jnp.isnan(batch.q[1])))


def test_export_serialize_and_call():
    def f(r, g):
        traj = jl.simulate(
            SPHERE,
            jnp.stack([r, jnp.asarray(0.3)]),
            jnp.zeros(2),
            TS,
            args=dict(SPHERE_ARGS, g=g),
            checks=NAN,
        )
        return traj.q, traj.failure.code

    args = (jnp.asarray(2.0), jnp.asarray(9.81))
    exported = jax.export.export(jax.jit(f))(*args)
    serialized = exported.serialize()
    restored = jax.export.deserialize(serialized)
    q, code = restored.call(*args)
    q_eager, code_eager = f(*args)
    np.testing.assert_array_equal(q, q_eager)
    assert int(code) == int(code_eager) == jl.FailureCode.COMPLETED
    # The refused state gives NaN and its code through the exported program too.
    q_bad, code_bad = restored.call(jnp.asarray(2.1), args[1])
    assert int(code_bad) == jl.FailureCode.INITIAL_STATE and bool(jnp.all(jnp.isnan(q_bad)))


def test_the_default_still_raises_under_jit():
    with pytest.raises(Exception, match="jaxlag: The initial state is off the constraint manifold"):
        jax.block_until_ready(jax.jit(lambda r: sphere(r, checks=jl.Checks()).q)(jnp.asarray(2.1)))
    with pytest.raises(Exception, match="jaxlag: the simulation stopped: max_steps was reached"):
        jax.block_until_ready(
            jax.jit(lambda x: pendulum(x, jl.Checks(), max_steps=4).q)(CASES["pendulum"][1])
        )


def test_eager_calls_raise_with_the_numbers_under_either_choice():
    with pytest.raises(
        ValueError, match=r"off the constraint manifold beyond the tolerance 1e-08: f\(q0\) = \[0.1\]"
    ):
        sphere(jnp.asarray(2.1))
    with pytest.raises(jl.SimulationError, match="reached max_steps = 4"):
        pendulum(CASES["pendulum"][1], max_steps=4)


def test_checks_refuses_another_object():
    with pytest.raises(TypeError, match="jl.RaiseOnFailure"):
        jl.Checks(compiled="nan")  # pyright: ignore[reportArgumentType]
