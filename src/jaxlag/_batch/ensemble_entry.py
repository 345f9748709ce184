"""``simulate_batch(..., method=jl.Ensemble())``: options, checks and the compiled call.

Turns the options of :func:`~jaxlag.simulate` (as :func:`~jaxlag.simulate_batch` received them)
into :class:`~jaxlag._batch.ensemble.EnsembleSettings`, rejects what the ensemble loop does not do (with
a pointer to ``method=jl.Vmap()``), computes the
constant-step grid on the host and runs :func:`~jaxlag._batch.ensemble.integrate_ensemble` (or the Pallas
kernel) under one ``jax.jit``.
"""

from __future__ import annotations

import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _checks as checking
from .. import _compile as compilation
from .._misc import is_concrete
from .._tolerances import default_solver_tolerance
from .ensemble import (
    as_member_times,
    constant_grid,
    ensemble_problem,
    integrate_ensemble,
    make_settings,
    member_failures,
)
from .._events import as_events
from .pallas import integrate_pallas
from .._trajectory import Trajectory

_VMAP = "Use simulate_batch(..., method=jl.Vmap()) (jax.vmap of jl.simulate), which supports it."


def _options(options: dict, dtype=np.float64) -> dict:
    """The simulate options of :func:`~jaxlag.simulate_batch` (a dict by ``simulate``'s keyword
    names: ``solver``, ``stepsize_controller``, ``checks``, ``events``, ...) with ``simulate``'s
    default solver and controller filled in (``rtol = atol`` of the state's ``dtype``)."""
    options = dict(options)
    if options["solver"] is None:
        options["solver"] = diffrax.Tsit5()
    if options["stepsize_controller"] is None:
        tol = default_solver_tolerance(dtype)
        options["stepsize_controller"] = diffrax.PIDController(rtol=tol, atol=tol)
    return options


def unsupported(system, ts, options: dict) -> str | None:
    """Why ``method=jl.Ensemble()`` cannot run these options, or ``None``."""
    options = _options(options)
    if system.unilateral:
        return (
            "unilateral constraints switch per member at events; the ensemble integrator has "
            "no event handling. " + _VMAP
        )
    if system.friction:
        return (
            "Coulomb friction switches per member at events; the ensemble integrator has no event handling. "
            + _VMAP
        )
    if as_events(options["events"]).conditions:
        return "jl.Event conditions are not supported by the ensemble integrator. " + _VMAP
    if options["event"] is not None:
        return "diffrax events are not supported by the ensemble integrator. " + _VMAP
    if options["progress_meter"] is not None and not isinstance(
        options["progress_meter"], diffrax.NoProgressMeter
    ):
        return "progress meters are not supported by the ensemble integrator. " + _VMAP
    saveat = options["saveat"]
    if saveat is not None:
        sub = saveat.subs
        plain_t1 = (
            sub.t1
            and not sub.t0
            and sub.ts is None
            and not sub.steps
            and not saveat.dense
            and sub.fn is diffrax._saveat.save_y
        )
        plain_ts = (
            not sub.t0
            and not sub.t1
            and sub.ts is not None
            and not sub.steps
            and not saveat.dense
            and sub.fn is diffrax._saveat.save_y
        )
        if not (plain_t1 or plain_ts):
            return (
                "the ensemble integrator saves at given times only: pass ts, or "
                "saveat=diffrax.SaveAt(t1=True) / SaveAt(ts=...). " + _VMAP
            )
    try:
        make_settings(
            options["solver"],
            options["stepsize_controller"],
            options["max_steps"],
            options["adjoint"],
            options["throw"],
        )
    except (TypeError, ValueError) as error:
        return str(error)
    if isinstance(options["stepsize_controller"], diffrax.ConstantStepSize):
        if options["dt0"] is None:
            return "diffrax.ConstantStepSize() needs dt0."
        times = _save_times(ts, options)
        if times is None or not is_concrete((times, options["dt0"])):
            return (
                "constant steps need concrete save times and dt0 (the number of steps is "
                "static); pass them as numbers, not traced values. " + _VMAP
            )
    return None


