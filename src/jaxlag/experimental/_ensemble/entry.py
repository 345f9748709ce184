"""The ensemble integrator's entry: the options it supports, their checks, the constant-step
grid on the host, and `integrate_ensemble` (or the
Pallas kernel) under one ``jax.jit``.

`run_batch` is what ``jl.Ensemble().simulate`` calls for ``jl.simulate_batch``;
`integrate_batch` takes the supported options of [`simulate`][jaxlag.simulate] as keywords
with ``simulate``'s defaults, so an option it does not support cannot reach it.
"""

import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ... import _checks as checking
from ... import _compile as compilation
from ..._batch.methods import BatchProblem
from ..._checks import Checks
from ..._custom_types import RealScalarLike
from ..._misc import is_concrete
from ..._options import SimulateOptions
from ..._stabilization import Baumgarte, Projection
from ..._tolerances import default_solver_tolerance
from ..._trajectory import Trajectory
from .integrate import (
    EnsembleSettings,
    as_member_times,
    constant_grid,
    ensemble_problem,
    integrate_ensemble,
    make_settings,
    member_failures,
)
from .pallas import integrate_pallas

_VMAP = "Use simulate_batch(..., method=jl.Vmap()) (jax.vmap of jl.simulate), which supports it."

# The options of jl.simulate that the ensemble loop does not have, and why.
_UNSUPPORTED = {
    "events": "jl.Event conditions (events=) are not supported by the ensemble integrator. ",
    "event": "diffrax events (event=) are not supported by the ensemble integrator. ",
    "progress_meter": "progress meters are not supported by the ensemble integrator. ",
}
_SAVE_Y = diffrax.SubSaveAt(t1=True).fn  # diffrax's default: save the state as it is


class ConstantGrid(eqx.Module):
    """Constant steps: ``steps[b, k]`` equal steps in save interval ``k`` of member ``b``
    (`constant_grid`), ``inner`` their maximum,
    ``uniform`` whether every entry equals it and ``shared_times`` whether every member has
    the same save times (the lane-wise Pallas kernel)."""

    steps: Int[Array, "batch intervals"]
    inner: int = eqx.field(static=True)
    uniform: bool = eqx.field(static=True)
    shared_times: bool = eqx.field(static=True)

    def as_tuple(self):
        return self.steps, self.inner, self.uniform, self.shared_times


class EnsembleRun(eqx.Module):
    """One compiled ensemble run: the batch, its save times ``ts`` ``(B, T)`` (the first
    column the start), the loop's settings, the constant-step grid (``None``: adaptive) or the
    first step ``dt0``, and how the result is assembled (``keep_first``: the start is a save,
    as ``ts[0]`` is for ``jl.simulate``). ``check``: the initial-state check, ``"host"``
    (diagnostics returned), ``True`` (compiled in) or ``False``."""

    problem: BatchProblem
    ts: Float[Array, "batch times"]
    settings: EnsembleSettings
    grid: ConstantGrid | None
    dt0: Float[Array, ""] | None
    baumgarte: Baumgarte | None
    projection: Projection | None
    check: bool | str = eqx.field(static=True)
    tolerance: float = eqx.field(static=True)
    keep_first: bool = eqx.field(static=True)


def run_batch(problem: BatchProblem, backend: str, options: SimulateOptions) -> Trajectory:
    """``simulate_batch(..., method=jl.Ensemble(backend), **options)``: a ``ValueError`` that
    points to ``method=jl.Vmap()`` for an option the ensemble loop does not have, else
    `integrate_batch`. (``throw`` is read by ``simulate_batch``, which raises from the
    failure records.)"""
    for name in options:
        if name in _UNSUPPORTED:
            raise ValueError("simulate_batch(method=jl.Ensemble()): " + _UNSUPPORTED[name] + _VMAP)
    options = SimulateOptions(**options)
    options.pop("throw", None)
    return integrate_batch(problem, backend, **options)  # pyright: ignore[reportCallIssue]


def ensemble_by_default(problem: BatchProblem, options: SimulateOptions) -> bool:
    """``method=None`` on an accelerator: the ensemble loop for constant steps on a grid that
    divides the save intervals (so that the result equals the vmap one to rounding)."""
    if any(name in _UNSUPPORTED for name in options) or problem.system.unilateral or problem.system.friction:
        return False
    if not isinstance(options.get("stepsize_controller"), diffrax.ConstantStepSize):
        return False
    options = SimulateOptions(**options)
    options.pop("throw", None)
    try:
        run = _prepare(problem, **options)  # pyright: ignore[reportCallIssue]
    except (TypeError, ValueError):  # auto never fails where vmap would run
        return False
    if run.grid is None or options.get("dt0") is None:
        return False
    times = np.asarray(run.ts, dtype=float)
    ratio = np.diff(times, axis=1) / float(np.asarray(options.get("dt0")))
    return bool(np.all(np.abs(ratio - np.round(ratio)) <= 1e-9 * np.maximum(1.0, ratio)))


