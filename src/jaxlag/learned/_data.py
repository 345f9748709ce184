"""Training data for learned Lagrangians: states with accelerations, and sampled trajectories.

Both kinds refuse, when built from concrete arrays, values that are not finite (naming the field
and the rows) and `TrajectoryData` times that do not increase: a NaN target would otherwise be
counted as a failed member at every step and learn nothing, silently. Under ``jit`` (tracers) the
checks are left to the losses, which mask such rows as failed members.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray, PyTree

from .._custom_types import Validated


class StateData(eqx.Module):
    r"""Samples ``(q, q̇, q̈)`` of a motion: one state per row (leading ``batch`` axis).

    ``qdd`` are the accelerations of the data, the targets of `AccelerationLoss`, which
    compares them with the model's ``q̈`` from ``M q̈ = F + Q + Jᵀλ``. ``forces`` (optional): the
    known generalized forces ``Q`` acting at each sample (motor torques, a known drive), in the
    coordinates ``q``. They fix the scale of the learned ``L``: from ``(q, q̇, q̈)`` alone ``L``
    and ``c·L`` (any ``c ≠ 0``) have the same motion, so masses are only identifiable relative to
    the potential, unless a known force sets the units.
    """

    # The shapes are checked by __check_init__, with a message.
    q: Validated[Float[Array, "batch n"]]
    qd: Validated[Float[Array, "batch n"]]
    qdd: Validated[Float[Array, "batch n"]]
    forces: Validated[Float[Array, "batch n"] | None] = None

    def __check_init__(self):
        shapes = {jnp.shape(self.q), jnp.shape(self.qd), jnp.shape(self.qdd)}
        if self.forces is not None:
            shapes.add(jnp.shape(self.forces))
        if len(shapes) != 1 or len(jnp.shape(self.q)) != 2:
            raise ValueError(
                "StateData: q, qd, qdd (and forces) must have one shape (batch, n); got "
                f"{jnp.shape(self.q)}, {jnp.shape(self.qd)}, {jnp.shape(self.qdd)}"
                + ("" if self.forces is None else f" and {jnp.shape(self.forces)}")
                + "."
            )
        fields = {"q": self.q, "qd": self.qd, "qdd": self.qdd}
        if self.forces is not None:
            fields["forces"] = self.forces
        check_finite("StateData", fields)


class TrajectoryData(eqx.Module):
    r"""Observed trajectories: ``q(t)`` and ``q̇(t)`` at the times ``ts`` of each member.

    ``ts`` (batch, times) increase along each row; ``q`` and ``qd`` are (batch, times, n).
    """

    # The shapes are checked by __check_init__, with a message.
    ts: Validated[Float[Array, "batch times"]]
    q: Validated[Float[Array, "batch times n"]]
    qd: Validated[Float[Array, "batch times n"]]

    def __check_init__(self):
        b_t = jnp.shape(self.ts)
        if len(b_t) != 2 or jnp.shape(self.q)[:2] != b_t or jnp.shape(self.qd) != jnp.shape(self.q):
            raise ValueError(
                "TrajectoryData: ts must be (batch, times) and q, qd (batch, times, n); got "
                f"{jnp.shape(self.ts)}, {jnp.shape(self.q)} and {jnp.shape(self.qd)}."
            )
        if b_t[1] < 2:
            raise ValueError(f"TrajectoryData: each trajectory needs at least 2 times; got {b_t[1]}.")
        check_finite("TrajectoryData", {"ts": self.ts, "q": self.q, "qd": self.qd})
        check_increasing("TrajectoryData", self.ts)


def _rows_text(rows: np.ndarray, total: int) -> str:
    shown = ", ".join(str(int(r)) for r in rows[:10])
    more = f", … ({len(rows) - 10} more)" if len(rows) > 10 else ""
    return f"{len(rows)} of {total} rows: [{shown}{more}]"


def _is_concrete(x: object) -> bool:
    return x is not None and not isinstance(x, Tracer)


def check_finite(owner: str, fields: dict[str, Any]) -> None:
    """Raise a ValueError naming the first field of ``fields`` with non-finite values and its rows
    (indices along the leading axis). Tracers (under ``jit``) are not checked."""
    for name, x in fields.items():
        if not _is_concrete(x) or not jnp.issubdtype(jnp.result_type(x), jnp.inexact):
            continue
        values = np.asarray(x)
        if values.ndim == 0:
            if not np.isfinite(values):
                raise ValueError(f"{owner}: {name} is not finite ({values}).")
            continue
        if values.shape[0] == 0:
            continue
        bad = ~np.all(np.isfinite(values.reshape(values.shape[0], -1)), axis=1)
        if np.any(bad):
            raise ValueError(
                f"{owner}: {name} is not finite (NaN or ±inf) in "
                f"{_rows_text(np.flatnonzero(bad), values.shape[0])}. Drop or repair those rows, e.g. "
                "keep = np.all(np.isfinite(x), axis=1) for each field x and "
                "jax.tree.map(lambda x: x[keep], data)."
            )


def check_increasing(owner: str, ts: ArrayLike, name: str = "ts") -> None:
    """Raise a ValueError naming the rows of ``ts`` (batch, times) whose times do not increase."""
    if not _is_concrete(ts):
        return
    ts = np.asarray(ts)
    steps = np.diff(ts, axis=1)
    bad = ~np.all(steps > 0, axis=1)
    if np.any(bad):
        rows = np.flatnonzero(bad)
        first = int(rows[0])
        where = int(np.flatnonzero(~(steps[first] > 0))[0])
        raise ValueError(
            f"{owner}: {name} must increase strictly along each trajectory; it does not in "
            f"{_rows_text(rows, ts.shape[0])} (row {first}: {name}[{first}, {where}] = "
            f"{float(ts[first, where])}, {name}[{first}, {where + 1}] = {float(ts[first, where + 1])})."
        )


def check_values(data: PyTree[Array], name: str) -> None:
    """The eager checks of `train` on a data set: at least one row, finite values (and, for
    `TrajectoryData`, increasing times), naming the field and the rows of a failure. Data built
    under ``jit`` or by ``jax.tree.map`` skips the checks of the constructors; this does not."""
    rows = batch_size(data)
    if rows == 0:
        raise ValueError(f"train: {name} has no rows (its leading, batch axis has length 0).")
    leaves = jax.tree_util.tree_leaves_with_path(data)
    check_finite("train", {name + jax.tree_util.keystr(path): x for path, x in leaves})
    if isinstance(data, TrajectoryData):
        check_increasing("train", data.ts, f"{name}.ts")


def finite_rows(*arrays: Array | None) -> Array:
    """``(batch,)``: the rows at which every one of ``arrays`` (leading axis ``batch``) is finite."""
    ok = None
    for x in arrays:
        if x is None:
            continue
        row = jnp.all(jnp.isfinite(x.reshape(x.shape[0], -1)), axis=1)
        ok = row if ok is None else ok & row
    assert ok is not None
    return ok


def batch_size(data: PyTree[Array]) -> int:
    """The length of the leading axis shared by every array of ``data``."""
    sizes = {jnp.shape(x)[0] for x in jax.tree.leaves(data)}
    if len(sizes) != 1:
        raise ValueError(f"The arrays of the data must share their leading (batch) axis; got sizes {sizes}.")
    return sizes.pop()


def take(data: PyTree[Array], index: Int[Array, " k"]) -> PyTree[Array]:
    """Rows ``index`` of every array of ``data`` (a minibatch); works under ``jit``."""
    return jax.tree.map(lambda x: x[index], data)


def split(
    data: PyTree[Array], validation: float = 0.2, *, key: PRNGKeyArray
) -> tuple[PyTree[Array], PyTree[Array]]:
    """Split the rows of ``data`` at random into ``(train, validation)``.

    ``validation`` is the fraction held out (at least one row each side). Split trajectories,
    not the states of one trajectory, to measure generalization to new motions.
    """
    n = batch_size(data)
    if not 0.0 < validation < 1.0:
        raise ValueError(f"split: validation must be a fraction in (0, 1); got {validation}.")
    held = min(max(int(round(validation * n)), 1), n - 1)
    if n < 2:
        raise ValueError(f"split needs at least 2 rows; got {n}.")
    return _split_rows(data, key, held)


@eqx.filter_jit
def _split_rows(data, key, held):
    """`split`'s rows, one program per data structure and sizes (eagerly, each indexing would be
    a program of its own)."""
    order = jax.random.permutation(key, batch_size(data))
    return take(data, order[held:]), take(data, order[:held])


def segments(data: TrajectoryData, length: int) -> TrajectoryData:
    r"""Cut every trajectory into consecutive segments of ``length`` samples (multiple shooting).

    Segment ``k`` holds samples ``k(length − 1) … k(length − 1) + length − 1``: neighbours share
    their boundary sample, so every interval of the data is covered once. A tail shorter than
    ``length`` is dropped. Returns a `TrajectoryData` of ``batch · K`` members.
    """
    times = data.ts.shape[1]
    length = int(length)
    if not 2 <= length <= times:
        raise ValueError(f"segments: length must be in [2, {times}] (samples per trajectory); got {length}.")
    return _cut_segments(data, length)


@eqx.filter_jit
def _cut_segments(data, length):
    """`segments`, one program per data shapes and ``length`` (a static Python int)."""
    stride = length - 1
    count = (data.ts.shape[1] - 1) // stride
    starts = np.arange(count) * stride
    index = starts[:, None] + np.arange(length)[None, :]

    def cut(x):
        out = x[:, index]
        return out.reshape((-1, length) + x.shape[2:])

    return TrajectoryData(cut(data.ts), cut(data.q), cut(data.qd))


def flatten(data: TrajectoryData) -> tuple[Float[Array, "states n"], Float[Array, "states n"]]:
    """All the states ``(q, q̇)`` of ``data``, one per row."""
    n = data.q.shape[-1]
    return data.q.reshape(-1, n), data.qd.reshape(-1, n)
