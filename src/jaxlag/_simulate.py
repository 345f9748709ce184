"""``simulate``: integrate a [`System`][jaxlag.System] with ``diffrax.diffeqsolve``."""

import dataclasses
import functools as ft
from collections.abc import Sequence
from typing import cast

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from . import _compile as compilation
from . import _diagnosis
from . import _errors as failures
from ._adjoint import (
    AbstractPushingRun,
    ForwardSensitivities,
    call_with_forward_sensitivities,
    captures_traced_values,
    trace_outputs,
)
from ._checks import Checks, initial_refusal, validate_initial_state
from ._conventions import as_array_leaves, as_float_state, as_jax_array
from ._custom_types import Args, Coordinates, RealScalarLike, SaveTimes, Validated, Velocities
from ._events import Event, Events, as_events
from ._inputs import controller_for_args
from ._mechanics.constant_mass import with_constant_mass
from ._misc import is_concrete
from ._segment_loop import solve_segments
from ._simulation_inputs import SimulationInputs
from ._solver import tangent_solve, unit_time
from ._solver.guard import guard, saving_guard_state
from ._solver.save_times import checked_save_times, save_checked_state, solve_saving_times
from ._solver.step_once import StepOnce
from ._solver.validation import check_solver_controller
from ._stabilization import (
    Baumgarte,
    Projection,
    stages_for_adjoint,
    stages_for_forward_mode,
    wrap_for_projection,
)
from ._system import System
from ._tolerances import default_solver_tolerance
from ._trajectory import Trajectory
from ._vector_field import EquationsOfMotion


def save_times_message(ts) -> str | None:
    """Why the (host, possibly batched) save times are unusable, or None."""
    ts = np.asarray(ts)
    flat = ts.reshape(-1, ts.shape[-1]) if ts.ndim else ts.reshape(1, 1)
    for row in flat:
        steps = np.diff(row)
        if not np.all(steps > 0):
            k = int(np.argmax(~(steps > 0)))
            return (
                f"ts must be strictly increasing and finite; ts[{k}] = {row[k]:g} is followed "
                f"by ts[{k + 1}] = {row[k + 1]:g}."
            )
    return None


_SAVE_TIMES = (
    "jaxlag: ts must be strictly increasing and finite (checked inside a compiled program: "
    "call outside jit/vmap/grad to see which entry)."
)
_SAVE_Y = diffrax.SubSaveAt(t1=True).fn  # diffrax's default: save the state as it is


def _as_time(t, dtype):
    """A time as a 0-d array; concrete values stay on the host (NumPy) until the compiled call,
    which transfers them with the other inputs instead of one eager device operation each."""
    if isinstance(t, jax.Array):  # also every tracer
        return jnp.asarray(t, dtype=dtype)
    return np.asarray(t, dtype=dtype)


def _prepare(system, q0, qd0, t0, args, solver, baumgarte, projection, adjoint):
    """What the solver loop integrates: ``(system, solver, term)`` with a state-independent
    ``M`` found and inverted once (`jaxlag._mechanics.constant_mass`) and the solver wrapped for the
    projection."""
    # A state-independent M (Cartesian particles) is inverted once here, not at every step.
    fast = with_constant_mass(system, q0, qd0, t0, args)
    if projection is not None:
        solver = wrap_for_projection(solver, fast, projection, adjoint)
    return fast, solver, diffrax.ODETerm(EquationsOfMotion(fast, baumgarte))


def _integrate(
    term,
    solver,
    t0,
    t1,
    dt0,
    y0,
    args,
    saveat,
    controller,
    adjoint,
    event,
    max_steps,
    progress_meter,
    with_tangents=False,
):
    """``diffrax.diffeqsolve`` without diffrax's exceptions: failures are recorded (`jaxlag._errors`).
    ``with_tangents``: ``solver`` is a `TangentSolver` and ``y0``
    carries tangents, which the (guarded) ``controller`` is kept from seeing."""
    saveat = saving_guard_state(saveat)
    save_times = checked_save_times(saveat)
    clock = None
    applies = unit_time.unit_time_applies(solver, controller, saveat, adjoint, event, (save_checked_state,))
    if applies and unit_time.default_time_dtype(t0):
        # diffrax integrates s in [0, 1] (constants): its t1 threshold folds away (jaxlag._solver.unit_time)
        clock = unit_time.Clock(jnp.asarray(t0), jnp.asarray(t1, jnp.asarray(t0).dtype))
        solver = unit_time.UnitTimeSolver(solver, clock)
        controller = unit_time.unit_time_controller(controller, clock)
        t0, t1 = unit_time.unit_interval()
    if with_tangents:
        controller = tangent_solve.primal_step_sizes(controller)
    solve = diffrax.diffeqsolve
    if save_times is not None:  # checked by simulate: without diffrax's run-time checks (host callbacks)
        solve = ft.partial(solve_saving_times, save_times, clock=clock)
    solution = solve(
        terms=term,
        solver=solver,
        t0=t0,
        t1=t1,
        dt0=dt0,
        y0=y0,
        args=args,
        saveat=saveat,
        stepsize_controller=controller,
        adjoint=adjoint,
        event=event,
        max_steps=max_steps,
        throw=False,
        progress_meter=progress_meter,
    )
    if clock is None or save_times is not None:
        return solution
    return unit_time.real_time_solution(solution, clock)


