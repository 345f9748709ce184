"""jaxlag.learned: wrong answers and silent failures that are refused by name, with the fix at the cause.

Each test reproduces a reported case first: NaN rows in the data (a NaN gradient, every weight NaN
after one step, returned silently), empty data and bad learning rates accepted, decreasing times,
a model of the wrong size (a raw ``dot_general`` error), ``state_data`` with its arguments swapped
(a raw ``AttributeError``), and the recipe behind the benchmark table as a library call.
"""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jaxlag as jl
from jaxlag import learned as jll

KEY = jax.random.PRNGKey(0)

# optax's adam and its schedules mix int32 step counts with floats: the tests that run them use
# JAX's standard dtype promotion (as users' scripts do), not the suite's strict one.
standard_promotion = jax.numpy_dtype_promotion("standard")


def _pendulum_states(count=64, seed=0):
    """States of the ready double pendulum with its accelerations (θ, θ̇ ~ U(−1, 1))."""
    truth = jl.systems.double_pendulum()
    kq, kv = jax.random.split(jax.random.PRNGKey(seed))
    q = jax.random.uniform(kq, (count, 2), minval=-1.0, maxval=1.0)
    qd = jax.random.uniform(kv, (count, 2), minval=-1.0, maxval=1.0)
    qdd = jax.vmap(lambda a, b: jll.accelerations(truth, a, b))(q, qd)
    return q, qd, qdd


def _finite(tree):
    return all(
        np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(eqx.filter(tree, eqx.is_inexact_array))
    )


def _with_nan_rows(data, field, rows):
    """``data`` with NaN in ``rows`` of ``field``, built around the constructor's check (as data
    built under ``jit`` or by ``jax.tree.map`` is)."""
    return eqx.tree_at(lambda d: getattr(d, field), data, getattr(data, field).at[rows].set(jnp.nan))


# ---------------------------------------------------------------------------- case 1: NaN rows
def test_nan_rows_are_refused_by_name_when_the_data_are_built():
    q, qd, qdd = _pendulum_states()
    with pytest.raises(ValueError, match=r"StateData: qdd is not finite .* 2 of 64 rows: \[3, 10\]"):
        jll.StateData(q, qd, qdd.at[3].set(jnp.nan).at[10, 1].set(jnp.inf))
    with pytest.raises(ValueError, match=r"StateData: q is not finite .* 1 of 64 rows: \[7\]"):
        jll.StateData(q.at[7, 0].set(jnp.nan), qd, qdd)
    with pytest.raises(ValueError, match=r"StateData: forces is not finite .* \[0\]"):
        jll.StateData(q, qd, qdd, forces=jnp.zeros_like(q).at[0].set(jnp.nan))
    ts = jnp.broadcast_to(jnp.linspace(0.0, 1.0, 5), (3, 5))
    with pytest.raises(ValueError, match=r"TrajectoryData: qd is not finite .* 1 of 3 rows: \[2\]"):
        jll.TrajectoryData(ts, jnp.zeros((3, 5, 2)), jnp.zeros((3, 5, 2)).at[2, 4, 0].set(jnp.nan))


def test_train_refuses_nan_rows_that_bypassed_the_constructor():
    # Before: train ran, counted the NaN rows as failed members, and the gradient was NaN (the
    # masked mean's `where` dropped their value, not the 0 · NaN of their backward pass): after
    # one step every weight was NaN, returned with loss inf, 64/64 failed and no error.
    q, qd, qdd = _pendulum_states()
    data = _with_nan_rows(jll.StateData(q, qd, qdd), "qdd", jnp.array([3, 10]))
    model = jll.DeLaN(2, 16, 2, key=KEY)
    with pytest.raises(ValueError, match=r"train: data\.qdd is not finite .* 2 of 64 rows: \[3, 10\]"):
        jll.train(model, jll.AccelerationLoss(), data, steps=3)
    good = jll.StateData(q, qd, qdd)
    with pytest.raises(ValueError, match=r"train: validation\.q is not finite .* \[0\]"):
        jll.train(model, jll.AccelerationLoss(), good, steps=3, validation=_with_nan_rows(good, "q", 0))


