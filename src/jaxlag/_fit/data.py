"""The observed experiments: `Experiment`, their checks and stacking, and the
`Data` the residuals compare against."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._custom_types import Coordinates, RealScalarLike, SaveTimes, Velocities
from .._misc import is_concrete


class Experiment(eqx.Module):
    """One observed run: save times ``ts`` (T,), ``observations`` (T, k), initial state.

    ``q0``, ``qd0`` are the known initial state, or the starting guess when the initial state is
    estimated. NaN entries of ``observations`` are missing data and are masked out. Several
    experiments of equal shapes are passed as a list (stacked and ``vmap``-ed internally).
    """

    ts: SaveTimes
    observations: Float[ArrayLike, "times k"]
    q0: Coordinates
    qd0: Velocities


class Data(eqx.Module):
    """What the residuals ``r = (y_model − y_observed) / σ`` are computed against.

    ``fixed``: the fixed ``args``; ``observations`` (E, T, k), NaN = missing; ``noise``: ``σ``;
    ``ts_seg`` (E, S, m + 1): the save times of each shooting segment; ``continuity_weight``:
    ``w`` of the continuity residuals. Python numbers are static under the fit's ``filter_jit``
    (part of the cache key, as the options are), arrays are traced.
    """

    fixed: dict[str, Any]
    observations: Float[np.ndarray | Array, "experiments times k"]
    noise: RealScalarLike
    ts_seg: Float[np.ndarray | Array, "experiments segments points"]
    continuity_weight: RealScalarLike


def _check_shapes(experiments) -> None:
    for index, e in enumerate(experiments):
        if jnp.shape(e.q0) != jnp.shape(e.qd0) or jnp.ndim(e.q0) != 1:
            raise ValueError(
                f"Experiment {index}: q0 and qd0 must be 1-D of equal length (one entry per "
                f"coordinate); got q0 of shape {jnp.shape(e.q0)} and qd0 of shape {jnp.shape(e.qd0)}."
            )
        if jnp.shape(e.q0) != jnp.shape(experiments[0].q0):
            raise ValueError(
                f"Experiment {index}: q0 has {jnp.shape(e.q0)[0]} entries, but experiment 0's q0 "
                f"has {jnp.shape(experiments[0].q0)[0]} (one per coordinate of the system)."
            )
    shapes = {(jnp.shape(e.ts), jnp.shape(e.observations), jnp.shape(e.q0)) for e in experiments}
    if len(shapes) != 1:
        raise ValueError(
            "All experiments must have the same shapes (ts, observations, q0) to be batched with "
            f"vmap; got {sorted(shapes)}. Pad shorter ones with NaN observations."
        )


def _check_values(index: int, e: Experiment) -> None:
    ts = np.asarray(e.ts)
    bad_ts = np.flatnonzero(~np.isfinite(ts))
    if bad_ts.size:
        raise ValueError(
            f"Experiment {index}: save time ts[{bad_ts[0]}] = {ts[bad_ts[0]]} is not finite; "
            "save times must be finite numbers."
        )
    if ts.ndim != 1 or not np.all(np.diff(ts) > 0):
        raise ValueError("Each experiment's ts must be a strictly increasing 1-D array.")
    if not is_concrete((e.ts, e.observations, e.q0, e.qd0)):
        return
    if np.ndim(e.observations) != 2 or np.shape(e.observations)[0] != ts.shape[0]:
        raise ValueError(
            f"observations must have shape (T, k) with T = len(ts) = {ts.shape[0]}; got "
            f"{np.shape(e.observations)}."
        )
    observations = np.asarray(e.observations)
    infinite = np.argwhere(np.isinf(observations))
    if infinite.size:
        i, k = infinite[0]
        raise ValueError(
            f"Experiment {index}: observations[{i}, {k}] (time index {i}, t = {ts[i]}) is "
            f"{observations[i, k]}. Infinite observations are not data; mark missing values "
            "with NaN (they are masked out)."
        )
    for name, value in (("q0", e.q0), ("qd0", e.qd0)):
        value = np.atleast_1d(np.asarray(value))
        bad = np.flatnonzero(~np.isfinite(value))
        if bad.size:
            raise ValueError(
                f"Experiment {index}: {name}[{bad[0]}] = {value[bad[0]]} is not finite; the "
                "initial state (or its starting guess) must be finite."
            )


def stack(experiments) -> Any:
    """The experiments checked and stacked: an `Experiment` of NumPy arrays with a leading
    axis E (``ts`` (E, T), ``observations`` (E, T, k), ``q0``, ``qd0`` (E, n)), not the
    ``ArrayLike`` fields a user's Experiment declares."""
    if isinstance(experiments, Experiment):
        experiments = [experiments]
    experiments = list(experiments)
    if not experiments:
        raise ValueError("fit needs at least one Experiment.")
    _check_shapes(experiments)
    for index, e in enumerate(experiments):
        _check_values(index, e)
    # Stacked on the host (NumPy, JAX's default float type): the fit's bookkeeping compiles no
    # small device programs; the arrays go to the device as inputs of the compiled programs.
    dtype = jax.dtypes.canonicalize_dtype(float)
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x, dtype) for x in xs]), *experiments)


def segment_grid(ts, segments: int):
    """The save times of each shooting segment, ``ts[:, index]`` with ``index[k] = k m + (0..m)``,
    ``m = (T − 1)/S`` (neighbouring segments share their boundary time), and the index of each
    segment's first save time."""
    t = ts.shape[-1]
    if (t - 1) % segments:
        raise ValueError(
            f"Shooting(segments={segments}): the number of segments must divide len(ts) − 1 = "
            f"{t - 1} (segments share their boundary save times)."
        )
    m = (t - 1) // segments
    index = np.arange(segments)[:, None] * m + np.arange(m + 1)[None, :]
    return np.asarray(ts)[:, index], index[:, 0]


def save_times(ts_seg) -> np.ndarray:
    """The save times (E, T) back from the segments' (E, S, m + 1) of `segment_grid`."""
    ts_seg = np.asarray(ts_seg)
    rest = ts_seg[:, 1:, 1:].reshape(ts_seg.shape[0], -1)
    return np.concatenate([ts_seg[:, 0], rest], axis=1)
