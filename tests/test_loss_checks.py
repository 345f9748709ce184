"""The losses a user jits (``jl.least_squares_loss``, the losses of ``jaxlag.learned``) hold no host
callback when asked not to: ``jl.least_squares_loss(..., simulation=dict(checks=jl.Checks(
compiled=jl.NaNOnFailure())))`` compiles its checks (the simulation's, and the projection of a
constrained initial state) as NaN, so that the user's program can be cached and exported; the
learned losses are check-free already. Host callbacks are counted in the jaxpr, as in
``tests/test_failure_modes.py``."""

import re
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
from jaxlag import learned as jll

NAN = jl.SimulateOptions(checks=jl.Checks(compiled=jl.NaNOnFailure()))


def _callbacks(fn, *x) -> int:
    return len(re.findall(r"callback\[", str(jax.make_jaxpr(jax.jit(fn))(*x))))


def _pendulum() -> tuple[jl.System, jl.Experiment, dict[str, Any]]:
    system = jl.System(
        lambda q, qd, args: 0.5 * args["l"] ** 2 * qd[0] ** 2 + args["g"] * args["l"] * jnp.cos(q[0])
    )
    ts = jnp.linspace(0.0, 1.0, 11)
    truth = {"g": 9.81, "l": 0.8}
    data = jl.simulate(system, jnp.array([0.5]), jnp.zeros(1), ts, args=truth).q
    return system, jl.Experiment(ts, data, jnp.array([0.5]), jnp.zeros(1)), {"g": 9.0, "l": 1.0}


def _sphere() -> tuple[jl.System, jl.Experiment, dict[str, Any]]:
    def lagrangian(q, qd, args):
        r, th = q
        rd, thd = qd
        return 0.5 * (rd**2 + r**2 * thd**2) - args["g"] * r * jnp.cos(th)

    system = jl.System(lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]))
    ts = jnp.linspace(0.0, 1.0, 11)
    data = jl.simulate(system, jnp.array([2.0, 0.1]), jnp.zeros(2), ts, args={"g": 9.81, "R": 2.0}).q
    return system, jl.Experiment(ts, data, jnp.array([2.0, 0.1]), jnp.zeros(2)), {"g": 9.0, "R": 2.0}


@pytest.mark.parametrize("make", [_pendulum, _sphere], ids=["pendulum", "constrained"])
def test_least_squares_loss_without_host_callbacks(make):
    system, experiment, params = make()

    def loss(p, simulation: jl.SimulateOptions):
        return jl.least_squares_loss(system, p, experiment, simulation=simulation)

    # The default compiles raising checks (host callbacks) into the user's program.
    assert _callbacks(lambda p: loss(p, jl.SimulateOptions()), params) > 0
    # NaN on failure: none, in the value and in the gradient.
    assert _callbacks(lambda p: loss(p, NAN), params) == 0
    assert _callbacks(jax.grad(lambda p: loss(p, NAN)), params) == 0
    # The same loss and gradient where nothing fails; eager calls are unchanged.
    value = jax.jit(lambda p: loss(p, NAN))(params)
    np.testing.assert_allclose(value, loss(params, jl.SimulateOptions()), rtol=1e-12)
    np.testing.assert_allclose(value, loss(params, NAN), rtol=1e-12)
    grads = jax.jit(jax.grad(lambda p: loss(p, NAN)))(params)
    expected = jax.grad(lambda p: loss(p, jl.SimulateOptions()))(params)
    for name in params:
        np.testing.assert_allclose(grads[name], expected[name], rtol=1e-9)


def test_least_squares_loss_nan_for_a_refused_run():
    system, experiment, params = _pendulum()
    loss = jax.jit(lambda p: jl.least_squares_loss(system, p, experiment, simulation=NAN))
    assert np.isnan(loss({**params, "g": jnp.nan}))
    # Eagerly, a NaN parameter raises with either choice.
    with pytest.raises(ValueError):
        jl.least_squares_loss(system, {**params, "g": jnp.nan}, experiment, simulation=NAN)


def test_least_squares_loss_checks_must_be_checks():
    system, experiment, params = _pendulum()
    with pytest.raises(TypeError, match="jl.Checks"):
        wrong: Any = {"checks": jl.NaNOnFailure()}
        jl.least_squares_loss(system, params, experiment, simulation=wrong)
    # jl.fit still checks its data itself and refuses the option.
    with pytest.raises(ValueError, match="checks"):
        jl.fit(system, params, experiment, simulation=NAN)


def test_learned_losses_hold_no_host_callback():
    model = jll.DeLaN(1, 8, 1, key=jax.random.PRNGKey(0))
    weights, static = eqx.partition(model, eqx.is_array)
    q = jnp.linspace(-1.0, 1.0, 8)[:, None]
    states = jll.StateData(q, jnp.linspace(-0.5, 0.5, 8)[:, None], -9.81 * jnp.sin(q))
    ts = jnp.broadcast_to(jnp.linspace(0.0, 0.5, 6), (3, 6))
    trajectories = jll.TrajectoryData(ts, 0.1 * jnp.ones((3, 6, 1)), jnp.zeros((3, 6, 1)))
    cases: list[tuple[Any, Any]] = [
        (jll.AccelerationLoss(), states),
        (jll.RolloutLoss(), trajectories),
        (jll.MultipleShootingLoss(length=3), trajectories),
    ]
    for loss, data in cases:

        def value(w, loss=loss, data=data):
            return loss(eqx.combine(w, static), data).value

        assert _callbacks(value, weights) == 0, type(loss).__name__
        assert _callbacks(jax.grad(value), weights) == 0, type(loss).__name__
