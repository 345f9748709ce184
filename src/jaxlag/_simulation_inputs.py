"""The inputs of one simulation: what ``jax.grad`` may differentiate."""

import diffrax
import equinox as eqx
from jaxtyping import Array, Float, PyTree

from ._custom_types import RealScalarLike
from ._events import Events
from ._stabilization import Baumgarte, Projection
from ._system import System


class SimulationInputs(eqx.Module):
    """The inputs of one simulation, as `_Run` receives them: a pytree whose inexact array
    leaves are what ``jax.grad`` may differentiate (`jaxlag._adjoint`; the other leaves
    are static). ``events``: the user conditions and the segmented integration's options (only
    read when the run is segmented); ``event``: a diffrax event (plain solves only)."""

    system: System
    q0: Float[Array, " n"]
    qd0: Float[Array, " n"]
    t0: RealScalarLike  # a 0-d array of q0's dtype; NumPy while concrete (simulate's _as_time)
    t1: RealScalarLike
    ts: Float[Array, " times"] | None
    dt0: RealScalarLike | None
    args: PyTree
    saveat: diffrax.SaveAt
    solver: diffrax.AbstractSolver
    stepsize_controller: diffrax.AbstractStepSizeController
    baumgarte: Baumgarte | None
    projection: Projection | None
    events: Events
    event: diffrax.Event | None
