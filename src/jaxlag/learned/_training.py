r"""Training learned Lagrangians with optax: one public step function and a small loop around it.

No hidden state: the model, the optimizer state and the data go in, the new model and optimizer
state come out. ``train_step`` is what `train` runs, so a hand-written optax loop is::

    optimizer = optax.adam(1e-3)
    opt_state = optimizer.init(eqx.filter(model, eqx.is_inexact_array))
    step = eqx.filter_jit(jl.learned.train_step)
    for i in range(1000):
        model, opt_state, loss = step(model, opt_state, data, loss_fn, optimizer)
"""

import math
import time
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float, Int, PRNGKeyArray, PyTree

from ._data import batch_size as _rows
from ._data import take
from ._losses import LossValue


def train_step(
    model: PyTree,
    opt_state: PyTree,
    data: PyTree[Array],
    loss: Callable[[PyTree, PyTree[Array]], LossValue],
    optimizer: optax.GradientTransformation,
) -> tuple[PyTree, PyTree, LossValue]:
    r"""One optimizer step on ``loss(model, data).value``; returns ``(model, opt_state, loss_value)``.

    Gradients are taken with ``eqx.filter_value_and_grad`` with respect to the model's
    floating-point arrays (static leaves such as activation functions pass through); the optax
    ``optimizer`` turns them into updates, applied with ``eqx.apply_updates``. The returned
    `LossValue` is the loss *before* the update. Pure: wrap it in ``eqx.filter_jit``, and
    ``jax.vmap`` it (with ``eqx.filter_vmap``) over an ensemble of models.
    """

    def objective(m):
        out = loss(m, data)
        return out.value, out

    (_, value), grads = eqx.filter_value_and_grad(objective, has_aux=True)(model)
    updates, opt_state = optimizer.update(grads, opt_state, eqx.filter(model, eqx.is_inexact_array))
    return eqx.apply_updates(model, updates), opt_state, value


@eqx.filter_jit
def _draw(data, key, batch):
    return take(data, jax.random.choice(key, _rows(data), (batch,), replace=False))


# Module level, so that every call of `train` with the same model structure, loss, optimizer and
# minibatch shapes reuses one compiled step (the data set's size is not part of the program).
_step = eqx.filter_jit(train_step)


@eqx.filter_jit
def _evaluate(model, data, loss):
    return loss(model, data)


class TrainResult(eqx.Module):
    """What `train` returns.

    - ``model``: the model with the best validation loss (the last one without validation data).
    - ``train_loss`` (steps,): the (minibatch) training loss before each step.
    - ``failed`` (steps,): members of each minibatch whose prediction was not finite.
    - ``validation_loss`` (evaluations,) at the steps ``validation_steps``.
    - ``best_step``: the step whose model is returned; ``stopped_early``: patience ran out.
    - ``seconds``: wall-clock time of the loop, compilation included.
    """

    model: PyTree
    train_loss: Float[np.ndarray, " steps"]
    failed: Int[np.ndarray, " steps"]
    validation_loss: Float[np.ndarray, " evaluations"]
    validation_steps: Int[np.ndarray, " evaluations"]
    best_step: int
    stopped_early: bool
    seconds: float


def train(
    model: PyTree,
    loss: Callable[[PyTree, PyTree[Array]], LossValue],
    data: PyTree[Array],
    *,
    optimizer: optax.GradientTransformation = optax.adam(1e-3),
    steps: int = 1000,
    batch_size: int | None = None,
    validation: PyTree[Array] | None = None,
    validate_every: int = 10,
    patience: int | None = None,
    min_improvement: float = 0.0,
    key: PRNGKeyArray | None = None,
    progress: bool = False,
) -> TrainResult:
    r"""Minimize ``loss(model, data).value`` with ``optimizer`` for ``steps`` steps.

    - ``batch_size``: sample this many rows of ``data`` (without replacement) per step, with
      ``key``; ``None`` uses all of ``data`` every step.
    - ``validation``: held-out data (see `split`), scored every ``validate_every`` steps; the
      model with the lowest validation loss is returned.
    - ``patience``: stop when the validation loss has not dropped by more than
      ``min_improvement`` (relative) for ``patience`` evaluations in a row (early stopping).
    - ``progress``: show a ``tqdm`` bar (``pip install tqdm``; imported only then).

    The losses leave failed members out of the value and the gradient; a step in which every
    member fails has no finite gradient and would poison the weights: wrap the optimizer in
    ``optax.apply_if_finite(optimizer, max_consecutive_errors)`` to skip such steps.

    The loop runs `train_step` compiled once (``eqx.filter_jit``): changing ``data`` of the
    same shapes does not recompile.
    """
    if steps < 1:
        raise ValueError(f"train: steps must be at least 1; got {steps}.")
    if validate_every < 1:
        raise ValueError(f"train: validate_every must be at least 1; got {validate_every}.")
    if patience is not None and validation is None:
        raise ValueError("train: early stopping (patience) needs validation data.")
    if batch_size is not None:
        total = _rows(data)
        if not 1 <= batch_size <= total:
            raise ValueError(f"train: batch_size must be in [1, {total}] (rows of data); got {batch_size}.")
        if key is None:
            raise ValueError("train: a batch_size needs a key for drawing the minibatches.")
    if key is None:
        key = jax.random.PRNGKey(0)
    opt_state = optimizer.init(eqx.filter(model, eqx.is_inexact_array))
    iterator = range(steps)
    bar = None
    if progress:
        from tqdm.auto import tqdm  # optional dependency

        bar = tqdm(iterator, total=steps)
        iterator = bar

    start = time.perf_counter()
    train_loss, failed = [], []
    validation_loss, validation_steps = [], []
    best_value, best_model, best_step, bad = math.inf, model, 0, 0
    stopped = False
    keys = jax.random.split(key, steps)
    for i in iterator:
        if validation is not None and i % validate_every == 0:
            value = float(_evaluate(model, validation, loss).value)
            validation_loss.append(value)
            validation_steps.append(i)
            improved = math.isfinite(value) and (
                not math.isfinite(best_value) or value < best_value * (1.0 - min_improvement)
            )
            if improved:
                best_value, best_model, best_step, bad = value, model, i, 0
            else:
                bad += 1
                if patience is not None and bad >= patience:
                    stopped = True
                    break
        batch = data if batch_size is None else _draw(data, keys[i], batch_size)
        model, opt_state, out = _step(model, opt_state, batch, loss, optimizer)
        train_loss.append(out.value)
        failed.append(out.failed)
        if bar is not None and i % 10 == 0:
            bar.set_postfix(loss=float(out.value))
    if bar is not None:
        bar.close()
    if validation is None:
        best_model, best_step = model, len(train_loss)
    elif not stopped:
        value = float(_evaluate(model, validation, loss).value)
        validation_loss.append(value)
        validation_steps.append(len(train_loss))
        if math.isfinite(value) and value < best_value:
            best_model, best_step = model, len(train_loss)
    losses = np.asarray(jnp.stack(train_loss)) if train_loss else np.zeros((0,))
    counts = np.asarray(jnp.stack(failed)) if failed else np.zeros((0,), np.int32)
    return TrainResult(
        best_model,
        losses,
        counts,
        np.asarray(validation_loss),
        np.asarray(validation_steps, dtype=np.int64),
        int(best_step),
        stopped,
        time.perf_counter() - start,
    )
