r"""Training learned Lagrangians with optax: one public step function and a small loop around it.

No hidden state: the model, the optimizer state and the data go in, the new model and optimizer
state come out. ``train_step`` is the step that `train` runs (with a guard around it, below), so a
hand-written optax loop is::

    optimizer = optax.adam(1e-3)
    opt_state = optimizer.init(eqx.filter(model, eqx.is_inexact_array))
    step = eqx.filter_jit(jl.learned.train_step)
    for i in range(1000):
        model, opt_state, loss = step(model, opt_state, data, loss_fn, optimizer)

`train` adds what such a loop needs to be trusted: it refuses data that are empty or not finite
(naming the field and the rows), skips a step whose loss or gradient is not finite (counted in
`TrainResult.skipped`, with a warning), refuses an optimizer whose first update is not finite or
climbs the loss (an infinite, NaN or negative learning rate), and never returns weights that are
not finite.
"""

import math
import time
import warnings
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray, PyTree

from .. import _compile as compilation
from ._data import batch_size as _rows
from ._data import check_values, take
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
    `LossValue` is the loss *before* the update. Pure, and compiled once per model structure,
    loss, optimizer and data shapes (the weights, the optimizer state and the data are inputs of
    the program): an eager call runs one program, and inside your ``eqx.filter_jit`` (or
    ``eqx.filter_vmap`` over an ensemble of models) it is inlined. Pass the same ``loss`` and
    ``optimizer`` at every step: a new ``optax.adam(...)`` or a new ``lambda`` is a new program.
    """
    return _train_step(model, opt_state, data, loss, optimizer)


@compilation.filter_jit(cpu_options=False)
def _train_step(model, opt_state, data, loss, optimizer):
    value, grads, updates, opt_state = _value_and_update(model, opt_state, data, loss, optimizer)
    return eqx.apply_updates(model, updates), opt_state, value


def _value_and_update(model, opt_state, data, loss, optimizer):
    def objective(m):
        out = loss(m, data)
        return out.value, out

    (_, value), grads = eqx.filter_value_and_grad(objective, has_aux=True)(model)
    updates, opt_state = optimizer.update(grads, opt_state, eqx.filter(model, eqx.is_inexact_array))
    return value, grads, updates, opt_state


def _all_finite(tree) -> Array:
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree) if eqx.is_inexact_array(x)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


#: Why `train` skipped a step (`_guarded_step`'s code; 0: the step was taken).
_REASONS = {
    1: "no member of the batch gave a finite loss",
    2: "the gradient was not finite",
    3: "the gradient was finite but the optimizer's update was not",
}


def _guarded_step(model, opt_state, data, loss, optimizer):
    """`train_step`, taken only where the loss value, the gradient, the update and the new
    optimizer state are all finite; otherwise the model and the optimizer state stay as they were.
    Also returns the step's code (0, or a key of ``_REASONS``) and ``update · gradient``."""
    value, grads, updates, new_state = _value_and_update(model, opt_state, data, loss, optimizer)
    grads_ok = _all_finite(grads)
    update_ok = _all_finite(updates) & _all_finite(new_state)
    code = jnp.where(update_ok, jnp.int32(0), jnp.int32(3))
    code = jnp.where(grads_ok, code, jnp.int32(2))
    code = jnp.where(jnp.isfinite(value.value), code, jnp.int32(1))
    keep = code == 0
    new_model = eqx.apply_updates(model, updates)
    params, static = eqx.partition(model, eqx.is_inexact_array)
    new_params = eqx.filter(new_model, eqx.is_inexact_array)
    params = jax.tree.map(lambda new, old: jnp.where(keep, new, old), new_params, params)
    opt_state = jax.tree.map(
        lambda new, old: jnp.where(keep, new, old) if eqx.is_array(new) else new, new_state, opt_state
    )
    dtype = jnp.result_type(float)
    descent = sum(
        (jnp.vdot(u, g).astype(dtype) for u, g in zip(jax.tree.leaves(updates), jax.tree.leaves(grads))),
        jnp.zeros((), dtype),
    )
    return eqx.combine(params, static), opt_state, value, code, descent