@pytest.mark.parametrize("field", ["qdd", "q"])
def test_nan_rows_leave_the_value_and_the_gradient_of_the_others(field):
    # The losses mask the inputs of the computation, not only its output (the double `where`):
    # with NaN targets or NaN states in rows 3 and 10, the value and the gradient are those of the
    # other 62 rows, to round-off, and the two rows are counted as failed.
    q, qd, qdd = _pendulum_states()
    data = jll.StateData(q, qd, qdd)
    rows = jnp.array([3, 10])
    broken = _with_nan_rows(data, field, rows)
    keep = np.setdiff1d(np.arange(64), np.asarray(rows))
    clean = jll.StateData(q[keep], qd[keep], qdd[keep])
    model = jll.DeLaN(2, 16, 2, key=KEY, embedding=jll.AngleEmbedding((0, 1)))
    loss = jll.AccelerationLoss(scale=jnp.std(qdd, axis=0))

    @eqx.filter_jit
    def value_and_grad(m, d):
        return eqx.filter_value_and_grad(lambda m: loss(m, d).value)(m), loss(m, d).failed

    (value, grads), failed = value_and_grad(model, broken)
    (value_clean, grads_clean), failed_clean = value_and_grad(model, clean)
    assert int(failed) == 2 and int(failed_clean) == 0
    assert _finite(grads)
    np.testing.assert_allclose(value, value_clean, rtol=1e-13)
    for g, g_clean in zip(jax.tree.leaves(grads), jax.tree.leaves(grads_clean)):
        # The same sums over the same 62 rows; the masked rows add exact zeros.
        np.testing.assert_allclose(g, g_clean, rtol=1e-11, atol=1e-14)


def test_rollout_loss_leaves_out_members_whose_data_are_not_finite():
    ts = jnp.linspace(0.0, 1.0, 11)
    q0 = jnp.array([[0.5], [1.0], [-0.7]])
    truth = jl.simulate_batch(jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2), q0, 0.0 * q0, ts)
    data = jll.TrajectoryData(jnp.broadcast_to(ts, (3, 11)), truth.q, truth.qd)
    broken = eqx.tree_at(lambda d: d.q, data, data.q.at[1, 6, 0].set(jnp.nan))
    model = jll.DeLaN(1, 4, 1, key=KEY)
    loss = jll.RolloutLoss()
    grad = eqx.filter_jit(eqx.filter_value_and_grad(lambda m, d: loss(m, d).value))
    value, g = grad(model, broken)
    value_two, g_two = grad(model, jax.tree.map(lambda x: x[jnp.array([0, 2])], data))
    assert int(loss(model, broken).failed) == 1 and _finite(g)
    np.testing.assert_allclose(value, value_two, rtol=1e-13)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_two)):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-14)


# ---------------------------------------------------------------------------- steps that fail
class _Scalar(eqx.Module):
    w: jax.Array


def _kinked(model, data):
    """``mean((w − d)²)`` plus a term that is 0 with a NaN gradient once ``w > 0.5`` (``|·|`` at 0)."""
    kink = jnp.linalg.norm(jnp.where(model.w > 0.5, 0.0 * model.w, 0.0) * jnp.ones(2))
    return jll.LossValue(jnp.mean((model.w - data) ** 2) + kink, jnp.zeros((), jnp.int32))


def test_a_step_with_a_non_finite_gradient_is_skipped_counted_and_reported():
    # sgd(0.1) pulls w from 0 towards 1: 0.2, 0.36, 0.488, 0.59; there the gradient is NaN. The step
    # is skipped (w stays finite), every later one too, and train says so.
    with pytest.warns(
        RuntimeWarning,
        match=r"6 of 10 steps were skipped \(the gradient was not finite: 6; the first at step 4",
    ):
        result = jll.train(
            _Scalar(jnp.zeros(())), _kinked, jnp.ones((4,)), optimizer=optax.sgd(0.1), steps=10
        )
    np.testing.assert_array_equal(result.skipped, [False] * 4 + [True] * 6)
    np.testing.assert_allclose(float(result.model.w), 0.5904, rtol=1e-12)
    assert np.all(np.isfinite(result.train_loss))


def test_every_step_skipped_raises_instead_of_returning_the_untrained_model():
    def never(model, data):
        return jll.LossValue(jnp.nan * model.w, jnp.ones((), jnp.int32))

    with pytest.raises(
        RuntimeError, match=r"5 of 5 steps were skipped .*no member of the batch gave a finite loss"
    ):
        jll.train(_Scalar(jnp.zeros(())), never, jnp.ones((4,)), optimizer=optax.sgd(0.1), steps=5)


def _quadratic(model, data):
    return jll.LossValue(jnp.mean((model.w - data) ** 2), jnp.zeros((), jnp.int32))


