r"""The training recipe of the learned-model benchmark as a library call: `Recipe` and `train_recipe`.

The numbers of the benchmark table (``benchmarks/bench_learned.py``, the cookbook's table) come
from this recipe, and ``bench_learned.py`` calls `train_recipe` itself, so that the table and a
reader following the cookbook run the same code.
"""

import functools
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, Float, PRNGKeyArray, PyTree

from ._data import StateData, TrajectoryData, segments
from ._data import batch_size as _rows
from ._losses import AccelerationLoss, MultipleShootingLoss, RolloutLoss
from ._training import TrainResult, train


class Recipe(eqx.Module):
    r"""How `train_recipe` trains a learned model: the benchmark's recipe, in two phases.

    1. **Accelerations**, ``steps`` steps of [`AccelerationLoss`][jaxlag.learned.AccelerationLoss]
       with the coordinates balanced (`loss`: each weighs alike, and the loss keeps the size of the
       plain mean squared error), on minibatches of ``batch_size`` states drawn
       without replacement (``None``: all of them, in order); adam after clipping the gradient to the
       global norm ``clip``, its learning rate rising linearly from 0 to ``learning_rate`` over
       the first ``warmup`` fraction of the steps, then decaying along a cosine to
       ``final_learning_rate`` at the last step.
    2. **Multiple shooting** (with trajectories, if ``shooting_steps > 0``):
       ``shooting_steps`` steps of [`MultipleShootingLoss`][jaxlag.learned.MultipleShootingLoss] on
       segments of ``segment_length`` samples, the positions balanced alike, on minibatches of
       ``shooting_batch_size`` segments; adam at ``shooting_learning_rate`` after clipping to
       ``shooting_clip``.

    The defaults are the benchmark's: 2000 + 200 steps, peak learning rate 3e-3, minibatches of
    256 states and 100 segments of 5 samples. They are validated when the recipe is built (a
    learning rate must be finite and positive, a step count at least 1).
    """

    steps: int = eqx.field(static=True, default=2000)
    learning_rate: float = eqx.field(static=True, default=3e-3)
    warmup: float = eqx.field(static=True, default=0.05)
    final_learning_rate: float = eqx.field(static=True, default=1e-5)
    clip: float = eqx.field(static=True, default=10.0)
    batch_size: int | None = eqx.field(static=True, default=256)
    shooting_steps: int = eqx.field(static=True, default=200)
    segment_length: int = eqx.field(static=True, default=5)
    shooting_learning_rate: float = eqx.field(static=True, default=3e-4)
    shooting_clip: float = eqx.field(static=True, default=1.0)
    shooting_batch_size: int | None = eqx.field(static=True, default=100)

    def __check_init__(self):
        for name in ("learning_rate", "shooting_learning_rate", "clip", "shooting_clip"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"Recipe: {name} must be finite and positive; got {value}.")
        final = self.final_learning_rate
        if not (math.isfinite(final) and 0 <= final <= self.learning_rate):
            raise ValueError(
                f"Recipe: final_learning_rate must be in [0, learning_rate = {self.learning_rate}]; "
                f"got {self.final_learning_rate}."
            )
        if not 0 <= self.warmup < 1:
            raise ValueError(f"Recipe: warmup is a fraction of the steps in [0, 1); got {self.warmup}.")
        if self.steps < 1:
            raise ValueError(f"Recipe: steps must be at least 1; got {self.steps}.")
        if self.shooting_steps < 0:
            raise ValueError(f"Recipe: shooting_steps must be at least 0; got {self.shooting_steps}.")
        if self.segment_length < 2:
            raise ValueError(f"Recipe: segment_length must be at least 2 samples; got {self.segment_length}.")
        for name in ("batch_size", "shooting_batch_size"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"Recipe: {name} must be at least 1 (or None: all rows); got {value}.")

    def optimizer(self) -> optax.GradientTransformation:
        """The optimizer of the acceleration phase: ``clip_by_global_norm(clip)``, then adam with
        the warm-up and cosine schedule. The same object for equal recipes, so that `train`
        reuses its compiled step."""
        return _acceleration_optimizer(
            self.steps, self.learning_rate, self.warmup, self.final_learning_rate, self.clip
        )

    def shooting_optimizer(self) -> optax.GradientTransformation:
        """The optimizer of the multiple-shooting phase: ``clip_by_global_norm(shooting_clip)``, then
        ``adam(shooting_learning_rate)``."""
        return _shooting_optimizer(self.shooting_learning_rate, self.shooting_clip)

    def loss(self, states: StateData) -> AccelerationLoss:
        r"""``AccelerationLoss(scale=σ / rms(σ))``, ``σᵢ`` the standard deviation of the
        accelerations ``states.qdd`` of coordinate ``i``: the coordinates are balanced (each
        weighs alike) and the loss keeps the size and the units of the plain mean squared error.

        Dividing by ``σ`` itself would also shrink the loss, and its gradient, by ``rms(σ)²``:
        on the Cartesian accelerations of a double pendulum (``rms(σ)`` ≈ 6 m/s²) the gradient
        of a constrained Lagrangian fell from 11 to 0.27 at the first step, below a gradient clip
        at norm 1 that then never acted, and adam left it 1.4–1.6× worse on held-out
        accelerations (θ̈ RMS 0.0063 and 0.0104 against 0.0046 and 0.0067 rad/s², two seeds,
        2000 steps; 2.4–3.4× after 1000; ``benchmarks/RESULTS_learned.md``).
        """
        return AccelerationLoss(scale=balanced_scale(states.qdd))

    def shooting_loss(self, trajectories: TrajectoryData) -> MultipleShootingLoss:
        """``MultipleShootingLoss(segment_length, RolloutLoss(scale=σ / rms(σ)))``, ``σᵢ`` the
        standard deviation of the observed positions of coordinate ``i`` (balanced as in `loss`)."""
        n = trajectories.q.shape[-1]
        return MultipleShootingLoss(
            self.segment_length, RolloutLoss(scale=balanced_scale(trajectories.q.reshape(-1, n)))
        )


