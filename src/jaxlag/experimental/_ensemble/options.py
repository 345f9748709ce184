"""The options of [`simulate`][jaxlag.simulate] that the ensemble integrator supports, written once.

`EnsembleOptions` names them (with ``simulate``'s types); their defaults are ``simulate``'s
(read with `jaxlag._options.default_option`); the other options of ``simulate`` are refused with
the reason and the method that has them. A new option of ``simulate`` fails here, at import,
until it is listed in one or the other.
"""

from collections.abc import Mapping

import diffrax
import jax.numpy as jnp
import numpy as np
from typing_extensions import TypedDict

from ..._checks import Checks
from ..._custom_types import RealScalarLike, Validated
from ..._misc import is_concrete
from ..._options import SimulateOptions
from ..._stabilization import Baumgarte, Projection

__all__ = [
    "EnsembleOptions",
    "VMAP",
    "UNSUPPORTED",
    "refuse_unsupported",
    "check_names",
    "plain_saves",
    "save_times",
]


class EnsembleOptions(TypedDict, total=False):
    """The options of [`simulate`][jaxlag.simulate] the ensemble integrator has; each is optional,
    and one left out means ``simulate``'s default."""

    t0: RealScalarLike | None
    t1: RealScalarLike | None
    solver: diffrax.AbstractSolver | None
    stepsize_controller: diffrax.AbstractStepSizeController | None
    dt0: RealScalarLike | None
    saveat: diffrax.SaveAt | None
    max_steps: int | None
    adjoint: Validated[diffrax.AbstractAdjoint | None]
    throw: bool
    baumgarte: Baumgarte | None
    projection: Validated[Projection | None]
    checks: Validated[Checks]


_SAVE_Y = diffrax.SubSaveAt(t1=True).fn  # diffrax's default: save the state as it is
VMAP = "Use simulate_batch(..., method=jl.Vmap()) (jax.vmap of jl.simulate), which supports it."

# The options of jl.simulate that the ensemble loop does not have, and why.
UNSUPPORTED = {
    "events": "jl.Event conditions (events=) are not supported by the ensemble integrator. ",
    "event": "diffrax events (event=) are not supported by the ensemble integrator. ",
    "progress_meter": "progress meters are not supported by the ensemble integrator. ",
}

# Written once: a new option of jl.simulate, or a changed type, fails here at import until it is
# listed as supported (with simulate's type; ``adjoint`` is narrowed: no ForwardSensitivities)
# or not.
_LISTED = set(EnsembleOptions.__annotations__) | set(UNSUPPORTED)
_DRIFTED = [
    name
    for name, kind in EnsembleOptions.__annotations__.items()
    if name != "adjoint" and SimulateOptions.__annotations__.get(name) != kind
]
if set(SimulateOptions.__annotations__) != _LISTED or _DRIFTED:
    raise ImportError(
        "jaxlag's ensemble options are out of date with jl.simulate's: "
        f"{sorted(set(SimulateOptions.__annotations__) ^ _LISTED) + _DRIFTED}"
    )


def refuse_unsupported(options: Mapping[str, object]) -> None:
    """A ``ValueError`` that points to ``method=jl.Vmap()`` for an option the loop does not have."""
    for name in options:
        if name in UNSUPPORTED:
            raise ValueError("simulate_batch(method=jl.Ensemble()): " + UNSUPPORTED[name] + VMAP)


def check_names(options: Mapping[str, object], caller: str) -> None:
    """A ``TypeError`` (as Python raises for a keyword) for a name that is not an option the loop
    has, with the reason for an option of ``simulate`` it does not have."""
    for name in options:
        if name not in EnsembleOptions.__annotations__:
            why = f" ({UNSUPPORTED[name].strip()} {VMAP})" if name in UNSUPPORTED else ""
            raise TypeError(f"{caller}() got an unexpected keyword argument {name!r}{why}.")


def plain_saves(saveat: diffrax.SaveAt) -> bool:
    """Whether ``saveat`` asks for the state as it is, at ``t1`` or at given times only."""
    sub = saveat.subs
    if not isinstance(sub, diffrax.SubSaveAt) or sub.steps or sub.t0 or saveat.dense or sub.fn is not _SAVE_Y:
        return False
    return sub.t1 != (sub.ts is not None)


def save_times(ts, t0, t1, saveat):
    """The save times including the start (T ≥ 2), or ``None`` when not given."""
    if ts is not None:
        return ts
    if saveat is not None and isinstance(saveat.subs, diffrax.SubSaveAt) and saveat.subs.ts is not None:
        if t0 is None:
            return None
        return jnp.concatenate([jnp.atleast_1d(jnp.asarray(t0)), jnp.asarray(saveat.subs.ts)])
    if t0 is None or t1 is None:
        return None
    if is_concrete((t0, t1)):  # stays on the host, also under jit
        return np.array([float(np.asarray(t0)), float(np.asarray(t1))])
    return jnp.stack([jnp.asarray(t0, float), jnp.asarray(t1, float)])
