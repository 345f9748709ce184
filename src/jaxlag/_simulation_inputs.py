"""The inputs of one simulation: what ``jax.grad`` may differentiate."""

from typing import Any

import diffrax
import equinox as eqx

from ._events import Events
from ._stabilization import Baumgarte, Projection
from ._system import System


class SimulationInputs(eqx.Module):
    """The inputs of one simulation, as `_Run` receives them: a pytree whose inexact array
    leaves are what ``jax.grad`` may differentiate (`jaxlag._adjoint`; the other leaves
    are static). ``events``: the user conditions and the segmented integration's options (only
    read when the run is segmented); ``event``: a diffrax event (plain solves only)."""

    system: System
    q0: Any
    qd0: Any
    t0: Any
    t1: Any
    ts: Any
    dt0: Any
    args: Any
    saveat: diffrax.SaveAt
    solver: diffrax.AbstractSolver
    stepsize_controller: diffrax.AbstractStepSizeController
    baumgarte: Baumgarte | None
    projection: Projection | None
    events: Events
    event: diffrax.Event | None
