r"""``simulate_batch``: many simulations in one compiled call, optionally sharded across devices.

A batch is ``jax.vmap`` of [`simulate`][jaxlag.simulate] over the leading axis of the initial states
and of selected parameter leaves, compiled once with ``jax.jit``. Every member integrates the
same equations ``M q̈ = F + Jᵀλ + Aᵀμ`` with its own ``(q0, q̇0, args)``; constrained systems,
unilateral constraints and [`Event`][jaxlag.Event] s work unchanged (each member switches at its
own times).

Memory grows linearly in the batch size ``B``: the program holds ``B`` copies of the solver state
and of the saved states (``B × T × n``), nothing quadratic. Time grows linearly too, with one
caveat of ``vmap``-ed adaptive solvers: the batched solver loop runs until the *slowest* member
has finished (finished members are masked), so a batch costs ``B ×`` the largest step count in
it. Group members of similar stiffness, or use a constant step.

With ``method=jl.Ensemble()`` the batch is instead an array axis of one batched Runge–Kutta
loop ([`jaxlag.experimental.simulate_ensemble`][jaxlag.experimental.simulate_ensemble]): no per-member
solver loop, each member
with its own step size when adaptive; ``method=None`` (the default) uses it on accelerators for
constant steps and keeps ``jl.Vmap()`` everywhere else (always on CPU).

Sharding uses JAX's own machinery. With ``sharding="auto"`` the batch axis is split over every
device of ``jax.devices()`` (a 1-D `jax.sharding.Mesh` named ``"batch"``): batched inputs
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

import dataclasses
import math
from typing import cast

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import PyTree
from typing_extensions import Unpack

from .. import _checks as checking
from .. import _diagnosis
from .. import _errors as failures
from .._checks import Checks
from .._conventions import as_array_leaves, as_float_state, as_jax_array
from .._custom_types import Args, RealArrayLike, SaveTimes, Validated
from .._errors import FailureCode
from .._events import as_events
from .._misc import is_concrete
from .._options import SimulateOptions, check_option_names, default_option
from .._simulate import as_projection, failed_outputs
from .._solver.validation import check_solver_controller
from .._system import System
from .._trajectory import Trajectory
from .ensemble import Ensemble
from .methods import AbstractBatchMethod, BatchProblem
from .vmap import Vmap

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


def simulate_batch(
    system: System,
    q0: RealArrayLike,
    qd0: RealArrayLike,
    ts: SaveTimes | None = None,
    *,
    args: Args = None,
    args_axes: PyTree[int | None] = None,
    sharding: Validated[str | Mesh | NamedSharding | None] = None,
    method: Validated[AbstractBatchMethod | None] = None,
    **options: Unpack[SimulateOptions],
) -> Trajectory:
    """Simulate a batch of initial states and/or parameters in one compiled, vmapped call.

    **Arguments:**

    - ``system``: a [`System`][jaxlag.System] (shared by the whole batch).
    - ``q0``, ``qd0``: ``(B, n)`` per-member initial states, or ``(n,)`` shared by all members.
    - ``ts``: save times ``(T,)``, shared (or ``t0``/``t1``/``saveat``).
    - ``args``: parameters, any pytree.
    - ``args_axes``: which ``args`` leaves carry the batch axis, in the style of ``jax.vmap``'s
      ``in_axes``: ``None`` (default: all shared), ``0`` (every leaf has a leading axis of
      length ``B``), or a pytree prefix of ``args`` with ``0``/``None`` entries, e.g.
      ``{"g": 0, "l": None}``.
    - ``sharding``: ``None`` (one device), ``"auto"`` (split the batch over all devices of
      ``jax.devices()``), a `jax.sharding.Mesh` (split over all its axes) or a
      `jax.sharding.NamedSharding` whose spec's first entry splits the batch axis. The
      batch is padded to a multiple of the number of shards and un-padded on return.
    - ``method``: [`Vmap`][jaxlag.Vmap] (``jl.Vmap()``: ``jax.vmap`` of
      [`simulate`][jaxlag.simulate]: every option, events, unilateral constraints),
      [`Ensemble`][jaxlag.Ensemble] (``jl.Ensemble(backend="auto")``: one batched Runge–Kutta loop
      for the whole batch, [`jaxlag.experimental.simulate_ensemble`][jaxlag.experimental.simulate_ensemble]:
      explicit tableau
      solvers, constant or PID steps; ``ts`` may then also be per member, ``(B, T)``; ``backend`` ``"xla"``,
      ``"pallas"``, ``"pallas-interpret"`` or ``"auto"``) or ``None`` (default): ``jl.Ensemble()``
      on an accelerator (GPU/TPU) for constant steps whose step divides the save intervals (the
      result equals the vmap one to rounding), ``jl.Vmap()`` otherwise, in particular always on
      CPU.
    - ``**options``: the options of [`simulate`][jaxlag.simulate] (a
      [`SimulateOptions`][jaxlag.SimulateOptions]: ``t0``, ``t1``, ``solver``, ``stepsize_controller``,
      ``dt0``, ``saveat``, ``max_steps``, ``adjoint``, ``event``, ``throw``, ``progress_meter``,
      ``baumgarte``, ``projection``, ``checks`` and ``events``), with its defaults, applied to
      every member; ``throw=True`` raises once for the batch, naming the first failed member.

    Returns a [`Trajectory`][jaxlag.Trajectory] whose leaves all have a leading batch axis ``B``
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
    if ts is not None and np.ndim(ts) == 2:  # per-member save times (method=jl.Ensemble())
        sizes["ts"] = np.shape(ts)[0]
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
    options = _checked_options(system, options)
    if ts is not None:
        ts = as_jax_array(ts, q0.dtype)
    problem = BatchProblem(system, q0, qd0, ts, batched_args, shared_args, size, 0, None)
    if sharding is not None:
        problem = _placed(problem, batch_sharding(sharding))
    if method is None:
        method = _default_method(problem, options)
    compiled = default_option(options, "checks").compiled
    with failures.on_failure(compiled):  # for the checks that no option reaches (see simulate)
        out = method.simulate(problem, options)
    return _raise_for_failed_members(
        out, default_option(options, "throw"), system, batched_args, shared_args, compiled
    )