def _finish(system, fast, projection, solution, ys, t0, t1, q0, qd0, args, max_steps):
    """The `Trajectory` of a solve whose saved states are ``ys``."""
    q, qd = ys
    if projection is not None:
        # Saved values between steps come from the solver's interpolant: project them too.
        q, qd = jax.vmap(lambda t, x, v: projection(fast, x, v, t, args))(solution.ts, q, qd)
        # Saves the run did not reach (a failure, a terminal event) stay inf, not NaN.
        reached = jnp.isfinite(solution.ts)[:, None]
        q, qd = jnp.where(reached, q, jnp.inf), jnp.where(reached, qd, jnp.inf)
    failure = failures.from_solution(solution, t0, t1, q0, qd0, solution.ts, q, qd, max_steps)
    return Trajectory.from_states(
        system,
        solution.ts,
        q,
        qd,
        args,
        stats=solution.stats,
        result=solution.result,
        failure=failure,
    )


class _SolveArguments(eqx.Module):
    """What `_solve` integrates: the inputs of the run and its options, by name. The arrays
    are the program's inputs; everything else (functions, options, shapes) is static."""

    system: System
    q0: Float[Array, " n"]
    qd0: Float[Array, " n"]
    t0: RealScalarLike  # as in SimulationInputs: NumPy while concrete
    t1: RealScalarLike
    dt0: RealScalarLike | None
    args: PyTree
    solver: diffrax.AbstractSolver
    stepsize_controller: diffrax.AbstractStepSizeController
    saveat: diffrax.SaveAt
    max_steps: int | None
    adjoint: diffrax.AbstractAdjoint
    event: diffrax.Event | None
    progress_meter: diffrax.AbstractProgressMeter
    baumgarte: Baumgarte | None
    projection: Projection | None
    check: bool
    tolerance: float | Float[Array, ""]


@compilation.filter_jit
def _solve(arguments: _SolveArguments, compiled: failures.AbstractOnFailure) -> Trajectory:
    """The plain solve (no events) of ``arguments`` as one program, its checks compiled as
    ``compiled`` says."""
    with failures.on_failure(compiled):  # for the checks inside the user's functions
        return _solve_checked(arguments)


def _solve_checked(a: _SolveArguments) -> Trajectory:
    """The body of `_solve`."""
    q0, qd0, args = a.q0, a.qd0, a.args
    a.system.check(q0, qd0, a.t0, args)  # shapes only: runs once per compilation
    if a.check:
        q0, qd0 = validate_initial_state(a.system, q0, qd0, a.t0, args, a.tolerance)
    solver = stages_for_adjoint(a.solver, a.adjoint)  # diffrax does not see it through StepOnce
    fast, solver, term = _prepare(a.system, q0, qd0, a.t0, args, solver, a.baumgarte, a.projection, a.adjoint)
    solver = StepOnce(solver)
    # Failures are recorded (jaxlag._errors), not thrown by diffrax: simulate raises with the
    # numbers and a diagnosis instead of "max_steps reached" after 65,536 rejected NaN steps.
    controller = guard(a.stepsize_controller, a.dt0)  # diffrax's own dt0 check is a host callback
    solution = _integrate(
        term,
        solver,
        a.t0,
        a.t1,
        None,
        (q0, qd0),
        args,
        a.saveat,
        controller,
        a.adjoint,
        a.event,
        a.max_steps,
        a.progress_meter,
    )
    return _finish(
        a.system, fast, a.projection, solution, solution.ys, a.t0, a.t1, q0, qd0, args, a.max_steps
    )


# The inputs that the solver steps see: the only ones the one-loop tangent solve may perturb.
_STEPPED = frozenset({"system", "q0", "qd0", "args", "baumgarte", "projection"})