@eqx.filter_jit
def _draw(data, key, batch):
    return take(data, jax.random.choice(key, _rows(data), (batch,), replace=False))


# Module level, so that every call of `train` with the same model structure, loss, optimizer and
# minibatch shapes reuses one compiled step (the data set's size is not part of the program).
_step = eqx.filter_jit(_guarded_step)


@eqx.filter_jit
def _init_state(optimizer, params):
    """``optimizer.init(params)`` as one program (eagerly, one per leaf of the state)."""
    return optimizer.init(params)


@eqx.filter_jit
def _split_keys(key, steps):
    return jax.random.split(key, steps)


@eqx.filter_jit
def _evaluate(model, data, loss):
    return loss(model, data)


class TrainResult(eqx.Module):
    """What `train` returns.

    - ``model``: the model with the best validation loss (the last one without validation data,
      or, with a warning, when the validation loss was never finite).
    - ``train_loss`` (steps,): the (minibatch) training loss before each step.
    - ``failed`` (steps,): members of each minibatch whose prediction was not finite.
    - ``skipped`` (steps,): steps not taken because their loss value or gradient (or the
      optimizer's update) was not finite; the model and the optimizer state were left as they were.
    - ``validation_loss`` (evaluations,) at the steps ``validation_steps``.
    - ``best_step``: the step whose model is returned; ``stopped_early``: patience ran out.
    - ``seconds``: wall-clock time of the loop, compilation included.
    """

    model: PyTree
    train_loss: Float[np.ndarray, " steps"]
    failed: Int[np.ndarray, " steps"]
    skipped: Bool[np.ndarray, " steps"]
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

    What it refuses, and what it does with a step that goes wrong:

    - ``data`` (and ``validation``) with no rows, with values that are not finite (the error names
      the field and the rows: a NaN target would otherwise fail its member at every step, and
      learn nothing, without a word), or with `TrajectoryData` times that do not increase; a
      model whose weights are not finite.
    - A step whose loss value is not finite (every member of the batch failed) or whose gradient
      is not finite is **skipped**: the model and the optimizer state stay as they were. The
      losses leave failed members out of the value and the gradient, so this is rare; such steps
      are marked in ``TrainResult.skipped`` and reported by a ``RuntimeWarning`` after the loop.
      If every step is skipped, ``train`` raises a ``RuntimeError`` instead of returning the
      untrained model. The returned model's weights are always finite.
    - An optimizer whose first update is not finite for a finite gradient (an infinite or NaN
      learning rate) or climbs the loss (``update · gradient > 0``: a negative learning rate),
      at step 0; one that leaves the weights unchanged through every step (a learning rate of
      0), at the end: ``ValueError``. Later steps whose update is not finite are skipped as above.

    The loop runs `train_step` compiled once (``eqx.filter_jit``), with the check and the skip
    of the step in the same program: changing ``data`` of the same shapes does not recompile.
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
    check_values(data, "data")
    if validation is not None:
        check_values(validation, "validation")
    initial = eqx.filter(model, eqx.is_inexact_array)
    for path, x in jax.tree_util.tree_leaves_with_path(initial):
        if not np.all(np.isfinite(np.asarray(x))):
            raise ValueError(f"train: the model's weights model{jax.tree_util.keystr(path)} are not finite.")
    if key is None:
        key = jax.random.PRNGKey(0)
    opt_state = _init_state(optimizer, initial)
    iterator = range(steps)
    bar = None
    if progress:
        from tqdm.auto import tqdm  # optional dependency

        bar = tqdm(iterator, total=steps)
        iterator = bar

    start = time.perf_counter()
    train_loss, failed, codes = [], [], []
    validation_loss, validation_steps = [], []
    best_value, best_model, best_step, bad = math.inf, model, 0, 0
    stopped = False
    keys = None if batch_size is None else _split_keys(key, steps)
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
        batch = data if keys is None else _draw(data, keys[i], batch_size)
        model, opt_state, out, code, descent = _step(model, opt_state, batch, loss, optimizer)
        if i == 0:
            _check_first_step(int(code), float(descent))
        train_loss.append(out.value)
        failed.append(out.failed)
        codes.append(code)
        if bar is not None and i % 10 == 0:
            bar.set_postfix(loss=float(out.value))
    if bar is not None:
        bar.close()
    skipped = np.asarray(jax.device_get(codes)) if codes else np.zeros((0,), np.int32)
    _report_skipped(skipped)
    if codes and not np.any(skipped) and _unchanged(initial, eqx.filter(model, eqx.is_inexact_array)):
        raise ValueError(
            f"train: the weights did not change in {len(codes)} steps: a learning rate of 0 (at "
            "every step of its schedule), or a loss that does not depend on the weights?"
        )
    if validation is None:
        best_model, best_step = model, len(train_loss)
    elif not stopped:
        value = float(_evaluate(model, validation, loss).value)
        validation_loss.append(value)
        validation_steps.append(len(train_loss))
        if math.isfinite(value) and value < best_value:
            best_model, best_step = model, len(train_loss)
    if validation is not None and not any(math.isfinite(v) for v in validation_loss):
        warnings.warn(
            "train: the validation loss was not finite at any evaluation (every validation member "
            "failed); the last model is returned, not a best one.",
            RuntimeWarning,
            stacklevel=2,
        )
        best_model, best_step = model, len(train_loss)
    # One transfer of the per-step scalars (a jnp.stack would compile a program per step count).
    losses = np.asarray(jax.device_get(train_loss)) if train_loss else np.zeros((0,))
    counts = np.asarray(jax.device_get(failed)) if failed else np.zeros((0,), np.int32)
    return TrainResult(
        best_model,
        losses,
        counts,
        skipped != 0,
        np.asarray(validation_loss),
        np.asarray(validation_steps, dtype=np.int64),
        int(best_step),
        stopped,
        time.perf_counter() - start,
    )