def test_a_validation_loss_that_is_never_finite_returns_the_last_model_with_a_warning():
    # Before: the "best" model was the initial one (no finite validation loss beat inf), returned
    # with best_step 0 and no word.
    def loss(model, data):
        value = jnp.mean((model.w - data) ** 2)
        return jll.LossValue(jnp.where(data[0] > 1.5, jnp.inf, value), jnp.zeros((), jnp.int32))

    with pytest.warns(RuntimeWarning, match="validation loss was not finite at any evaluation"):
        result = jll.train(
            _Scalar(jnp.zeros(())),
            loss,
            jnp.ones((4,)),
            optimizer=optax.sgd(0.1),
            steps=6,
            validation=jnp.full((4,), 2.0),
            validate_every=2,
        )
    assert result.best_step == 6 and float(result.model.w) > 0.5


# ---------------------------------------------------------------------------- case 2: refused inputs
def test_train_refuses_empty_data_bad_learning_rates_and_a_nan_model():
    model, data = _Scalar(jnp.zeros(())), jnp.ones((4,))
    with pytest.raises(ValueError, match="train: data has no rows"):
        jll.train(model, _quadratic, jnp.ones((0,)), steps=3)
    q, qd, qdd = _pendulum_states(4)
    with pytest.raises(ValueError, match="train: data has no rows"):
        jll.train(jll.DeLaN(2, 4, 1, key=KEY), jll.AccelerationLoss(), jll.StateData(q[:0], qd[:0], qdd[:0]))
    with pytest.raises(ValueError, match="train: validation has no rows"):
        jll.train(model, _quadratic, data, steps=3, validation=jnp.ones((0,)))
    # Before: an infinite or NaN learning rate made every weight NaN after one step, returned
    # silently (loss inf); a negative one climbed the loss; a zero one returned the initial model.
    with standard_promotion:
        for rate in (jnp.inf, jnp.nan):
            with pytest.raises(
                ValueError, match="step 0 the gradient is finite but the optimizer's update is not"
            ):
                jll.train(model, _quadratic, data, optimizer=optax.adam(rate), steps=3)
        with pytest.raises(ValueError, match="first update climbs the loss .* learning rate negative"):
            jll.train(model, _quadratic, data, optimizer=optax.adam(-1e-3), steps=3)
    with pytest.raises(ValueError, match="weights did not change in 3 steps: a learning rate of 0"):
        jll.train(model, _quadratic, data, optimizer=optax.sgd(0.0), steps=3)
    with pytest.raises(ValueError, match=r"weights model\.w are not finite"):
        jll.train(_Scalar(jnp.array(jnp.nan)), _quadratic, data, steps=3)
    for rate in (float("inf"), float("nan"), 0.0, -1e-3):
        with pytest.raises(ValueError, match="Recipe: learning_rate must be finite and positive"):
            jll.Recipe(learning_rate=rate)
    with pytest.raises(ValueError, match="Recipe: shooting_learning_rate must be finite and positive"):
        jll.Recipe(shooting_learning_rate=-1.0)


def test_decreasing_times_are_refused():
    ts = jnp.broadcast_to(jnp.linspace(0.0, 1.0, 5), (3, 5)).at[1].set(jnp.linspace(1.0, 0.0, 5))
    with pytest.raises(
        ValueError, match=r"ts must increase strictly .* 1 of 3 rows: \[1\] \(row 1: ts\[1, 0\] = 1\.0"
    ):
        jll.TrajectoryData(ts, jnp.zeros((3, 5, 1)), jnp.zeros((3, 5, 1)))
    with pytest.raises(ValueError, match=r"ts must increase"):  # a repeated time
        jll.TrajectoryData(jnp.array([[0.0, 0.5, 0.5]]), jnp.zeros((1, 3, 1)), jnp.zeros((1, 3, 1)))
    good = jll.TrajectoryData(
        jnp.broadcast_to(jnp.linspace(0.0, 1.0, 5), (3, 5)), jnp.zeros((3, 5, 1)), jnp.zeros((3, 5, 1))
    )
    bad = eqx.tree_at(lambda d: d.ts, good, ts)
    with pytest.raises(ValueError, match=r"train: data\.ts must increase"):
        jll.train(jll.DeLaN(1, 4, 1, key=KEY), jll.RolloutLoss(), bad, steps=1)