def _user_functions(inputs: SimulationInputs):
    """Every function of the system (Lagrangian, constraints, dissipation, forces) evaluated
    once at the initial state, for `captures_traced_values`: the solver loop calls
    nothing else that a user wrote (the solver, controller and projection are diffrax's and
    jaxlag's modules, whose arrays are inputs, not captured values)."""
    system, q0, qd0, t0, args = inputs.system, inputs.q0, inputs.qd0, inputs.t0, inputs.args
    state = {
        "lagrangian": (q0, qd0),
        "holonomic": (q0,),
        "velocity_constraints": (q0, qd0),
        "dissipation": (q0, qd0),
        "forces": (q0, qd0),
    }
    called = [
        getattr(system, name)(*values, t=t0, args=args)
        for name, values in state.items()
        if getattr(system, name) is not None
    ]
    if system.actuation is not None and system.control is not None:  # u = control(...), then Q_u
        u = system.control(q0, qd0, t=t0, args=args)
        called += [u, system.actuation(q0, qd0, u, t=t0, args=args)]
    return called


@compilation.filter_jit
def _solve_with_tangents(run, static, primals, tangents, axes, structure):
    """The solve of `_solve` (``run``'s, not segmented) and its derivatives along k
    directions in one solver loop (`jaxlag._solver.tangent_solve`): ``(outputs, tangents,
    rest)`` as ``jax.vmap(jax.jvp(...))`` of ``run`` gives them (`jaxlag._adjoint`),
    the outputs' inexact leaves, their k tangents (leading axis) and the other leaves.

    ``primals``: the inexact leaves of the inputs (structure ``structure``, the rest in
    ``static``); ``tangents``: one per leaf, k leading where ``axes`` says 0, else not batched.
    Only the inputs that the solver steps see may be perturbed (not times, not the controller):
    `_Run.solves_with_tangents` decides."""
    with failures.on_failure(run.compiled):  # for the checks inside the user's functions
        return _solve_with_tangents_checked(run, static, primals, tangents, axes, structure)


def _solve_with_tangents_checked(run, static, primals, tangents, axes, structure):
    """The body of `_solve_with_tangents`."""
    leaves = jax.tree.leaves(primals)
    axes = list(axes)

    def inputs_of(values):
        return eqx.combine(jax.tree.unflatten(structure, values), static)

    inputs = inputs_of(leaves)
    inputs.system.check(inputs.q0, inputs.qd0, inputs.t0, inputs.args)  # shapes only: once per compilation
    forward = diffrax.ForwardMode()

    def prepared(values):
        i = inputs_of(values)
        solver = stages_for_forward_mode(i.solver)
        _, solver, term = _prepare(
            i.system, i.q0, i.qd0, i.t0, i.args, solver, i.baumgarte, i.projection, forward
        )
        return tangent_solve.partition_inexact((solver, term, (i.q0, i.qd0), i.args))

    pieces, piece_tangents, piece_static = tangent_solve.push(
        prepared, (leaves,), (tangents,), in_axes=(axes,)
    )
    solver, term, y0, _ = eqx.combine(pieces, piece_static)
    solver_tangent, term_tangent, y0_tangent, args_tangent = piece_tangents
    # The projected solver's system (M found constant, from the parameters) has tangents too.
    projected = getattr(solver_tangent, "system", None) if inputs.projection is not None else None
    stepper = tangent_solve.TangentSolver(solver, projected)
    controller = guard(inputs.stepsize_controller, inputs.dt0)  # diffrax's dt0 check: a host callback
    variational = tangent_solve.TangentTerm(term, term_tangent, args_tangent)
    solution = _integrate(
        variational,
        stepper,
        inputs.t0,
        inputs.t1,
        None,
        (y0, y0_tangent),
        inputs.args,
        inputs.saveat,
        controller,
        forward,
        None,
        run.max_steps,
        run.progress_meter,
        with_tangents=True,
    )
    if solution.ys is None:  # inputs.saveat saves states
        raise RuntimeError("jaxlag: diffrax returned no saved states.")
    ys, ys_tangent = solution.ys
    ys_tangent = jax.tree.map(lambda x: jnp.moveaxis(x, 1, 0), ys_tangent)  # (k, T, ...)
    term_dyn, term_static = tangent_solve.partition_inexact(term)

    def finished(values, term_values, ys):
        i = inputs_of(values)
        fast = eqx.combine(term_values, term_static).vector_field.system
        trajectory = _finish(
            i.system, fast, i.projection, solution, ys, i.t0, i.t1, i.q0, i.qd0, i.args, run.max_steps
        )
        return eqx.partition(trajectory, eqx.is_inexact_array)

    return tangent_solve.push(
        finished, (leaves, term_dyn, ys), (tangents, term_tangent, ys_tangent), in_axes=(axes, 0, 0)
    )