def integrate_batch(
    problem: BatchProblem,
    backend: str = "auto",
    *,
    t0: RealScalarLike | None = None,
    t1: RealScalarLike | None = None,
    solver: diffrax.AbstractSolver | None = None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    dt0: RealScalarLike | None = None,
    saveat: diffrax.SaveAt | None = None,
    max_steps: int | None = 2**16,
    adjoint: diffrax.AbstractAdjoint | None = None,
    baumgarte: Baumgarte | None = None,
    projection: Projection | None = Projection(),
    checks: Checks = Checks(),
) -> Trajectory:
    """The batch integrated by the ensemble loop, the options as for [`simulate`][jaxlag.simulate];
    failed members are recorded in ``Trajectory.failure`` (the caller raises for them)."""
    run = _prepare(
        problem,
        t0=t0,
        t1=t1,
        solver=solver,
        stepsize_controller=stepsize_controller,
        dt0=dt0,
        saveat=saveat,
        max_steps=max_steps,
        adjoint=adjoint,
        baumgarte=baumgarte,
        projection=projection,
        checks=checks,
    )
    if backend == "auto":
        backend = "xla"
    if backend.startswith("pallas") and run.settings.adaptive:
        raise ValueError(
            "jl.Ensemble(backend='pallas') integrates constant steps only "
            "(diffrax.ConstantStepSize()); use backend='xla' for adaptive steps."
        )
    if backend == "pallas":
        error = _kernel_lowers(run, backend)
        if error is not None:
            message = str(error).splitlines()[0][:200] if str(error) else ""
            warnings.warn(
                f"simulate_batch(method=jl.Ensemble(backend='pallas')): the kernel did not lower "
                f"({type(error).__name__}: {message}); using the XLA loop.",
                RuntimeWarning,
                stacklevel=4,
            )
            backend = "xla"
    out, diagnostics = _run(run, backend)
    out, diagnostics = problem.unpad((out, diagnostics))
    if diagnostics is not None:
        args = eqx.combine(problem.batched_args, problem.shared_args)
        checking.raise_for_initial_states(problem.system, diagnostics, args, run.tolerance)
    return out


def _prepare(
    problem: BatchProblem,
    *,
    t0: RealScalarLike | None = None,
    t1: RealScalarLike | None = None,
    solver: diffrax.AbstractSolver | None = None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    dt0: RealScalarLike | None = None,
    saveat: diffrax.SaveAt | None = None,
    max_steps: int | None = 2**16,
    adjoint: diffrax.AbstractAdjoint | None = None,
    baumgarte: Baumgarte | None = None,
    projection: Projection | None = Projection(),
    checks: Checks = Checks(),
) -> EnsembleRun:
    """The options checked and turned into an `EnsembleRun` (a ``ValueError`` or
    ``TypeError`` for what the loop cannot do), on the host: the save times checked and, for
    constant steps, gridded."""
    p = problem
    system = p.system
    dtype = p.q0.dtype
    if system.unilateral:
        raise ValueError(
            "simulate_batch(method=jl.Ensemble()): unilateral constraints switch per member at "
            "events; the ensemble integrator has no event handling. " + _VMAP
        )
    if system.friction:
        raise ValueError(
            "simulate_batch(method=jl.Ensemble()): Coulomb friction switches per member at events; "
            "the ensemble integrator has no event handling. " + _VMAP
        )
    if solver is None:
        solver = diffrax.Tsit5()
    if stepsize_controller is None:
        tol = default_solver_tolerance(dtype)
        stepsize_controller = diffrax.PIDController(rtol=tol, atol=tol)
    # throw=False: simulate_batch raises from the failure records.
    settings = make_settings(solver, stepsize_controller, max_steps, adjoint, False)
    if saveat is not None and not _plain_saves(saveat):
        raise ValueError(
            "simulate_batch(method=jl.Ensemble()): the ensemble integrator saves at given times "
            "only: pass ts, or saveat=diffrax.SaveAt(t1=True) / SaveAt(ts=...). " + _VMAP
        )
    times = _save_times(p.ts, t0, t1, saveat)
    if times is None:
        raise ValueError("Give save times `ts`, or `t0` and `t1` (with saveat=SaveAt(t1=True)).")
    batch = p.size + p.pad
    host = None
    if is_concrete(times):  # checked and gridded on the host (also under a caller's jit)
        host = np.asarray(times, dtype=np.float64)
        host = np.broadcast_to(host, (batch,) + host.shape) if host.ndim == 1 else host
        if host.ndim == 2 and not np.all(np.diff(host, axis=1) > 0):
            raise ValueError("ts must be strictly increasing (for every member).")
    grid = None
    if not settings.adaptive:
        if dt0 is None:
            raise ValueError("simulate_batch(method=jl.Ensemble()): diffrax.ConstantStepSize() needs dt0.")
        if host is None or not is_concrete(dt0):
            raise ValueError(
                "simulate_batch(method=jl.Ensemble()): constant steps need concrete save times "
                "and dt0 (the number of steps is static); pass them as numbers, not traced "
                "values. " + _VMAP
            )
        m, inner = constant_grid(host, float(np.asarray(dt0)))
        if int(m.sum(axis=1).max()) > settings.max_steps:
            raise ValueError(
                f"Constant steps of dt0={dt0} need {int(m.sum(axis=1).max())} steps, more "
                f"than max_steps={settings.max_steps}."
            )
        grid = ConstantGrid(
            jnp.asarray(m, jnp.int32), inner, bool(np.all(m == inner)), bool(np.all(host == host[:1]))
        )
    # A weakly typed state (jnp.full(..., 0.5)) would compile a second program for the same shapes.
    q0, qd0 = (x.astype(x.dtype) if x.weak_type else x for x in (p.q0, p.qd0))
    q0, qd0 = (jnp.broadcast_to(x, (batch,) + x.shape) if x.ndim == 1 else x for x in (q0, qd0))
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
        baumgarte=baumgarte,
        projection=projection if system.is_constrained else None,
        check=check,
        tolerance=float(checks.tolerance(dtype)),
        keep_first=p.ts is not None,  # simulate saves at ts[0]; with t0/t1/saveat only what saveat asks
    )


