"""Training data for learned Lagrangians: states with accelerations, and sampled trajectories."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray, PyTree

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
    order = jax.random.permutation(key, n)
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
    stride = length - 1
    count = (times - 1) // stride
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