class _Run(AbstractPushingRun):
    """The simulation as a function of its inputs and the adjoint: ``run(inputs, adjoint)``.

    A module, not a closure, so that it compares equal across ``simulate`` calls with the same
    options: the forward-sensitivity program of ``jax.grad`` is compiled once and reused.
    """

    segmented: bool = eqx.field(static=True)
    max_steps: int | None = eqx.field(static=True)
    progress_meter: diffrax.AbstractProgressMeter
    check: bool = eqx.field(static=True)
    tolerance: float | Float[Array, ""]
    # What the compiled checks do (jl.Checks(compiled=...)): part of every program's key.
    compiled: failures.AbstractOnFailure = eqx.field(static=True)

    def may_solve_with_tangents(self, inputs: SimulationInputs) -> bool:
        """Whether `solves_with_tangents` holds for some perturbed inputs (those of the
        steps): the run's options allow the tangent solve."""
        return self.solves_with_tangents(inputs, None)

    def solves_with_tangents(self, inputs: SimulationInputs, perturbed) -> bool:
        """Whether `_solve_with_tangents` gives this run's forward sensitivities when the
        inexact input leaves flagged in ``perturbed`` (a list in leaf order) are differentiated:
        a plain solve (no events), an explicit Runge–Kutta solver, a guarded controller, states
        saved as they are, and no perturbed time, save time, solver, controller or progress
        meter."""
        if self.segmented or inputs.event is not None or inputs.events.conditions:
            return False
        # An explicit Runge–Kutta method (Euler included), not wrapped: its step of the
        # variational equations is exactly the jvp of its step. (A wrapper may transform the
        # state nonlinearly; other solvers take the general path.)
        solver, saveat = inputs.solver, inputs.saveat
        explicit = isinstance(solver, (diffrax.AbstractERK, diffrax.Euler)) and not isinstance(
            solver, diffrax.AbstractWrappedSolver
        )
        if not explicit or isinstance(inputs.stepsize_controller, diffrax.StepTo):
            return False
        subs = jax.tree.leaves(saveat.subs, is_leaf=lambda x: isinstance(x, diffrax.SubSaveAt))
        if (
            saveat.dense
            or saveat.solver_state
            or saveat.made_jump
            or any(sub.fn is not _SAVE_Y and sub.fn is not save_checked_state for sub in subs)
        ):
            return False
        if perturbed is None:
            return True
        # The field of each inexact leaf, in the leaf order of `perturbed`.
        paths = jax.tree_util.tree_leaves_with_path(eqx.filter(inputs, eqx.is_inexact_array))
        return all(
            path[0].name in _STEPPED or not flag for (path, _), flag in zip(paths, perturbed, strict=True)
        )

    def push_along(self, primals, static, tangents, axes, structure):
        """``(outputs, tangents, rest)`` along k directions: `_solve_with_tangents`."""
        return _solve_with_tangents(self, static, primals, tangents, axes, structure)

    def __call__(self, inputs: SimulationInputs, adjoint):
        i = inputs
        if self.segmented:
            return solve_segments(inputs=i, events=i.events, run=self, adjoint=adjoint)
        arguments = _SolveArguments(
            system=i.system,
            q0=i.q0,
            qd0=i.qd0,
            t0=i.t0,
            t1=i.t1,
            dt0=i.dt0,
            args=i.args,
            solver=i.solver,
            stepsize_controller=i.stepsize_controller,
            saveat=i.saveat,
            max_steps=self.max_steps,
            adjoint=adjoint,
            event=i.event,
            progress_meter=self.progress_meter,
            baumgarte=i.baumgarte,
            projection=i.projection,
            check=self.check,
            tolerance=self.tolerance,
        )
        return _solve(arguments, self.compiled)