@eqx.filter_jit  # one program (eagerly, each of its operations would be one)
def balanced_scale(x: Float[Array, "rows n"]) -> Float[Array, " n"]:
    r"""``σ / rms(σ)``, ``σᵢ`` the standard deviation of column ``i`` of ``x`` (a column that does
    not vary counts as the others' RMS): the ``scale`` of a loss that weighs the coordinates
    alike without changing the loss's overall size (``rms`` of the result: 1)."""
    sigma = jnp.std(x, axis=0)
    varies = sigma > 0
    count = jnp.maximum(jnp.sum(varies), 1).astype(sigma.dtype)
    rms = jnp.sqrt(jnp.sum(jnp.where(varies, sigma**2, 0.0)) / count)
    rms = jnp.where(rms > 0, rms, 1.0)
    return jnp.where(varies, sigma, rms) / rms


@functools.cache
def _acceleration_optimizer(steps, peak, warmup, final, clip):
    warmup_steps = max(int(round(warmup * steps)), 1) if warmup > 0 else 0
    # optax's schedule needs decay_steps > warmup_steps: a single-step recipe is all warm-up.
    decay_steps = max(steps, warmup_steps + 1)
    schedule = optax.warmup_cosine_decay_schedule(0.0, peak, warmup_steps, decay_steps, final)
    return optax.chain(optax.clip_by_global_norm(clip), optax.adam(schedule))


@functools.cache
def _shooting_optimizer(learning_rate, clip):
    return optax.chain(optax.clip_by_global_norm(clip), optax.adam(learning_rate))


class RecipeResult(eqx.Module):
    """What `train_recipe` returns: the trained ``model``, the `TrainResult` of each phase
    (``shooting`` is ``None`` without trajectories or shooting steps) and the wall-clock
    ``seconds`` of both, compilation included."""

    model: PyTree
    acceleration: TrainResult
    shooting: TrainResult | None
    seconds: float


def train_recipe(
    model: PyTree,
    states: StateData,
    trajectories: TrajectoryData | None = None,
    *,
    recipe: Recipe = Recipe(),
    key: PRNGKeyArray,
    progress: bool = False,
) -> RecipeResult:
    r"""Train ``model`` with ``recipe``: accelerations on ``states``, then multiple shooting on
    ``trajectories`` (see `Recipe`); the benchmark table's numbers come from this call.

    ``states``: `StateData` ``(q, q̇, q̈)``, e.g. ``state_data(known_system, trajectories)`` or
    measured accelerations. ``trajectories``: the observed `TrajectoryData` for the second phase
    (``None``: accelerations only). ``key`` draws the minibatches: the first phase with ``key``,
    the second with ``jax.random.fold_in(key, 1)``. Both phases run `train`, with its checks
    (data refused by name, steps with a non-finite gradient skipped and reported).
    """
    if not isinstance(states, StateData):
        raise TypeError(f"train_recipe: states must be a StateData; got {type(states).__name__}.")
    if trajectories is not None and not isinstance(trajectories, TrajectoryData):
        raise TypeError(
            f"train_recipe: trajectories must be a TrajectoryData or None; got {type(trajectories).__name__}."
        )
    start = time.perf_counter()
    first = train(
        model,
        recipe.loss(states),
        states,
        optimizer=recipe.optimizer(),
        steps=recipe.steps,
        batch_size=_batch(recipe.batch_size, _rows(states)),
        key=key,
        progress=progress,
    )
    second = None
    if trajectories is not None and recipe.shooting_steps > 0:
        pieces = segments(trajectories, recipe.segment_length)
        second = train(
            first.model,
            recipe.shooting_loss(trajectories),
            pieces,
            optimizer=recipe.shooting_optimizer(),
            steps=recipe.shooting_steps,
            batch_size=_batch(recipe.shooting_batch_size, _rows(pieces)),
            key=jax.random.fold_in(key, 1),
            progress=progress,
        )
    model = first.model if second is None else second.model
    return RecipeResult(model, first, second, time.perf_counter() - start)


def _batch(size: int | None, rows: int) -> int | None:
    return None if size is None else min(size, rows)
