"""The ensemble integrator's entry: the options checked and turned into an `EnsembleRun` on the
host (the constant-step grid included), then one compiled `run`.

`run_batch` is what ``jl.Ensemble().simulate`` calls for ``jl.simulate_batch``;
`integrate_batch` takes the supported options of [`simulate`][jaxlag.simulate]
(`EnsembleOptions`, with ``simulate``'s defaults), so an option it does not support cannot
reach it.
"""

import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from typing_extensions import Unpack

from ... import _checks as checking
from ..._batch.methods import BatchProblem
from ..._misc import is_concrete
from ..._options import SimulateOptions, default_option
from ..._tolerances import default_solver_tolerance
from ..._trajectory import Trajectory
from .constant import constant_grid
from .integrate import as_member_times
from .options import UNSUPPORTED, VMAP, EnsembleOptions, plain_saves, refuse_unsupported, save_times
from .run import ConstantGrid, EnsembleRun, kernel_lowers, run
from .settings import EnsembleSettings, make_settings

__all__ = ["run_batch", "ensemble_by_default", "integrate_batch"]


def _supported(options: SimulateOptions) -> EnsembleOptions:
    """``options`` without ``throw`` (read by ``simulate_batch``, which raises from the failure
    records), once the options the loop does not have are refused."""
    refuse_unsupported(options)
    return EnsembleOptions(**{k: v for k, v in options.items() if k != "throw"})  # pyright: ignore[reportArgumentType]


def run_batch(problem: BatchProblem, backend: str, options: SimulateOptions) -> Trajectory:
    """``simulate_batch(..., method=jl.Ensemble(backend), **options)``: a ``ValueError`` that
    points to ``method=jl.Vmap()`` for an option the ensemble loop does not have, else
    `integrate_batch`."""
    return integrate_batch(problem, backend, **_supported(options))


def ensemble_by_default(problem: BatchProblem, options: SimulateOptions) -> bool:
    """``method=None`` on an accelerator: the ensemble loop for constant steps on a grid that
    divides the save intervals (so that the result equals the vmap one to rounding)."""
    if any(name in UNSUPPORTED for name in options) or problem.system.unilateral or problem.system.friction:
        return False
    if not isinstance(options.get("stepsize_controller"), diffrax.ConstantStepSize):
        return False
    try:
        ensemble = _prepare(problem, _supported(options))
    except (TypeError, ValueError):  # auto never fails where vmap would run
        return False
    dt0 = options.get("dt0")
    if ensemble.grid is None or dt0 is None:
        return False
    times = np.asarray(ensemble.ts, dtype=float)
    ratio = np.diff(times, axis=1) / float(np.asarray(dt0))
    return bool(np.all(np.abs(ratio - np.round(ratio)) <= 1e-9 * np.maximum(1.0, ratio)))


def integrate_batch(
    problem: BatchProblem, backend: str = "auto", **options: Unpack[EnsembleOptions]
) -> Trajectory:
    """The batch integrated by the ensemble loop, the options as for [`simulate`][jaxlag.simulate];
    failed members are recorded in ``Trajectory.failure`` (the caller raises for them)."""
    ensemble = _prepare(problem, options)
    if backend == "auto":
        backend = "xla"
    if backend.startswith("pallas") and ensemble.settings.adaptive:
        raise ValueError(
            "jl.Ensemble(backend='pallas') integrates constant steps only "
            "(diffrax.ConstantStepSize()); use backend='xla' for adaptive steps."
        )
    if backend == "pallas":
        backend = _pallas_or_xla(ensemble)
    out, diagnostics = run(ensemble, backend)
    out, diagnostics = problem.unpad((out, diagnostics))
    if diagnostics is not None:
        args = eqx.combine(problem.batched_args, problem.shared_args)
        checking.raise_for_initial_states(problem.system, diagnostics, args, ensemble.tolerance)
    return out


def _pallas_or_xla(ensemble: EnsembleRun) -> str:
    """``"pallas"`` if the kernel lowers, else ``"xla"`` with a warning that says why."""
    error = kernel_lowers(ensemble, "pallas")
    if error is None:
        return "pallas"
    message = str(error).splitlines()[0][:200] if str(error) else ""
    warnings.warn(
        f"simulate_batch(method=jl.Ensemble(backend='pallas')): the kernel did not lower "
        f"({type(error).__name__}: {message}); using the XLA loop.",
        RuntimeWarning,
        stacklevel=5,
    )
    return "xla"