def simulate(
    system: System,
    q0: Coordinates,
    qd0: Velocities,
    ts: SaveTimes | None = None,
    *,
    t0: RealScalarLike | None = None,
    t1: RealScalarLike | None = None,
    args: Args = None,
    solver: diffrax.AbstractSolver | None = None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    dt0: RealScalarLike | None = None,
    saveat: diffrax.SaveAt | None = None,
    max_steps: int | None = 2**16,
    adjoint: Validated[diffrax.AbstractAdjoint | ForwardSensitivities | None] = None,
    event: diffrax.Event | None = None,
    throw: bool = True,
    progress_meter: diffrax.AbstractProgressMeter | None = None,
    baumgarte: Baumgarte | None = None,
    projection: Validated[Projection | None] = Projection(),
    checks: Validated[Checks] = Checks(),
    events: Validated[Events | Event | Sequence[Event]] = Events(),
) -> Trajectory:
    """Integrate the equations of motion of ``system`` from ``(q0, qd0)``.

    **Arguments:**

    - ``system``: a [`System`][jaxlag.System].
    - ``q0``, ``qd0``: initial coordinates and velocities, 1-D arrays of the same length n.
    - ``ts``: increasing save times; the integration runs from ``ts[0]`` to ``ts[-1]``.
      Alternatively give ``t0``, ``t1`` and a ``diffrax.SaveAt``.
    - ``args``: parameters (any pytree) passed to every user function that declares ``args``.
      An adaptive step-size controller steps onto the breakpoints of the time tables of
      `jaxlag.inputs` in ``args`` (see [`jaxlag.inputs.with_breakpoints`][jaxlag.inputs.with_breakpoints]).
    - ``checks``: a [`Checks`][jaxlag.Checks] of the input checks (default ``jl.Checks()``: all
      on). ``initial_state``: raise if ``(q0, qd0)`` is non-finite, has a singular mass matrix,
      redundant constraints, or is off the constraint manifold by more than
      ``constraint_tolerance`` (default 1e-8 in float64, ``√ε`` = 3.5e-4 in float32; see
      [`consistent_initial_state`][jaxlag.consistent_initial_state]); non-finite parameters in ``args`` are
      an error.
      ``times``: traced ``ts`` (inside ``jit``/``vmap``) are checked to increase inside the
      compiled program (and diffrax checks its save times there too); pass
      ``jl.Checks(times=False)`` when you have checked them yourself, as ``jl.fit`` does once
      on the host, so that the program has no host callback and JAX's persistent cache can
      store it. Concrete ``ts`` are always checked, on the host.
      ``compiled``: what these checks, and with ``throw=True`` the run's own failures, do when
      they fail inside a compiled program (under your ``jax.jit``, ``jax.vmap``,
      ``jax.export``): [`RaiseOnFailure`][jaxlag.RaiseOnFailure] (default) raises a static
      message through a host callback; [`NaNOnFailure`][jaxlag.NaNOnFailure] returns the
      trajectory with NaN outputs (and NaN derivatives) and ``traj.failure.code`` a
      [`FailureCode`][jaxlag.FailureCode] (``INITIAL_STATE``, ``SAVE_TIMES`` or ``PARAMETER``
      for a refused input), with no host callback in the program, so that your jitted function
      can be cached on disk and exported. E.g.
      ``jax.jit(lambda g: jl.simulate(system, q0, qd0, ts, args={"g": g},
      checks=jl.Checks(compiled=jl.NaNOnFailure())))``. Eager calls raise with the numbers
      either way.

    Every diffrax option passes through unchanged: ``solver`` (default ``diffrax.Tsit5()``),
    ``stepsize_controller`` (default ``diffrax.PIDController(rtol=1e-10, atol=1e-10)``, in
    float32 ``1.2e-5``; with a
    ``ConstantStepSize`` give ``dt0``; a solver without an error estimate, such as ``jl.RK4()``
    or ``diffrax.Euler()``, needs one: with an adaptive controller it is a ``ValueError``),
    ``dt0`` (default: chosen by the controller), ``saveat``,
    ``max_steps``, ``adjoint``, ``event``, ``throw`` and ``progress_meter``. The default adjoint,
    [`ForwardSensitivities`][jaxlag.ForwardSensitivities], gives ``jax.grad`` by forward sensitivities when
    at most
    10 scalars are differentiated and by diffrax's ``RecursiveCheckpointAdjoint`` otherwise
    (see [Differentiation modes][differentiation-modes]); for ``jax.jacfwd`` pass
    ``diffrax.ForwardMode()``.

    Constrained systems:

    - ``projection``: the [`Projection`][jaxlag.Projection] applied after every accepted step and at
      the saved times (default ``jl.Projection()``), or ``None`` for none. Ignored for a system
      without constraints.
    - ``baumgarte``: optional [`Baumgarte`][jaxlag.Baumgarte] feedback in the acceleration constraint.
    - ``throw``: on a run-time failure (non-finite equations of motion, a collapsing step size,
      ``max_steps``, ``max_segments``) raise [`SimulationError`][jaxlag.SimulationError] with the numbers
      and a diagnosis (see [Troubleshooting][a-run-that-cannot-be-completed-jlsimulationerror]);
      inside a compiled program as ``checks.compiled``
      says (raise, or NaN outputs and the code). With ``False`` return the trajectory as the
      run left it, whose ``failure`` record says what happened (``traj.raise_if_failed()``
      raises later).

    Events and unilateral constraints (see [Events and segments][events-and-segments]):

    - ``events``: a [`Events`][jaxlag.Events] of [`Event`][jaxlag.Event] conditions (terminal or
      recorded) and the options of the segmented integration, e.g.
      ``jl.Events(jl.Event(f), max_segments=16)``; a single ``jl.Event`` or a sequence of them
      is taken as ``jl.Events(*events)``.
    - If the system has ``unilateral`` constraints or there are event conditions, the motion is
      integrated in at most ``events.max_segments`` segments between switches (default 8;
      too few is a ``SimulationError`` that says how many are needed), each event located by
      ``events.root_finder`` (default ``optimistix.Newton(rtol=1e-13, atol=1e-13)``, ``√ε``
      in lower precision); the returned trajectory has ``events`` (an
      [`EventLog`][jaxlag.EventLog]), ``active`` and ``stats`` (summed over the segments) set.
      A crossing is a sign change after ``t0`` (see [`Event`][jaxlag.Event]). This mode needs
      ``ts``.

    Returns a [`Trajectory`][jaxlag.Trajectory].
    """
    if not isinstance(checks, Checks):
        raise TypeError(f"checks must be a jl.Checks; got {type(checks).__name__}.")
    # Every check compiled while simulate traces (also inside the user's functions) follows
    # checks.compiled; jaxlag's programs are cached per choice (jaxlag._compile.filter_jit).
    with failures.on_failure(checks.compiled):
        return _simulate(
            system,
            q0,
            qd0,
            ts,
            t0=t0,
            t1=t1,
            args=args,
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
            projection=projection,
            checks=checks,
            events=events,
        )


