r"""``simulate_batch``: many simulations in one compiled call, optionally sharded across devices.

A batch is ``jax.vmap`` of :func:`~jaxlag.simulate` over the leading axis of the initial states
and of selected parameter leaves, compiled once with ``jax.jit``. Every member integrates the
same equations ``M q̈ = F + Jᵀλ + Aᵀμ`` with its own ``(q0, q̇0, args)``; constrained systems,
unilateral constraints and :class:`~jaxlag.Event` s work unchanged (each member switches at its
own times).

Memory grows linearly in the batch size ``B``: the program holds ``B`` copies of the solver state
and of the saved states (``B × T × n``), nothing quadratic. Time grows linearly too, with one
caveat of ``vmap``-ed adaptive solvers: the batched solver loop runs until the *slowest* member
has finished (finished members are masked), so a batch costs ``B ×`` the largest step count in
it. Group members of similar stiffness, or use a constant step.

With ``method=jl.Ensemble()`` the batch is instead an array axis of one batched Runge–Kutta
loop (:mod:`jaxlag._batch.ensemble`): no per-member solver loop, each member with its own step size when
adaptive; ``method=None`` (the default) uses it on accelerators for constant steps and keeps
``jl.Vmap()`` everywhere else (always on CPU).

Sharding uses JAX's own machinery. With ``sharding="auto"`` the batch axis is split over every
device of ``jax.devices()`` (a 1-D :class:`jax.sharding.Mesh` named ``"batch"``): batched inputs
are placed with ``jax.device_put(x, NamedSharding(mesh, P("batch")))``, shared inputs are
replicated, and XLA's SPMD partitioner splits the jitted, vmapped program so that each device
integrates its own slice; the outputs stay sharded along the batch axis. The devices exchange
a few scalars per solver step (whether any member is still running), not the states. The batch is
padded to a multiple of the number of shards with copies of the last member; when padding was
needed the padded rows are dropped on return, which gathers the result (an unevenly split axis
cannot stay sharded), so choose ``B`` a multiple of the device count for large batches.

On several hosts, call ``jax.distributed.initialize()`` first in every process; ``jax.devices()``
is then the global device list, ``"auto"`` builds a mesh over all of them, and the same call
(with the same global batch in every process, or global ``jax.Array`` s built with
``jax.make_array_from_process_local_data(batch_sharding(), local_rows)``) shards over every
device of every host.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import cast

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import ArrayLike, Float, PyTree

from .. import _checks as checking
from .. import _compile as compilation
from .. import _errors as failures
from .._misc import is_concrete
from .._adjoint import ForwardSensitivities
from .._checks import Checks
from .._conventions import as_array_leaves, as_float_state, as_jax_array
from .._custom_types import Args, RealScalarLike
from .._events import Event, Events, as_events
from .ensemble_entry import ensemble_by_default as _ensemble_by_default
from .ensemble_entry import run_ensemble
from .methods import AbstractBatchMethod, Ensemble, Vmap
from .._simulate import save_times_message, as_projection, simulate
from .._solver.validation import check_solver_controller
from .._stabilization import Baumgarte, Projection
from .._system import System
from .._trajectory import Trajectory

__all__ = ["simulate_batch", "batch_sharding"]

_BATCH_AXIS = "batch"


def _batched_mask(args, args_axes):
    """A pytree like ``args`` with ``True`` at the leaves that carry the batch axis.

    ``args_axes`` follows ``jax.vmap``'s ``in_axes``: ``None`` (shared), ``0`` (batched), or a
    pytree prefix of ``args`` with ``0``/``None`` at its leaves.
    """

    def check(axis):
        if axis not in (0, None):
            raise ValueError(
                f"args_axes entries must be 0 (batched along the leading axis) or None (shared); "
                f"got {axis!r}."
            )
        return axis == 0

    # Leaves that are not arrays or numbers (an eqx.nn.MLP's activation function) are shared.
    if args_axes is None or args_axes == 0:
        flag = check(args_axes)
        return jax.tree.map(lambda leaf: flag and eqx.is_array_like(leaf), args)
    try:
        return jax.tree.map(
            lambda axis, sub: jax.tree.map(lambda leaf: check(axis) and eqx.is_array_like(leaf), sub),
            args_axes,
            args,
            is_leaf=lambda x: x is None,
        )
    except ValueError as error:
        if "args_axes entries" in str(error):
            raise
        raise ValueError(
            "args_axes must be 0, None, or a pytree prefix of args (like jax.vmap's in_axes); "
            f"args_axes={args_axes!r} does not match the structure of args: {error}"
        ) from None


def _spec_axes(sharding: NamedSharding) -> tuple:
    spec = sharding.spec
    if len(spec) == 0 or spec[0] is None:
        raise ValueError(
            f"The batch sharding must split the leading (batch) axis; got spec {spec}. "
            f"Use e.g. NamedSharding(mesh, PartitionSpec('{_BATCH_AXIS}'))."
        )
    first = spec[0]
    return (first,) if isinstance(first, str) else tuple(first)


def batch_sharding(sharding: str | Mesh | NamedSharding = "auto") -> NamedSharding:
    """The ``NamedSharding`` that ``simulate_batch`` uses for the leading (batch) axis.

    ``"auto"``: a 1-D mesh ``("batch",)`` over ``jax.devices()`` (every local device in one
    process; every device of every process after ``jax.distributed.initialize()``).
    A ``Mesh``: the batch axis split over all of its axes. A ``NamedSharding``: used as given; its
    spec's first entry names the mesh axes that split the batch.
    """
    if isinstance(sharding, str):
        if sharding != "auto":
            raise ValueError(f"sharding must be None, 'auto', a Mesh or a NamedSharding; got {sharding!r}.")
        mesh = Mesh(np.asarray(jax.devices()), (_BATCH_AXIS,))
        return NamedSharding(mesh, PartitionSpec(_BATCH_AXIS))
    if isinstance(sharding, Mesh):
        return NamedSharding(sharding, PartitionSpec(tuple(sharding.axis_names)))
    if isinstance(sharding, NamedSharding):
        _spec_axes(sharding)
        return sharding
    raise TypeError(
        "sharding must be None, 'auto', a jax.sharding.Mesh or a jax.sharding.NamedSharding; "
        f"got {type(sharding).__name__}."
    )


def _num_shards(sharding: NamedSharding) -> int:
    return math.prod(sharding.mesh.shape[a] for a in _spec_axes(sharding))


def _pad(x, pad):
    if pad == 0:
        return x
    return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)], axis=0)


def _constrain(tree, sharding):
    def place(x):
        if isinstance(x, jax.Array) and x.ndim >= 1:
            return jax.lax.with_sharding_constraint(x, sharding)
        return x

    return jax.tree.map(place, tree)


@compilation.filter_jit
def _run_batch(
    system, q0, qd0, ts, batched_args, shared_args, q_axis, qd_axis, kwargs, out_sharding, initial_check
):
    """The vmapped simulation; with ``initial_check = (t0, tolerance)`` also every member's
    initial-state diagnostics, returned as values for the host to raise (no callback)."""
    # The trajectory's non-array leaves (the system's functions, an eqx.nn.MLP's activation in
    # args) go around vmap, which maps arrays only.
    box = {}

    def one(q, qd, member_args):
        member_args = eqx.combine(member_args, shared_args)
        traj, box["static"] = eqx.partition(
            simulate(system, q, qd, ts, args=member_args, **kwargs), eqx.is_array
        )
        if initial_check is None:
            return traj, None
        t0, tolerance = initial_check
        return traj, checking.initial_state_diagnostics(system, q, qd, t0, member_args, tolerance)

    out, diagnostics = jax.vmap(one, in_axes=(q_axis, qd_axis, 0))(q0, qd0, batched_args)
    out = eqx.combine(out, box["static"])
    if out_sharding is not None:
        # The inputs arrive sharded along the batch axis; XLA's SPMD partitioner propagates that
        # through the vmapped program, so each device integrates its slice. (The batched solver
        # loop still agrees across devices on when to stop: a scalar all-reduce per step. A
        # shard_map with one loop per device would avoid it, but lineax's structure check fails
        # under shard_map for the event root finder, so events would not work.)
        out = _constrain(out, out_sharding)
    return out, diagnostics


def simulate_batch(
    system: System,
    q0: Float[ArrayLike, "*batch n"],
    qd0: Float[ArrayLike, "*batch n"],
    ts: Float[ArrayLike, "*batch times"] | None = None,
    *,
    args: Args = None,
    args_axes: PyTree[int | None] = None,
    sharding: str | Mesh | NamedSharding | None = None,
    method: AbstractBatchMethod | None = None,
    t0: RealScalarLike | None = None,
    t1: RealScalarLike | None = None,
    solver: diffrax.AbstractSolver | None = None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    dt0: RealScalarLike | None = None,
    saveat: diffrax.SaveAt | None = None,
    max_steps: int | None = 2**16,
    adjoint: diffrax.AbstractAdjoint | ForwardSensitivities | None = None,
    event: diffrax.Event | None = None,
    throw: bool = True,
    progress_meter: diffrax.AbstractProgressMeter | None = None,
    baumgarte: Baumgarte | None = None,
    projection: Projection | None = Projection(),
    checks: Checks = Checks(),
    events: Events | Event | Sequence[Event] = Events(),
) -> Trajectory:
    """Simulate a batch of initial states and/or parameters in one compiled, vmapped call.

    **Arguments:**

    - ``system``: a :class:`~jaxlag.System` (shared by the whole batch).
    - ``q0``, ``qd0``: ``(B, n)`` per-member initial states, or ``(n,)`` shared by all members.
    - ``ts``: save times ``(T,)``, shared (or ``t0``/``t1``/``saveat``).
    - ``args``: parameters, any pytree.
    - ``args_axes``: which ``args`` leaves carry the batch axis, in the style of ``jax.vmap``'s
      ``in_axes``: ``None`` (default: all shared), ``0`` (every leaf has a leading axis of
      length ``B``), or a pytree prefix of ``args`` with ``0``/``None`` entries, e.g.
      ``{"g": 0, "l": None}``.
    - ``sharding``: ``None`` (one device), ``"auto"`` (split the batch over all devices of
      ``jax.devices()``), a :class:`jax.sharding.Mesh` (split over all its axes) or a
      :class:`jax.sharding.NamedSharding` whose spec's first entry splits the batch axis. The
      batch is padded to a multiple of the number of shards and un-padded on return.
    - ``method``: :class:`~jaxlag.Vmap` (``jl.Vmap()``: ``jax.vmap`` of
      :func:`~jaxlag.simulate`: every option, events, unilateral constraints),
      :class:`~jaxlag.Ensemble` (``jl.Ensemble(backend="auto")``: one batched Runge–Kutta loop
      for the whole batch, :mod:`jaxlag._batch.ensemble`: explicit tableau solvers, constant or PID
      steps; ``ts`` may then also be per member, ``(B, T)``; ``backend`` ``"xla"``,
      ``"pallas"``, ``"pallas-interpret"`` or ``"auto"``) or ``None`` (default): ``jl.Ensemble()``
      on an accelerator (GPU/TPU) for constant steps whose step divides the save intervals (the
      result equals the vmap one to rounding), ``jl.Vmap()`` otherwise, in particular always on
      CPU.
    - ``t0``, ``t1``, ``solver``, ``stepsize_controller``, ``dt0``, ``saveat``, ``max_steps``,
      ``adjoint``, ``event``, ``throw``, ``progress_meter``, ``baumgarte``, ``projection``,
      ``checks`` (a :class:`~jaxlag.Checks`) and ``events`` (a :class:`~jaxlag.Events`): the
      options of :func:`~jaxlag.simulate`, with its defaults, applied to every member.

    Returns a :class:`~jaxlag.Trajectory` whose leaves all have a leading batch axis ``B``
    (``q``: ``(B, T, n)``), exactly what ``jax.vmap`` of ``simulate`` gives; its derived
    quantities (``energy``, ``multipliers``, ...) are batched too. With a sharding, the arrays
    are sharded over the devices along that axis.

    The call is compiled once per shape: a second call with new initial states or parameter
    values (same ``B``) reuses the compiled program. The checks of ``simulate`` apply to every
    member: with concrete inputs and plain save times ``ts`` the save times are checked on the
    host and each member's initial-state diagnostics are returned by the program, so that the
    message names the first bad member and the program holds no host callback (JAX's
    persistent cache stores it); under an enclosing ``jit`` they are compiled in.
    """
    q0, qd0 = as_float_state(q0, qd0)
    for name, x in (("q0", q0), ("qd0", qd0)):
        if x.ndim not in (1, 2):
            raise ValueError(
                f"{name} must have shape (B, n) (one row per batch member) or (n,) (shared); got {x.shape}."
            )
    args = as_array_leaves(args, q0.dtype)
    mask = _batched_mask(args, args_axes)
    batched_args, shared_args = eqx.partition(args, mask)

    sizes = {}
    if q0.ndim == 2:
        sizes["q0"] = q0.shape[0]
    if qd0.ndim == 2:
        sizes["qd0"] = qd0.shape[0]
    for path, leaf in jax.tree_util.tree_leaves_with_path(batched_args):
        shape = jnp.shape(leaf)
        if len(shape) == 0:
            raise ValueError(
                f"args{jax.tree_util.keystr(path)} is marked batched by args_axes but is a scalar."
            )
        sizes[f"args{jax.tree_util.keystr(path)}"] = shape[0]
    if ts is not None and jnp.ndim(ts) == 2:  # per-member save times (method=jl.Ensemble())
        sizes["ts"] = jnp.shape(ts)[0]
    if not sizes:
        raise ValueError(
            "Nothing to batch: give q0 or qd0 of shape (B, n), or mark args leaves with args_axes."
            + checking.unmarked_batch_hint(args, args_axes)
        )
    if len(set(sizes.values())) != 1:
        raise ValueError(f"Inconsistent batch sizes along the leading axis: {sizes}.")
    size = next(iter(sizes.values()))
    if size == 0:
        raise ValueError("The batch is empty (B = 0).")

    if method is not None and not isinstance(method, AbstractBatchMethod):
        raise TypeError(f"method must be jl.Vmap(), jl.Ensemble(...) or None; got {method!r}.")
    if solver is not None:  # the default, diffrax.Tsit5(), has an error estimate
        controller = (
            stepsize_controller
            if stepsize_controller is not None
            else diffrax.PIDController(rtol=1e-10, atol=1e-10)
        )
        check_solver_controller(solver, controller, default_controller=stepsize_controller is None)
    if not isinstance(checks, Checks):
        raise TypeError(f"checks must be a jl.Checks; got {type(checks).__name__}.")
    options = dict(
        t0=t0,
        t1=t1,
        solver=solver,
        stepsize_controller=stepsize_controller,
        dt0=dt0,
        saveat=saveat,
        max_steps=max_steps,
        adjoint=adjoint,
        event=event,
        throw=throw,
        progress_meter=progress_meter,
        baumgarte=baumgarte,
        projection=as_projection(projection, system),
        checks=checks,
        events=as_events(events),
    )
    if method is None:
        method = Ensemble() if _ensemble_by_default(system, ts, options) else Vmap()
    if ts is not None:
        ts = as_jax_array(ts, q0.dtype)
        if ts.ndim == 2 and isinstance(method, Vmap):
            raise ValueError(f"Per-member save times ts of shape {ts.shape} need method=jl.Ensemble().")

    out_sharding, pad = None, 0
    if sharding is not None:
        out_sharding = batch_sharding(sharding)
        shards = _num_shards(out_sharding)
        pad = -size % shards
        replicated = NamedSharding(out_sharding.mesh, PartitionSpec())

        def place_batched(x):
            return jax.device_put(_pad(x, pad), out_sharding)

        def place_shared(x):
            return jax.device_put(x, replicated) if isinstance(x, jax.Array) else x

        q0 = cast(jax.Array, place_batched(q0) if q0.ndim == 2 else place_shared(q0))
        qd0 = cast(jax.Array, place_batched(qd0) if qd0.ndim == 2 else place_shared(qd0))
        batched_args = jax.tree.map(place_batched, batched_args)
        shared_args = jax.tree.map(place_shared, shared_args)
        if ts is not None:
            ts = place_batched(ts) if ts.ndim == 2 else place_shared(ts)

    if isinstance(method, Ensemble):
        out = run_ensemble(
            system,
            q0,
            qd0,
            ts,
            batched_args,
            shared_args,
            size + pad,
            options,
            out_sharding,
            method.backend,
        )
        if pad:
            out = jax.tree.map(lambda x: x[:size] if isinstance(x, jax.Array) else x, out)
        return _raise_for_failed_members(out, throw, system, batched_args, shared_args)

    # Members fail on their own (traj.failure per member); the batch raises once, below, naming
    # the failed members, or not at all with throw=False.
    concrete = is_concrete((q0, qd0, ts, batched_args, shared_args))
    initial_check = None
    if concrete and _checked_on_host(ts, options):
        text = save_times_message(np.asarray(ts))
        if text is not None:
            raise ValueError(text)
        checks = dataclasses.replace(checks, times=False)
        if checks.initial_state:
            initial_check = (np.asarray(ts)[0], float(checks.tolerance(q0.dtype)))
            checks = dataclasses.replace(checks, initial_state=False)
    run_kwargs = {**options, "checks": checks, "throw": False}
    out, diagnostics = _run_batch(
        system,
        q0,
        qd0,
        ts,
        batched_args,
        shared_args,
        0 if q0.ndim == 2 else None,
        0 if qd0.ndim == 2 else None,
        run_kwargs,
        out_sharding,
        initial_check,
    )
    if concrete:  # compiled initial-state checks raise while we wait for the result
        jax.block_until_ready(out.failure.code)
    if pad:
        out, diagnostics = jax.tree.map(
            lambda x: x[:size] if isinstance(x, jax.Array) else x, (out, diagnostics)
        )
    if initial_check is not None:
        checking.raise_for_initial_states(system, diagnostics, args, initial_check[1])
    return _raise_for_failed_members(out, throw, system, batched_args, shared_args)


def _raise_for_failed_members(out: Trajectory, throw: bool, system, batched_args, shared_args) -> Trajectory:
    """``throw=True``: raise :class:`~jaxlag.SimulationError` naming the first failed member
    (eagerly, with its numbers and diagnosis), or compile the check in under a transformation."""
    if not throw or out.failure is None:
        return out
    if not is_concrete(out.failure):
        # The record carries no derivative: under jax.grad its integer code would otherwise
        # reach equinox's unvmap_max with a tangent, which has no differentiation rule.
        failure = jax.lax.stop_gradient(out.failure)
        # Every floating-point output, and (failures.error_if_failed) their derivatives: a
        # program that reads only an event time or only a gradient keeps the check.
        outputs, rest = eqx.partition(out, eqx.is_inexact_array)
        return eqx.combine(failures.error_if_failed(failure, outputs), rest)
    if out.failure.code.is_fully_addressable:
        if is_concrete((batched_args, shared_args)):
            member_args = _member_args(batched_args, shared_args)
            failures.raise_if_failed(out.failure, system, member_args, args_batched=True)
        else:  # a concrete record of traced parameters (jax.jacfwd): no diagnosis at the state
            failures.raise_if_failed(out.failure)
    else:
        # Several hosts: each process can read only its own rows; it raises for those.
        _raise_for_local_members(out.failure)
    return out


def _checked_on_host(ts, options: dict) -> bool:
    """Whether the batch's checks can run on the host: plain save times ``ts`` (no ``t0``,
    ``t1``, ``saveat`` or ``dt0`` of another sign) and one process (every row readable)."""
    if ts is None or any(options[k] is not None for k in ("t0", "t1", "saveat")):
        return False
    dt0 = options["dt0"]
    if dt0 is not None and not (is_concrete(dt0) and float(dt0) >= 0):
        return False
    return jax.process_count() == 1


def _raise_for_local_members(failure) -> None:
    for shard in failure.code.addressable_shards:
        codes = np.asarray(shard.data)
        if np.any(codes != failures.NONE):
            rows = shard.index[0]
            bad = [int(i) + (rows.start or 0) for i in np.nonzero(codes != failures.NONE)[0]]
            raise failures.SimulationError(
                f"Batch members {bad} (on this process) did not complete: failure codes "
                f"{codes[codes != failures.NONE].tolist()} (1 non-finite, 2 max_steps, 3 solver, "
                "4 max_segments, 5 step size collapsed). Pass throw=False and read "
                "traj.failure.code.addressable_shards (or gather it) for the details."
            )


def _member_args(batched_args, shared_args):
    """Host args with a leading batch axis on the batched leaves and size 1 on the shared ones
    (the layout :func:`jaxlag._errors.member` indexes)."""
    batched = jax.tree.map(np.asarray, batched_args)
    shared = jax.tree.map(lambda x: np.asarray(x)[None] if eqx.is_array_like(x) else x, shared_args)
    return eqx.combine(batched, shared)
