"""The options of [`fit`][jaxlag.fit] as Modules: the reparameterizations of the parameters
(``θ = to_physical(u)``, the optimizer works on ``u``), `Shooting`, `MultiStart`,
and `FitWarning`."""

import operator
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._custom_types import RealScalarLike
from .._misc import is_concrete

#: ``q`` or ``q̇`` of every shooting segment's starting state, one row per experiment and segment.
SegmentStates = Float[np.ndarray | Array, "experiments segments n"]


# ----------------------------------------------------------------------------- reparameterization
def _numpy_for_known(x) -> Any:
    """NumPy for known values (the starting point, computed on the host: eager ``jax.numpy``
    would compile a program per operation), ``jax.numpy`` for traced ones."""
    return np if is_concrete(x) else jnp


def _as_array(x) -> Any:
    """A NumPy scalar as an array (what NumPy returns for a 0-d input), anything else as it is."""
    return np.asarray(x) if isinstance(x, np.generic) else x


class Identity(eqx.Module):
    """No reparameterization: ``θ = u``."""

    def to_physical(self, u):
        return u

    def to_unconstrained(self, p):
        return p


class Positive(eqx.Module):
    """Positive parameter: ``θ = exp(u)``."""

    def to_physical(self, u: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
        return jnp.exp(u)

    def to_unconstrained(self, p: Float[ArrayLike, "*shape"]) -> Float[Array | np.ndarray, "*shape"]:
        return _as_array(_numpy_for_known(p).log(p))


class Bounded(eqx.Module):
    """Parameter in ``(lower, upper)``: ``θ = lower + (upper − lower) sigmoid(u)``.

    The bounds must be finite with ``lower < upper`` (checked when constructed, also inside
    ``jit``, where Python numbers are known); for ``(0, ∞)`` use `Positive`."""

    lower: RealScalarLike
    upper: RealScalarLike

    def __check_init__(self):
        if not is_concrete((self.lower, self.upper)):
            return  # traced bounds: the caller's to check
        lower, upper = np.asarray(self.lower), np.asarray(self.upper)
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
            raise ValueError(
                f"Bounded(lower={self.lower}, upper={self.upper}): both bounds must be finite; "
                "for a parameter in (0, inf) use jl.Positive()."
            )
        if not np.all(lower < upper):
            swapped = f"; did you mean Bounded({self.upper}, {self.lower})?" if np.all(lower > upper) else "."
            raise ValueError(
                f"Bounded(lower={self.lower}, upper={self.upper}): the lower bound must be below the "
                f"upper bound (an open interval (lower, upper) with lower < upper){swapped}"
            )

    def to_physical(self, u: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
        return jnp.asarray(self.lower + (self.upper - self.lower) * jax.nn.sigmoid(u))

    def to_unconstrained(self, p: Float[ArrayLike, "*shape"]) -> Float[Array | np.ndarray, "*shape"]:
        xp = _numpy_for_known((p, self.lower, self.upper))
        s = (p - self.lower) / (self.upper - self.lower)
        return _as_array(xp.log(s) - xp.log1p(-s))


# ----------------------------------------------------------------------------- options
def _index_tuple(indices) -> tuple:
    return tuple(operator.index(i) for i in indices)  # ints only: a float index is a TypeError


def _state_pair(states):
    return None if states is None else tuple(states)


def _as_starts(starts: dict[str, Any]) -> dict[str, Any]:
    """Lists and numbers as NumPy arrays of JAX's default float type (JAX arrays, traced ones
    included, stay)."""
    real = jax.dtypes.canonicalize_dtype(float)
    return {k: v if isinstance(v, jax.Array) else np.asarray(v, real) for k, v in starts.items()}


class Shooting(eqx.Module):
    """Multiple shooting, the ``shooting=`` option of `fit`.

    - ``segments``: each experiment is split into this many segments (it must divide
      ``len(ts) − 1``; segments share their boundary save times), each starting from its own
      free state. ``1`` (the default) is single shooting.
    - ``continuity_weight``: the weight ``w > 0`` of the continuity residuals
      ``w (x_end(segment k) − x_start(segment k+1))``.
    - ``states``: optional ``(q, qd)`` of shape (E, S, n) each, the starting guesses of the
      segment states (default: a simulation with the starting parameters).
    - ``periodic_coordinates``: indices of angle coordinates whose continuity gaps are taken
      modulo 2π (so segment states may be given in any branch, e.g. from inverse kinematics).
    """

    segments: int = 1
    continuity_weight: RealScalarLike = 10.0
    states: (
        tuple[Float[ArrayLike, "experiments segments n"], Float[ArrayLike, "experiments segments n"]] | None
    ) = eqx.field(default=None, converter=_state_pair)
    periodic_coordinates: tuple[int, ...] = eqx.field(default=(), converter=_index_tuple)

    def __check_init__(self):
        if isinstance(self.segments, bool) or not isinstance(self.segments, (int, np.integer)):
            raise TypeError(f"Shooting(segments=...) must be an int; got {self.segments!r}.")
        if self.segments < 1:
            raise ValueError(
                f"Shooting(segments={self.segments}): the number of shooting segments must be at "
                "least 1 (1 is single shooting)."
            )
        if is_concrete(self.continuity_weight) and not np.all(np.asarray(self.continuity_weight) > 0):
            raise ValueError(
                f"Shooting(continuity_weight={self.continuity_weight}): the weight of the continuity "
                "residuals must be positive."
            )
        if self.states is not None and len(self.states) != 2:
            raise ValueError(
                "Shooting(states=...) must be a pair (q, qd) of arrays of shape (E, S, n): "
                f"got {len(self.states)} items."
            )


class MultiStart(eqx.Module):
    """Several starting points for `fit`: pass ``params=jl.MultiStart({"g": [5.0, 10.0,
    20.0], "l": [0.5, 1.0, 2.0]})``. Every leaf has a leading axis of length K (the number of
    starts; a vector parameter of length n is given as (K, n)). The fits run one after the other
    (they share the compiled programs: only the first compiles); the result is the fit with the
    lowest final loss, with every start's final loss and parameters in
    `FitResult.start_losses` / `FitResult.start_params`. A start whose fit fails
    (diverges or its simulation fails) gets loss ``inf``; only the best fit's warnings are issued.
    """

    starts: dict[str, Float[np.ndarray | Array, " starts *shape"]] = eqx.field(converter=_as_starts)

    def __check_init__(self):
        if not self.starts:
            raise ValueError("MultiStart needs at least one parameter: got an empty dict.")
        sizes = {k: np.shape(v)[0] if np.ndim(v) else None for k, v in self.starts.items()}
        scalar = [k for k, size in sizes.items() if size is None]
        if scalar:
            raise ValueError(
                f"MultiStart needs every parameter with a leading axis, one entry per start; "
                f"{', '.join(scalar)} {'is a scalar' if len(scalar) == 1 else 'are scalars'} (give "
                f"[{scalar[0]}_1, {scalar[0]}_2, ...])."
            )
        if len(set(sizes.values())) != 1:
            counts = ", ".join(f"{k}: {size}" for k, size in sizes.items())
            raise ValueError(
                "MultiStart needs every parameter with the same leading axis (one entry per start); "
                f"got leading sizes {counts}."
            )
        if next(iter(sizes.values())) == 0:
            raise ValueError(
                "MultiStart has zero starting points: every parameter's leading axis has length 0 "
                f"({', '.join(sizes)}); give at least one start."
            )

    @property
    def count(self) -> int:
        """The number of starts K."""
        return int(np.shape(next(iter(self.starts.values())))[0])


class FitWarning(UserWarning):
    """What `fit` warns about: parameters the data cannot determine or that do not affect
    the residuals, a parameter ending at a bound, a fit far worse than the noise. Filter it with
    ``warnings.simplefilter("ignore", jl.FitWarning)``; the same texts are in
    `FitResult.warnings`."""