def _simulate(
    system: System,
    q0,
    qd0,
    ts,
    *,
    t0,
    t1,
    args,
    solver,
    stepsize_controller,
    dt0,
    saveat,
    max_steps,
    adjoint,
    event,
    throw: bool,
    progress_meter,
    baumgarte,
    projection,
    checks: Checks,
    events,
) -> Trajectory:
    """The body of `simulate` (its arguments checked, under its choice of compiled checks).

    With ``checks.compiled`` a `NaNOnFailure` (``records``) the checks of traced inputs are
    values: a prologue computes the refusal of the save times and of the initial state
    (`initial_refusal`), the run compiles no check, and the epilogue puts the refusal into the
    failure record (`jaxlag._errors.refused`) and, with ``throw``, NaN into the outputs of a
    run that failed or was refused."""
    compiled = checks.compiled
    # (code, index, value) of the input checks compiled as values, (q0, qd0) they refer to.
    refusals: list[tuple[jax.Array, jax.Array, jax.Array]] = []
    q0, qd0 = as_float_state(q0, qd0)
    args = as_array_leaves(args, q0.dtype)
    user_saveat = saveat is not None
    if ts is not None:
        ts = as_jax_array(ts, q0.dtype)
        if ts.ndim != 1 or ts.shape[0] < 1:
            raise ValueError(f"ts must be a non-empty 1-D array of save times; got shape {ts.shape}.")
        # Concrete save times are checked and sliced on the host: no eager device operations.
        ends = np.asarray(ts) if is_concrete(ts) else ts
        if is_concrete(ts):
            text = save_times_message(ends)
            if text is not None:
                raise ValueError(text)
        elif checks.times:  # traced save times: the same check, compiled in
            increasing = jnp.diff(ts) > 0
            if compiled.records:
                k = jnp.argmax(~increasing) if ts.shape[0] > 1 else jnp.asarray(0)
                bad = ~jnp.all(increasing)
                code = jnp.where(bad, failures.FailureCode.SAVE_TIMES, failures.FailureCode.COMPLETED)
                refusals.append((code.astype(jnp.int32), k.astype(jnp.int32), ts[k]))
                # The refused run integrates over increasing times instead (its outputs are NaN).
                ts = jnp.where(bad, _increasing_times(ts.shape[0], t0, t1, ts.dtype), ts)
                ends = ts
            else:
                ts = compiled.check(ts, ~jnp.all(increasing), 0, (_SAVE_TIMES,))
        if saveat is None and t0 is None and t1 is None:
            # Checked above (or compiled in): saved without diffrax's checks (host callbacks).
            saveat = diffrax.SaveAt(subs=diffrax.SubSaveAt(ts=cast(jax.Array, ts), fn=save_checked_state))
        elif saveat is None:
            saveat = diffrax.SaveAt(ts=cast(jax.Array, ts))  # an array since as_jax_array above
        t0 = ends[0] if t0 is None else t0
        t1 = ends[-1] if t1 is None else t1
    if t0 is None or t1 is None:
        raise ValueError("Give save times `ts`, or `t0` and `t1` (with a diffrax.SaveAt).")
    if saveat is None:
        saveat = diffrax.SaveAt(t1=True)
    t0, t1 = _as_time(t0, q0.dtype), _as_time(t1, q0.dtype)
    if dt0 is not None and is_concrete((dt0, t0, t1)):
        # (diffrax's own check is compiled in, a host callback: a traced dt0 takes the sign of
        # t1 - t0, see jaxlag._solver.guard)
        step, span = float(dt0), float(t1) - float(t0)
        if not (step * span > 0 or (span == 0 and np.isfinite(step))):
            raise ValueError(
                f"dt0 must be finite, nonzero and have the sign of t1 - t0 = {span:g}; got dt0={step!r}."
            )
    if solver is None:
        solver = diffrax.Tsit5()
    default_controller = stepsize_controller is None
    if stepsize_controller is None:
        tol = default_solver_tolerance(q0.dtype)
        stepsize_controller = diffrax.PIDController(rtol=tol, atol=tol)
    check_solver_controller(solver, stepsize_controller, default_controller=default_controller)
    # Time tables in args: step onto their breakpoints (jaxlag.inputs).
    stepsize_controller = controller_for_args(stepsize_controller, args, t0.dtype)
    constraint_tolerance = checks.tolerance(q0.dtype)
    if adjoint is None:
        adjoint = ForwardSensitivities()
    if not isinstance(adjoint, (diffrax.AbstractAdjoint, ForwardSensitivities)):
        raise TypeError(f"adjoint must be a diffrax adjoint or jl.ForwardSensitivities(); got {adjoint!r}.")
    if progress_meter is None:
        progress_meter = diffrax.NoProgressMeter()
    projection = as_projection(projection, system)
    events = as_events(events)
    segmented = bool(events.conditions) or bool(system.unilateral) or bool(system.friction)
    if segmented and (ts is None or event is not None or user_saveat):
        raise ValueError(
            "Unilateral constraints and jl.Event need save times `ts`, and neither a diffrax "
            "`event` (use jl.Event for conditions) nor a custom `saveat`."
        )
    check_in_jit = checks.initial_state
    if checks.initial_state and is_concrete((q0, qd0, t0, args)):
        # Concrete inputs: check eagerly, so that errors carry the numbers and constraint names.
        # (Returns the state threaded through compiled checks if the flags turn out traced.)
        q0, qd0 = validate_initial_state(system, q0, qd0, t0, args, constraint_tolerance)
        check_in_jit = False
    host_check = False  # ForwardSensitivities: the initial state checked inside, on the host
    if check_in_jit and compiled.records:
        # As values, in front of the run (which compiles no check): no host callback.
        refusals.append(initial_refusal(system, q0, qd0, t0, args, constraint_tolerance))
        check_in_jit, host_check = False, True
    state0 = (q0, qd0)

    run = _Run(segmented, max_steps, progress_meter, check_in_jit, constraint_tolerance, compiled)
    inputs = SimulationInputs(
        system=system,
        q0=q0,
        qd0=qd0,
        t0=t0,
        t1=t1,
        ts=cast("jax.Array | None", ts),  # as_jax_array above
        dt0=dt0,
        args=args,
        saveat=saveat,
        solver=solver,
        stepsize_controller=stepsize_controller,
        baumgarte=baumgarte,
        projection=projection,
        events=events,
        event=event,
    )
    if isinstance(adjoint, ForwardSensitivities) and not is_concrete(inputs):
        # One abstract trace: does a user function close over a traced value (a parameter of the
        # caller's grad captured in L)? A custom_vjp cannot see it, so the checkpointed adjoint
        # then differentiates the simulation as it stands. The trace also gives the output
        # shapes the forward-sensitivity rule needs.
        # The initial state is checked inside the custom_vjp, before the run, where the values
        # are concrete unless the caller itself is being traced: on the host then, and the
        # program of the forward sensitivities carries no check (JAX can cache it on disk).
        unchecked = dataclasses.replace(run, check=False)
        if unchecked.may_solve_with_tangents(inputs):
            # jax.grad will use the one-loop tangent solve, which needs no output shapes: the
            # test traces the user's functions, not the solver loop.
            captured, shapes = captures_traced_values(_user_functions, inputs), None
        else:
            captured, shapes = trace_outputs(unchecked, inputs, adjoint.inner)
        if captured:
            trajectory = run(inputs, adjoint.fallback)
        else:
            # Failures are raised inside the custom_vjp, where the record is concrete (host-side
            # check, no compiled check) unless the caller itself is being traced. Recorded
            # failures (NaNOnFailure) are put into the outputs outside it, with the refusals.
            inside = None if compiled.records else compiled
            finish = (lambda tr: _raise_if_failed(tr, tr.system, tr.args, events, inside)) if throw else None
            prepare = None
            if run.check or host_check:
                prepare = ft.partial(
                    _checked_initial_state, tolerance=constraint_tolerance, host_only=host_check
                )
            check_residuals = _check_residuals if throw and not compiled.records else None
            trajectory = call_with_forward_sensitivities(
                unchecked, inputs, adjoint, shapes, finish, prepare, check_residuals
            )
            trajectory = _with_refusals(trajectory, refusals, *state0)
            if throw and compiled.records and not is_concrete(trajectory.failure):
                return failed_outputs(trajectory, compiled)
            return trajectory
    elif isinstance(adjoint, ForwardSensitivities):
        # No traced input; a user function may still close over a value of the caller's grad,
        # which the fallback (reverse-mode) adjoint differentiates. Outside every transformation
        # nothing can be captured: the plain loop of the inner adjoint traces faster than the
        # checkpointed one (and is the one jax.grad's closure test and tangent solve share).
        plain = compilation.no_transformation_active()
        trajectory = run(inputs, adjoint.inner if plain else adjoint.fallback)
    else:
        trajectory = run(inputs, adjoint)
    trajectory = _with_refusals(trajectory, refusals, *state0)
    return _raise_if_failed(trajectory, system, args, events, compiled) if throw else trajectory


