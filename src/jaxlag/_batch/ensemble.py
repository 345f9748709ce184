"""``method=jl.Ensemble()``: the batch as an array axis of one Runge–Kutta loop, run by the
experimental ensemble integrator (`jaxlag.experimental`, imported when first used)."""

from typing import Literal, get_args

import equinox as eqx

from .._custom_types import Validated
from .._options import SimulateOptions
from .._trajectory import Trajectory
from .methods import AbstractBatchMethod, BatchProblem

EnsembleBackend = Literal["auto", "xla", "pallas", "pallas-interpret"]


class Ensemble(AbstractBatchMethod):
    """One batched Runge–Kutta loop for the whole batch
    ([`jaxlag.experimental.simulate_ensemble`][jaxlag.experimental.simulate_ensemble]):
    explicit Runge–Kutta solvers with a Butcher tableau (``diffrax.Tsit5()``, ``diffrax.Dopri5()``,
    ``jl.RK4()``, ...), constant or PID steps, each member with its own step size when
    adaptive; per-member save times ``ts`` of shape ``(B, T)`` are allowed.
    Events, unilateral constraints and progress meters are not supported: the options
    ``events``, ``event`` and ``progress_meter`` are a ``ValueError`` that points to
    [`Vmap`][jaxlag.Vmap]. Failed members are reported as [`Vmap`][jaxlag.Vmap]
    reports them: ``traj.failure`` and ``traj.result`` per member (a state that became
    non-finite, a step size that collapsed, ``max_steps``), their unreached saves ``inf``, and
    ``throw=True`` raises [`SimulationError`][jaxlag.SimulationError] naming the first failed member.

    ``backend``: ``"xla"`` (the loop as XLA operations), ``"pallas"`` (one fused Pallas kernel,
    constant steps; falls back to ``"xla"`` with a warning if the equations do not lower),
    ``"pallas-interpret"`` (the kernel in Pallas's interpreter, for testing on CPU) or
    ``"auto"`` (default: ``"xla"``; see the README for why).
    """

    backend: Validated[EnsembleBackend] = eqx.field(static=True, default="auto")

    def __check_init__(self):
        if self.backend not in get_args(EnsembleBackend):
            choices = ", ".join(repr(b) for b in get_args(EnsembleBackend))
            raise ValueError(f"Ensemble backend must be one of {choices}; got {self.backend!r}.")

    def simulate(self, problem: BatchProblem, options: SimulateOptions) -> Trajectory:
        # Experimental code, loaded on first use: the core does not import it.
        from ..experimental._ensemble.entry import run_batch

        return run_batch(problem, self.backend, options)
