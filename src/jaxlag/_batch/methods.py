"""How :func:`~jaxlag.simulate_batch` integrates a batch: ``method=jl.Vmap()`` or
``method=jl.Ensemble(backend=...)`` (``None``: chosen automatically)."""

from __future__ import annotations

from typing import Literal, get_args

import equinox as eqx

EnsembleBackend = Literal["auto", "xla", "pallas", "pallas-interpret"]


class AbstractBatchMethod(eqx.Module):
    """How :func:`~jaxlag.simulate_batch` integrates the batch: :class:`~jaxlag.Vmap` or
    :class:`~jaxlag.Ensemble`. (``method=None`` picks one; see ``simulate_batch``.)"""


class Vmap(AbstractBatchMethod):
    """``jax.vmap`` of :func:`~jaxlag.simulate`: every option of ``simulate`` (events,
    unilateral constraints, any diffrax solver, controller and adjoint), each member with its own
    solver loop inside one batched loop that runs until the slowest member has finished."""


class Ensemble(AbstractBatchMethod):
    """One batched Runge–Kutta loop for the whole batch (:mod:`jaxlag._batch.ensemble`): explicit
    Runge–Kutta solvers with a Butcher tableau (``diffrax.Tsit5()``, ``diffrax.Dopri5()``,
    ``jl.RK4()``, ...), constant or PID steps, each member with its own step size when
    adaptive; per-member save times ``ts`` of shape ``(B, T)`` are allowed.
    Events, unilateral constraints and progress meters are not supported (a ``ValueError``
    points to :class:`~jaxlag.Vmap`). Failed members are reported as :class:`~jaxlag.Vmap`
    reports them: ``traj.failure`` and ``traj.result`` per member (a state that became
    non-finite, a step size that collapsed, ``max_steps``), their unreached saves ``inf``, and
    ``throw=True`` raises :class:`~jaxlag.SimulationError` naming the first failed member.

    ``backend``: ``"xla"`` (the loop as XLA operations), ``"pallas"`` (one fused Pallas kernel,
    constant steps; falls back to ``"xla"`` with a warning if the equations do not lower),
    ``"pallas-interpret"`` (the kernel in Pallas's interpreter, for testing on CPU) or
    ``"auto"`` (default: ``"xla"``; see the README for why).
    """

    backend: EnsembleBackend = eqx.field(static=True, default="auto")

    def __check_init__(self):
        if self.backend not in get_args(EnsembleBackend):
            choices = ", ".join(repr(b) for b in get_args(EnsembleBackend))
            raise ValueError(f"Ensemble backend must be one of {choices}; got {self.backend!r}.")