def as_projection(projection, system: System) -> Projection | None:
    """``simulate``'s ``projection=``, checked: ``None`` for a system without constraints."""
    if isinstance(projection, str):
        raise TypeError(
            f"projection must be jl.Projection() or None; got the string {projection!r} (the "
            "default, jl.Projection(), projects constrained systems and is ignored otherwise)."
        )
    return projection if system.is_constrained else None


def _checked_initial_state(inputs: SimulationInputs, tolerance, host_only: bool = False) -> SimulationInputs:
    """``inputs`` with ``(q0, qd0)`` checked (`validate_initial_state`:
    raises here for concrete values, compiles the check in otherwise; ``host_only``: traced
    values are left to the refusal that ``simulate`` computed as values)."""
    i = inputs
    if host_only and not is_concrete((i.q0, i.qd0, i.t0, i.args)):
        return inputs
    q0, qd0 = validate_initial_state(i.system, i.q0, i.qd0, i.t0, i.args, tolerance)
    return dataclasses.replace(inputs, q0=q0, qd0=qd0)


def _increasing_times(n: int, t0, t1, dtype) -> jax.Array:
    """``n`` increasing save times, from ``t0`` to ``t1`` where they are given (else
    ``0, 1, ..., n − 1``): what a run refused for its save times integrates over."""
    start = jnp.asarray(0.0 if t0 is None else t0, dtype)
    stop = start + (n - 1) if t1 is None else jnp.asarray(t1, dtype)
    return jnp.linspace(start, stop, n, dtype=dtype)