def _checked_options(system: System, options: SimulateOptions) -> SimulateOptions:
    """``options`` checked where every method needs them checked, before anything is traced:
    names, ``checks``, ``projection`` (``None`` for an unconstrained system), ``events`` and the
    solver with its controller."""
    check_option_names(options, "simulate_batch")
    options = SimulateOptions(**options)
    if not isinstance(default_option(options, "checks"), Checks):
        raise TypeError(f"checks must be a jl.Checks; got {type(options.get('checks')).__name__}.")
    if "projection" in options:
        options["projection"] = as_projection(options["projection"], system)
    if "events" in options:
        options["events"] = as_events(options["events"])
    solver, controller = options.get("solver"), options.get("stepsize_controller")
    if solver is not None:  # the default, diffrax.Tsit5(), has an error estimate
        default = controller is None
        controller = diffrax.PIDController(rtol=1e-10, atol=1e-10) if controller is None else controller
        check_solver_controller(solver, controller, default_controller=default)
    return options


def _placed(problem: BatchProblem, sharding: NamedSharding) -> BatchProblem:
    """``problem`` on the devices of ``sharding``: batched arrays split along their leading
    axis (padded to a multiple of the shards with copies of the last member), shared ones
    replicated."""
    pad = -problem.size % _num_shards(sharding)
    replicated = NamedSharding(sharding.mesh, PartitionSpec())

    def batched(x):
        return jax.device_put(_pad(x, pad), sharding)

    def shared(x):
        return jax.device_put(x, replicated) if isinstance(x, jax.Array) else x

    def either(x):
        return cast(jax.Array, batched(x) if x.ndim == 2 else shared(x))

    p = problem
    return BatchProblem(
        p.system,
        either(p.q0),
        either(p.qd0),
        None if p.ts is None else either(p.ts),
        jax.tree.map(batched, p.batched_args),
        jax.tree.map(shared, p.shared_args),
        p.size,
        pad,
        sharding,
    )


def _default_method(problem: BatchProblem, options: SimulateOptions) -> AbstractBatchMethod:
    """``method=None``: [`Vmap`][jaxlag.Vmap] on CPU; on an accelerator [`Ensemble`][jaxlag.Ensemble]
    for constant steps whose step divides the save intervals (the result equals the vmap one
    to rounding), [`Vmap`][jaxlag.Vmap] otherwise."""
    if jax.default_backend() == "cpu":
        return Vmap()
    from ..experimental._ensemble.entry import ensemble_by_default

    return Ensemble() if ensemble_by_default(problem, options) else Vmap()


def _raise_for_failed_members(
    out: Trajectory,
    throw: bool,
    system,
    batched_args,
    shared_args,
    compiled: failures.AbstractOnFailure = failures.RaiseOnFailure(),
) -> Trajectory:
    """``throw=True``: raise [`SimulationError`][jaxlag.SimulationError] naming the first failed member
    (eagerly, with its numbers and diagnosis), or compile the check in under a transformation
    as ``compiled`` says (`NaNOnFailure`: the failed members' outputs NaN)."""
    if not throw or out.failure is None:
        return out
    if not is_concrete(out.failure):
        # The record carries no derivative: under jax.grad its integer code would otherwise
        # reach equinox's unvmap_max with a tangent, which has no differentiation rule.
        failure = jax.lax.stop_gradient(out.failure)
        # Every floating-point output, and their derivatives: a program that reads only an
        # event time or only a gradient keeps the check.
        return failed_outputs(dataclasses.replace(out, failure=failure), compiled)
    if out.failure.code.is_fully_addressable:
        if is_concrete((batched_args, shared_args)):
            member_args = _member_args(batched_args, shared_args)
            _diagnosis.raise_if_failed(out.failure, system, member_args, args_batched=True)
        else:  # a concrete record of traced parameters (jax.jacfwd): no diagnosis at the state
            _diagnosis.raise_if_failed(out.failure)
    else:
        # Several hosts: each process can read only its own rows; it raises for those.
        _raise_for_local_members(out.failure)
    return out


#: "1 nonfinite, 2 max_steps, ...": the codes of jl.FailureCode, for the messages.
_CODE_NAMES = ", ".join(f"{code.value} {code.name.lower()}" for code in FailureCode if code)


def _raise_for_local_members(failure) -> None:
    for shard in failure.code.addressable_shards:
        codes = np.asarray(shard.data)
        if np.any(codes != FailureCode.COMPLETED):
            rows = shard.index[0]
            bad = [int(i) + (rows.start or 0) for i in np.nonzero(codes != FailureCode.COMPLETED)[0]]
            raise failures.SimulationError(
                f"Batch members {bad} (on this process) did not complete: failure codes "
                f"{codes[codes != FailureCode.COMPLETED].tolist()} ({_CODE_NAMES}). Pass throw=False "
                "and read traj.failure.code.addressable_shards (or gather it) for the details."
            )


def _member_args(batched_args, shared_args):
    """Host args with a leading batch axis on the batched leaves and size 1 on the shared ones
    (the layout `jaxlag._diagnosis.member` indexes)."""
    batched = jax.tree.map(np.asarray, batched_args)
    shared = jax.tree.map(lambda x: np.asarray(x)[None] if eqx.is_array_like(x) else x, shared_args)
    return eqx.combine(batched, shared)