def _settings(problem: BatchProblem, options: EnsembleOptions) -> EnsembleSettings:
    """The loop's settings from the solver, controller, ``max_steps`` and adjoint (``Tsit5`` and
    a ``PIDController`` at the default tolerance of the dtype when not given)."""
    system = problem.system
    switching = (
        (system.unilateral, "unilateral constraints switch"),
        (system.friction, "Coulomb friction switches"),
    )
    for present, what in switching:
        if present:
            raise ValueError(
                f"simulate_batch(method=jl.Ensemble()): {what} per member at events; "
                "the ensemble integrator has no event handling. " + VMAP
            )
    solver = default_option(options, "solver")
    if solver is None:
        solver = diffrax.Tsit5()
    controller = default_option(options, "stepsize_controller")
    if controller is None:
        tol = default_solver_tolerance(problem.q0.dtype)
        controller = diffrax.PIDController(rtol=tol, atol=tol)
    max_steps, adjoint = default_option(options, "max_steps"), default_option(options, "adjoint")
    # throw=False: simulate_batch raises from the failure records.
    return make_settings(solver, controller, max_steps, adjoint, False)


def _times(problem: BatchProblem, options: EnsembleOptions):
    """The save times including the start, and on the host ``(B, T)`` when concrete (checked
    increasing, also under a caller's jit), else ``None``."""
    saveat = default_option(options, "saveat")
    if saveat is not None and not plain_saves(saveat):
        raise ValueError(
            "simulate_batch(method=jl.Ensemble()): the ensemble integrator saves at given times "
            "only: pass ts, or saveat=diffrax.SaveAt(t1=True) / SaveAt(ts=...). " + VMAP
        )
    times = save_times(problem.ts, default_option(options, "t0"), default_option(options, "t1"), saveat)
    if times is None:
        raise ValueError("Give save times `ts`, or `t0` and `t1` (with saveat=SaveAt(t1=True)).")
    if not is_concrete(times):
        return times, None
    host = np.asarray(times, dtype=np.float64)
    host = np.broadcast_to(host, (problem.size + problem.pad,) + host.shape) if host.ndim == 1 else host
    if host.ndim == 2 and not np.all(np.diff(host, axis=1) > 0):
        raise ValueError("ts must be strictly increasing (for every member).")
    return times, host


def _grid(settings: EnsembleSettings, host, dt0) -> ConstantGrid | None:
    """Constant steps: the steps per save interval, static; ``None`` for adaptive steps."""
    if settings.adaptive:
        return None
    if dt0 is None:
        raise ValueError("simulate_batch(method=jl.Ensemble()): diffrax.ConstantStepSize() needs dt0.")
    if host is None or not is_concrete(dt0):
        raise ValueError(
            "simulate_batch(method=jl.Ensemble()): constant steps need concrete save times "
            "and dt0 (the number of steps is static); pass them as numbers, not traced "
            "values. " + VMAP
        )
    m, inner = constant_grid(host, float(np.asarray(dt0)))
    if int(m.sum(axis=1).max()) > settings.max_steps:
        raise ValueError(
            f"Constant steps of dt0={dt0} need {int(m.sum(axis=1).max())} steps, more "
            f"than max_steps={settings.max_steps}."
        )
    return ConstantGrid(
        jnp.asarray(m, jnp.int32), inner, bool(np.all(m == inner)), bool(np.all(host == host[:1]))
    )


def _prepare(problem: BatchProblem, options: EnsembleOptions) -> EnsembleRun:
    """The options checked and turned into an `EnsembleRun` (a ``ValueError`` or
    ``TypeError`` for what the loop cannot do), on the host: the save times checked and, for
    constant steps, gridded."""
    p, dtype, batch = problem, problem.q0.dtype, problem.size + problem.pad
    settings = _settings(p, options)
    times, host = _times(p, options)
    dt0 = default_option(options, "dt0")
    grid = _grid(settings, host, dt0)
    # A weakly typed state (jnp.full(..., 0.5)) would compile a second program for the same shapes.
    q0, qd0 = (x.astype(x.dtype) if x.weak_type else x for x in (p.q0, p.qd0))
    q0, qd0 = (jnp.broadcast_to(x, (batch,) + x.shape) if x.ndim == 1 else x for x in (q0, qd0))
    checks = default_option(options, "checks")
    check: bool | str = bool(checks.initial_state)
    if check and jax.process_count() == 1 and is_concrete((q0, qd0, times, p.batched_args, p.shared_args)):
        # Concrete inputs: every member's diagnostics come back as values and the host raises
        # with the numbers and the first failing member, as for method=jl.Vmap().
        check = "host"
    return EnsembleRun(
        problem=eqx.tree_at(lambda x: (x.q0, x.qd0), p, (q0, qd0)),
        ts=as_member_times(times, batch, dtype),
        settings=settings,
        grid=grid,
        dt0=None if dt0 is None else jnp.asarray(dt0, dtype),
        baumgarte=default_option(options, "baumgarte"),
        projection=default_option(options, "projection") if p.system.is_constrained else None,
        check=check,
        tolerance=float(checks.tolerance(dtype)),
        keep_first=p.ts is not None,  # simulate saves at ts[0]; with t0/t1/saveat only what saveat asks
    )