def _check_first_step(code: int, descent: float) -> None:
    if code == 3:
        raise ValueError(
            "train: at step 0 the gradient is finite but the optimizer's update is not: is the "
            "optimizer's learning rate infinite or NaN?"
        )
    if code == 0 and descent > 0:
        raise ValueError(
            f"train: the optimizer's first update climbs the loss (update · gradient = {descent:.3g} "
            "> 0): is the optimizer's learning rate negative?"
        )


def _report_skipped(codes: np.ndarray) -> None:
    """Raise if every step was skipped; warn if some were."""
    bad = np.flatnonzero(codes)
    if bad.size == 0:
        return
    reasons = "; ".join(
        f"{reason}: {int(np.sum(codes == c))}" for c, reason in _REASONS.items() if np.any(codes == c)
    )
    first = int(bad[0])
    text = (
        f"{bad.size} of {codes.size} steps were skipped ({reasons}; the first at step {first}: "
        f"{_REASONS[int(codes[first])]})"
    )
    if bad.size == codes.size:
        raise RuntimeError(
            f"train: {text}, so the model was never updated. A loss that fails at every member "
            "(an LNN whose learned M is indefinite at every state, data of other units) or a "
            "gradient that overflows; TrainResult.failed counts the failed members."
        )
    warnings.warn(
        f"train: {text}; the model and the optimizer state were left as they were at those steps "
        "(TrainResult.skipped marks them).",
        RuntimeWarning,
        stacklevel=3,
    )


def _unchanged(before: PyTree, after: PyTree) -> bool:
    return all(
        np.array_equal(np.asarray(a), np.asarray(b))
        for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(after))
    )