def _with_refusals(trajectory: Trajectory, refusals, q0, qd0) -> Trajectory:
    """``trajectory`` whose failure record starts with the first of the input checks compiled as
    values that failed (`jaxlag._errors.refused`), in the order they were checked."""
    if not refusals:
        return trajectory
    failure = cast(failures.Failure, trajectory.failure)
    for code, index, value in reversed(refusals):
        failure = failures.refused(failure, code, index, value, q0, qd0)
    return dataclasses.replace(trajectory, failure=failure)


def _check_residuals(trajectory: Trajectory, residuals):
    """The reverse pass's residuals, checked as the outputs are (see ``_raise_if_failed``). A
    concrete record was checked on the host already (``finish``); ``eqx.error_if`` would compile
    a program of its own even then, one holding a host callback (never cached on disk)."""
    failure = cast(failures.Failure, trajectory.failure)
    if is_concrete(failure):
        return residuals
    return failures.error_if_failed(failure, residuals)


def _raise_if_failed(
    trajectory: Trajectory,
    system: System,
    args,
    events: Events | None = None,
    compiled: failures.AbstractOnFailure | None = failures.RaiseOnFailure(),
) -> Trajectory:
    """Eagerly (concrete result: synchronous, full diagnosis) or compiled into the program as
    ``compiled`` says (``None``: not at all)."""
    failure = cast(failures.Failure, trajectory.failure)  # simulate always records how it ended
    if is_concrete(failure):
        _diagnosis.raise_if_failed(failure, system, args, events=events)
        return trajectory
    if compiled is None:
        return trajectory
    return failed_outputs(trajectory, compiled)


def failed_outputs(trajectory: Trajectory, compiled: failures.AbstractOnFailure) -> Trajectory:
    """The (traced) failure record checked on every floating-point output, not only ``q``: a
    program that reads only an event time (e.g. ``jax.grad`` of a bounce time under ``jit``)
    must not drop the check as dead code. A recorded failure (`NaNOnFailure`) leaves the
    trajectory's inputs (``args``, the system's arrays) and the record itself as they are."""
    failure = cast(failures.Failure, trajectory.failure)
    if not compiled.records:  # the record's own arrays raise too
        outputs, rest = eqx.partition(trajectory, eqx.is_inexact_array)
        return eqx.combine(compiled.outputs(failure, outputs), rest)

    # The run's outputs, not its inputs (args, the system's arrays) nor the record's numbers.
    def is_output(path, leaf) -> bool:
        return path[0].name not in _NOT_OUTPUTS and eqx.is_inexact_array(leaf)

    outputs, rest = eqx.partition(trajectory, jax.tree_util.tree_map_with_path(is_output, trajectory))
    return eqx.combine(compiled.outputs(failure, outputs), rest)


#: The fields of a Trajectory that a recorded failure leaves as they are.
_NOT_OUTPUTS = frozenset({"args", "system_arrays", "failure"})