def _plain_saves(saveat: diffrax.SaveAt) -> bool:
    """Whether ``saveat`` asks for the state as it is, at ``t1`` or at given times only."""
    sub = saveat.subs
    if not isinstance(sub, diffrax.SubSaveAt) or sub.steps or sub.t0 or saveat.dense or sub.fn is not _SAVE_Y:
        return False
    return sub.t1 != (sub.ts is not None)


def _save_times(ts, t0, t1, saveat):
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


def _broadcast_members(tree, batch):
    def expand(x):
        if eqx.is_array(x):
            x = jnp.asarray(x)
            return jnp.broadcast_to(x, (batch,) + x.shape)
        return x

    return jax.tree.map(expand, tree)


def _run_impl(run: EnsembleRun, backend: str):
    p = run.problem
    ts = run.ts
    field, y0, diagnostics = ensemble_problem(
        p.system,
        p.q0,
        p.qd0,
        ts,
        p.batched_args,
        p.shared_args,
        run.baumgarte,
        run.projection,
        run.check,
        run.tolerance,
    )
    settings = run.settings
    grid = None if run.grid is None else run.grid.as_tuple()
    if backend in ("pallas", "pallas-interpret"):
        saved, stats, _ = integrate_pallas(
            field, settings, ts, y0, grid, interpret=backend == "pallas-interpret"
        )
        record = None
    else:
        saved, stats, record = integrate_ensemble(field, settings, ts, y0, run.dt0, grid)
    saved, failure, result = member_failures(
        ts, y0, saved, stats, record, None if grid is None else grid[0], settings.max_steps
    )
    q, qd = (jnp.moveaxis(x, 0, 1) for x in saved)  # (B, T-1, n)
    if run.keep_first:
        q = jnp.concatenate([y0[0][:, None], q], axis=1)
        qd = jnp.concatenate([y0[1][:, None], qd], axis=1)
        t = ts
    else:
        t = ts[:, 1:]
    batch = q.shape[0]
    stats = {**stats, "max_steps": jnp.full((batch,), settings.max_steps, jnp.int32)}
    args = eqx.combine(p.batched_args, _broadcast_members(p.shared_args, batch))
    system_arrays, system_static = eqx.partition(p.system, eqx.is_array)
    system_arrays = _broadcast_members(system_arrays, batch)
    out = Trajectory(
        t,
        q,
        qd,
        args,
        stats,
        result,
        system_arrays,
        active=None,
        events=None,
        failure=failure,
        system_static=system_static,
    )
    if p.sharding is not None:
        sharding = p.sharding
        out = jax.tree.map(
            lambda x: (
                jax.lax.with_sharding_constraint(x, sharding)
                if isinstance(x, jax.Array) and x.ndim >= 1
                else x
            ),
            out,
        )
    return out, diagnostics


_run = compilation.filter_jit(_run_impl)


def _kernel_lowers(run: EnsembleRun, backend: str) -> Exception | None:
    """Compile the Pallas variant from abstract shapes: ``None`` if it lowers, else the error.

    Done ahead of the real call so that a failure is caught here even when ``simulate_batch`` is
    traced inside the caller's own ``jax.jit`` (whose compilation would otherwise fail later).
    """
    dynamic, static = eqx.partition(run, eqx.is_array)
    spec = jax.tree.map(lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)), dynamic)
    try:
        compilation.jit(lambda d: _run_impl(eqx.combine(d, static), backend)).lower(spec).compile()
    except Exception as error:  # noqa: BLE001 - any lowering failure: the XLA loop is exact too
        return error
    return None