def ensemble_by_default(system, ts, options: dict) -> bool:
    """``method=None``: the ensemble loop only on an accelerator, for constant steps on a grid
    that divides the save intervals (so that the result equals the vmap one to rounding)."""
    if jax.default_backend() == "cpu":
        return False
    try:
        if unsupported(system, ts, options) is not None:
            return False
    except Exception:  # noqa: BLE001 - auto never fails where vmap would run
        return False
    options = _options(options)
    if not isinstance(options["stepsize_controller"], diffrax.ConstantStepSize):
        return False
    times = np.atleast_2d(np.asarray(_save_times(ts, options), dtype=float))
    ratio = np.diff(times, axis=1) / float(options["dt0"])
    return bool(np.all(np.abs(ratio - np.round(ratio)) <= 1e-9 * np.maximum(1.0, ratio)))


def _save_times(ts, options):
    """The save times including the start (T ≥ 2), or ``None`` when not given."""
    saveat = options["saveat"]
    if ts is not None:
        return ts
    if saveat is not None and saveat.subs.ts is not None:
        if options["t0"] is None:
            return None
        return jnp.concatenate([jnp.atleast_1d(jnp.asarray(options["t0"])), jnp.asarray(saveat.subs.ts)])
    if options["t0"] is None or options["t1"] is None:
        return None
    if is_concrete((options["t0"], options["t1"])):  # stays on the host, also under jit
        return np.array([float(options["t0"]), float(options["t1"])])
    return jnp.stack([jnp.asarray(options["t0"], float), jnp.asarray(options["t1"], float)])


def _broadcast_members(tree, batch):
    def expand(x):
        if eqx.is_array(x):
            x = jnp.asarray(x)
            return jnp.broadcast_to(x, (batch,) + x.shape)
        return x

    return jax.tree.map(expand, tree)


def _run_impl(
    system,
    q0,
    qd0,
    ts,
    batched_args,
    shared_args,
    settings,
    dt0,
    grid,
    baumgarte,
    projection,
    check,
    tolerance,
    keep_first,
    out_sharding,
    backend,
):
    field, y0, diagnostics = ensemble_problem(
        system, q0, qd0, ts, batched_args, shared_args, baumgarte, projection, check, tolerance
    )
    if backend in ("pallas", "pallas-interpret"):
        saved, stats, _ = integrate_pallas(
            field, settings, ts, y0, grid, interpret=backend == "pallas-interpret"
        )
        record = None
    else:
        saved, stats, record = integrate_ensemble(field, settings, ts, y0, dt0, grid)
    saved, failure, result = member_failures(
        ts, y0, saved, stats, record, None if grid is None else grid[0], settings.max_steps
    )
    q, qd = (jnp.moveaxis(x, 0, 1) for x in saved)  # (B, T-1, n)
    if keep_first:
        q = jnp.concatenate([y0[0][:, None], q], axis=1)
        qd = jnp.concatenate([y0[1][:, None], qd], axis=1)
        t = ts
    else:
        t = ts[:, 1:]
    batch = q.shape[0]
    stats = {**stats, "max_steps": jnp.full((batch,), settings.max_steps, jnp.int32)}
    args = _broadcast_members(shared_args, batch)
    args = eqx.combine(batched_args, args)
    system_arrays, system_static = eqx.partition(system, eqx.is_array)
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
    if out_sharding is not None:
        out = jax.tree.map(
            lambda x: (
                jax.lax.with_sharding_constraint(x, out_sharding)
                if isinstance(x, jax.Array) and x.ndim >= 1
                else x
            ),
            out,
        )
    return out, diagnostics


_run = compilation.filter_jit(_run_impl)


def _kernel_lowers(call) -> Exception | None:
    """Compile the Pallas variant from abstract shapes: ``None`` if it lowers, else the error.

    Done ahead of the real call so that a failure is caught here even when ``simulate_batch`` is
    traced inside the caller's own ``jax.jit`` (whose compilation would otherwise fail later).
    """
    dynamic, static = eqx.partition(call, eqx.is_array)
    spec = jax.tree.map(lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)), dynamic)
    try:
        compilation.jit(lambda d: _run_impl(*eqx.combine(d, static))).lower(spec).compile()
    except Exception as error:  # noqa: BLE001 - any lowering failure: the XLA loop is exact too
        return error
    return None


