"""``SimulateOptions``: the keyword options of [`simulate`][jaxlag.simulate], written once.

[`simulate`][jaxlag.simulate] spells them out as keywords with their defaults (its signature is where
the defaults live, as ``diffrax.diffeqsolve``'s is); every entry point that runs ``simulate`` for
its user ([`simulate_batch`][jaxlag.simulate_batch], the batch methods) takes them as
``**options: Unpack[SimulateOptions]`` and forwards them untouched, so a new option of
``simulate`` is added in two places: its signature and this ``TypedDict``.
"""

import inspect
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any

import diffrax
from typing_extensions import TypedDict

from ._adjoint import ForwardSensitivities
from ._checks import Checks
from ._custom_types import RealScalarLike, Validated
from ._events import Event, Events
from ._simulate import simulate
from ._stabilization import Baumgarte, Projection

__all__ = ["SimulateOptions", "default_option", "check_option_names"]


class SimulateOptions(TypedDict, total=False):
    """The options of [`simulate`][jaxlag.simulate] other than the problem ``(system, q0, qd0, ts,
    args)``; each is optional, and one left out means ``simulate``'s default. See
    [`simulate`][jaxlag.simulate] for their meaning."""

    t0: RealScalarLike | None
    t1: RealScalarLike | None
    solver: diffrax.AbstractSolver | None
    stepsize_controller: diffrax.AbstractStepSizeController | None
    dt0: RealScalarLike | None
    saveat: diffrax.SaveAt | None
    max_steps: int | None
    adjoint: Validated[diffrax.AbstractAdjoint | ForwardSensitivities | None]
    event: diffrax.Event | None
    throw: bool
    progress_meter: diffrax.AbstractProgressMeter | None
    baumgarte: Baumgarte | None
    projection: Validated[Projection | None]
    checks: Validated[Checks]
    events: Validated[Events | Event | Sequence[Event]]


# simulate's defaults, read from its signature (a name missing there fails here, at import).
_DEFAULTS = MappingProxyType(
    {name: inspect.signature(simulate).parameters[name].default for name in SimulateOptions.__annotations__}
)


def default_option(options: Mapping[str, object], name: str) -> Any:
    """``options[name]``, or [`simulate`][jaxlag.simulate]'s default when it was not given."""
    return options.get(name, _DEFAULTS[name])


def check_option_names(options: Mapping[str, object], caller: str) -> None:
    """A ``TypeError`` (as Python raises for a keyword) for a name that is not an option of
    [`simulate`][jaxlag.simulate]."""
    for name in options:
        if name not in _DEFAULTS:
            raise TypeError(f"{caller}() got an unexpected keyword argument {name!r}.")