# ---------------------------------------------------------------------------- case 3: sizes
def test_a_model_of_the_wrong_size_names_both_sizes():
    # Before: TypeError "dot_general requires contracting dimensions to have the same shape".
    q, qd, qdd = _pendulum_states(8)
    data = jll.StateData(q, qd, qdd)
    models = {
        "DeLaN": jll.DeLaN(3, 8, 1, key=KEY),
        "MLPLagrangian": jll.MLPLagrangian(3, 8, 1, key=KEY, embedding=jll.AngleEmbedding((0, 2))),
        "ConstrainedLagrangian": jll.ConstrainedLagrangian(3, 1, lambda x: x[:1], 8, 1, key=KEY),
    }
    for name, model in models.items():
        assert model.n == 3
        with pytest.raises(
            ValueError, match=rf"{name}: the model has n = 3 coordinates, but .* q of shape \(2,\)"
        ):
            jll.train(model, jll.AccelerationLoss(), data, steps=1)


# ---------------------------------------------------------------------------- case 4: argument order
def test_state_data_with_swapped_arguments_says_the_order():
    truth = jl.systems.double_pendulum()
    ts = jnp.linspace(0.0, 0.2, 3)
    data = jll.TrajectoryData(jnp.broadcast_to(ts, (1, 3)), jnp.zeros((1, 3, 2)), jnp.zeros((1, 3, 2)))
    assert jll.state_data(truth, data).qdd.shape == (3, 2)
    # The suite's run-time type checker refuses the swapped call before the function runs (a
    # TypeError too); users run the function itself, whose own check names the order.
    unchecked = getattr(jll.state_data, "__wrapped__", jll.state_data)
    with pytest.raises(
        TypeError, match=r"model .* first and the TrajectoryData second; got \(TrajectoryData, System\): swap"
    ):
        unchecked(data, truth)
    with pytest.raises(TypeError):
        jll.state_data(data, truth)  # pyright: ignore[reportArgumentType]


# ---------------------------------------------------------------------------- case 5: the recipe
def test_recipe_is_the_benchmark_schedule_and_train_recipe_runs_both_phases():
    recipe = jll.Recipe()
    assert (recipe.steps, recipe.learning_rate, recipe.clip, recipe.batch_size) == (2000, 3e-3, 10.0, 256)
    assert recipe.optimizer() is jll.Recipe().optimizer()  # one compiled step for equal recipes
    short = jll.Recipe(steps=40, shooting_steps=3, batch_size=32, shooting_batch_size=8)
    truth = jl.systems.double_pendulum()
    ts = jnp.linspace(0.0, 0.5, 11)
    k1, k2 = jax.random.split(KEY)
    q0 = jax.random.uniform(k1, (4, 2), minval=-1.0, maxval=1.0)
    qd0 = jax.random.uniform(k2, (4, 2), minval=-1.0, maxval=1.0)
    traj = jl.simulate_batch(truth, q0, qd0, ts)
    trajectories = jll.TrajectoryData(jnp.broadcast_to(ts, (4, 11)), traj.q, traj.qd)
    states = jll.state_data(truth, trajectories)
    model = jll.DeLaN(2, 8, 1, key=KEY, embedding=jll.AngleEmbedding((0, 1)))
    with standard_promotion:
        result = jll.train_recipe(model, states, trajectories, recipe=short, key=KEY)
        only = jll.train_recipe(model, states, recipe=short, key=KEY)
        # The same first phase by hand: train with the recipe's loss and optimizer and the same key.
        by_hand = jll.train(
            model, short.loss(states), states, optimizer=short.optimizer(), steps=40, batch_size=32, key=KEY
        )
    assert result.acceleration.train_loss.shape == (40,) and result.shooting is not None
    assert result.shooting.train_loss.shape == (3,)
    assert np.mean(result.acceleration.train_loss[-5:]) < np.mean(result.acceleration.train_loss[:5])
    assert _finite(result.model)
    assert only.shooting is None
    # The loss's scale balances the coordinates (σ / rms σ) and keeps the loss's size: its RMS is 1.
    scale = np.asarray(short.loss(states).scale)
    sigma = np.std(np.asarray(states.qdd), axis=0)
    np.testing.assert_allclose(scale, sigma / np.sqrt(np.mean(sigma**2)), rtol=1e-12)
    np.testing.assert_allclose(np.sqrt(np.mean(scale**2)), 1.0, rtol=1e-12)
    np.testing.assert_array_equal(by_hand.train_loss, only.acceleration.train_loss)


def test_train_keeps_working_without_warnings_on_good_data():
    q, qd, qdd = _pendulum_states(32)
    data = jll.StateData(q, qd, qdd)
    with warnings.catch_warnings(), standard_promotion:
        warnings.simplefilter("error")
        result = jll.train(jll.DeLaN(2, 8, 1, key=KEY), jll.AccelerationLoss(), data, steps=5)
    assert not result.skipped.any() and result.skipped.shape == (5,)