def run_ensemble(
    system, q0, qd0, ts, batched_args, shared_args, batch, options: dict, out_sharding, backend
) -> Trajectory:
    """``simulate_batch(..., method=jl.Ensemble(backend))`` after the batch inputs have been
    prepared; ``options``: the simulate options, ``projection`` already checked. Failed
    members are recorded in ``Trajectory.failure`` (``simulate_batch`` raises for them)."""
    options = _options(options, q0.dtype)
    # throw=False: one program for both; simulate_batch raises from the failure records.
    settings = make_settings(
        options["solver"], options["stepsize_controller"], options["max_steps"], options["adjoint"], False
    )
    reason = unsupported(system, ts, options)
    if reason is not None:
        raise ValueError("simulate_batch(method=jl.Ensemble()): " + reason)
    keep_first = ts is not None  # simulate saves at ts[0]; with t0/t1/saveat only what saveat asks
    times = _save_times(ts, options)
    if times is None:
        raise ValueError("Give save times `ts`, or `t0` and `t1` (with saveat=SaveAt(t1=True)).")
    host = None
    if is_concrete(times):  # checked and gridded on the host (also under a caller's jit)
        host = np.asarray(times, dtype=np.float64)
        host = np.broadcast_to(host, (batch,) + host.shape) if host.ndim == 1 else host
        if host.ndim == 2 and not np.all(np.diff(host, axis=1) > 0):
            raise ValueError("ts must be strictly increasing (for every member).")
    times = as_member_times(times, batch, q0.dtype)
    # A weakly typed state (jnp.full(..., 0.5)) would compile a second program for the same shapes.
    q0, qd0 = (x.astype(x.dtype) if getattr(x, "weak_type", False) else x for x in (q0, qd0))
    if q0.ndim == 1:
        q0 = jnp.broadcast_to(q0, (batch,) + q0.shape)
    if qd0.ndim == 1:
        qd0 = jnp.broadcast_to(qd0, (batch,) + qd0.shape)
    projection = options["projection"] if system.is_constrained else None
    grid = None
    if not settings.adaptive:
        if host is None:  # excluded by unsupported() above
            raise ValueError("simulate_batch(method=jl.Ensemble()): constant steps need concrete save times.")
        m, inner = constant_grid(host, float(options["dt0"]))
        # The 4th entry: every member has the same save times (the lane-wise Pallas kernel).
        grid = (jnp.asarray(m, jnp.int32), inner, bool(np.all(m == inner)), bool(np.all(host == host[:1])))
        if int(m.sum(axis=1).max()) > settings.max_steps:
            raise ValueError(
                f"Constant steps of dt0={options['dt0']} need {int(m.sum(axis=1).max())} steps, more "
                f"than max_steps={settings.max_steps}."
            )
    if backend == "auto":
        backend = "xla"
    if backend.startswith("pallas") and settings.adaptive:
        raise ValueError(
            "jl.Ensemble(backend='pallas') integrates constant steps only "
            "(diffrax.ConstantStepSize()); use backend='xla' for adaptive steps."
        )
    dt0 = options["dt0"]
    dt0 = None if dt0 is None else jnp.asarray(dt0, q0.dtype)
    tolerance = options["checks"].tolerance(q0.dtype)
    check = bool(options["checks"].initial_state)
    if check and jax.process_count() == 1 and is_concrete((q0, qd0, times, batched_args, shared_args)):
        # Concrete inputs: every member's diagnostics come back as values and the host raises
        # with the numbers and the first failing member, as for method=jl.Vmap().
        check = "host"
    call = (
        system,
        q0,
        qd0,
        times,
        batched_args,
        shared_args,
        settings,
        dt0,
        grid,
        options["baumgarte"],
        projection,
        check,
        tolerance,
        keep_first,
        out_sharding,
    )
    if backend == "pallas":
        error = _kernel_lowers((*call, backend))
        if error is not None:
            message = str(error).splitlines()[0][:200] if str(error) else ""
            warnings.warn(
                f"simulate_batch(method=jl.Ensemble(backend='pallas')): the kernel did not lower "
                f"({type(error).__name__}: {message}); using the XLA loop.",
                RuntimeWarning,
                stacklevel=3,
            )
            backend = "xla"
    out, diagnostics = _run(*call, backend)
    if diagnostics is not None:
        args = eqx.combine(batched_args, shared_args)
        checking.raise_for_initial_states(system, diagnostics, args, tolerance)
    return out
