r"""The segment loop: integrate across releases, contacts, friction switches and user events.

A run with unilateral constraints, Coulomb contacts or user conditions (`jaxlag._events`)
is integrated in segments; each segment is one ``diffrax.diffeqsolve`` with a fixed set of
acting constraints and friction modes, ended by the first of

* release: ``min_i λ_i`` over the acting unilateral constraints reaching zero from above;
* contact: ``min_i f_i`` over the inactive ones reaching zero from above;
* a friction switch (`jaxlag._mechanics.friction_modes`);
* a crossing of a user condition ``c_k``: ``σ_k c_k`` reaching zero from above, where
  ``σ_k = ±1`` is the side ``c_k`` starts the segment on.

With user conditions or friction these are one diffrax condition, their minimum, so that the
root find on the solver's dense output locates the earliest of them even when several happen
within one solver step; which one it was is read off at the event. (Releases and contacts alone
are two diffrax conditions, as the minimum of each is already one quantity per kind.)

The segments are a ``lax.scan`` of fixed length ``max_segments``, so the whole run compiles once
and works under ``vmap`` (each member switching at its own times) and ``grad``. The scan body is
a pipeline over named Modules; each variation of the physics is an object with a "does nothing"
implementation, chosen once per run, so the loop never asks whether a feature is present:

    solve one segment      -> _solve_segment     (a SolvedSegment)
    fill the saves         -> _fill_saves
    classify the end       -> _classify          (a Crossing)
    apply a reset          -> AbstractResets     (jaxlag._mechanics.resets)
    apply the jump         -> AbstractJumpLaw    (jaxlag._mechanics.jumps: impact, projection)
    choose the next modes  -> AbstractFrictionModes (jaxlag._mechanics.friction_modes)
    the conditions' sides  -> _next_sides
    record and advance     -> _record, _advance
"""

from typing import Protocol, runtime_checkable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, PyTree

from . import _compile as compilation
from ._checks import initial_activity, validate_initial_state
from ._custom_types import RealScalarLike
from ._errors import AbstractOnFailure, Failure, FailureCode, first_failure, from_solution, on_failure
from ._events import Event, EventKind, EventLog, Events, root_finder_for
from ._mechanics.constant_mass import with_constant_mass
from ._mechanics.constraints import holonomic_residual
from ._mechanics.friction import bad_friction_coefficient
from ._mechanics.friction_modes import AbstractFrictionModes, friction_modes_for
from ._mechanics.impacts import bad_restitution, impacts_to_rest
from ._mechanics.jumps import AbstractJumpLaw, Jump, SegmentEnd, jump_law_for
from ._mechanics.resets import AbstractResets, resets_for
from ._segment_conditions import SegmentConditions, condition_dtype, condition_values, sides_from
from ._simulation_inputs import SimulationInputs
from ._solver.guard import guard
from ._solver.save_times import SaveTimes, saved_values
from ._solver.step_once import StepOnce
from ._stabilization import Baumgarte, Projection, stages_for_adjoint, wrap_for_projection
from ._system import System
from ._trajectory import Trajectory
from ._vector_field import EquationsOfMotion

_STEP_COUNTS = ("num_steps", "num_accepted_steps", "num_rejected_steps")


class _Loop(eqx.Module):
    """What every segment of one run shares: the system, the options and the feature laws."""

    system: System
    args: PyTree
    ts: Float[Array, " saves"]
    t1: Float[Array, ""]
    dt0: RealScalarLike | None
    solver: diffrax.AbstractSolver
    controller: diffrax.AbstractStepSizeController
    adjoint: diffrax.AbstractAdjoint
    progress_meter: diffrax.AbstractProgressMeter
    baumgarte: Baumgarte | None
    projection: Projection | None
    events: tuple[Event, ...]
    root_finder: optx.AbstractRootFinder
    max_steps: int | None = eqx.field(static=True)
    max_segments: int = eqx.field(static=True)
    tolerance: Float[Array, ""] | float
    unilateral: Bool[Array, " m_h"]
    zeno: float | None = eqx.field(static=True)  # Events.zeno_time (None: the default rule)
    friction: AbstractFrictionModes
    resets: AbstractResets
    jumps: AbstractJumpLaw

    def departing(self, carry: "_SegmentCarry") -> Bool[Array, " m_h"] | None:
        """The inactive unilateral rows that touch at the start of a segment (``None``: no
        holonomic row)."""
        if not self.unilateral.shape[0]:
            return None
        f = holonomic_residual(self.system, carry.q, carry.t, self.args)
        return self.unilateral & ~carry.active & (f <= self.tolerance)

    def segment(self, active, t_start, sides, modes, departing=None) -> SegmentConditions:
        return SegmentConditions(
            self.system, self.events, self.friction, self.unilateral, active, t_start, sides, departing, modes
        )


class _SegmentCarry(eqx.Module):
    """What one segment hands to the next (the ``lax.scan`` carry)."""

    t: Float[Array, ""]  # the segment's start (t1 once done)
    q: Float[Array, " n"]
    qd: Float[Array, " n"]
    active: Bool[Array, " m_h"]  # acting holonomic rows
    modes: Float[Array, " k"]  # friction modes: 0 stick, ±1 slip
    done: Bool[Array, ""]
    sides: Float[Array, " e"]  # the side of each user condition
    out_q: Float[Array, "saves n"]  # the saves filled so far, inf elsewhere
    out_qd: Float[Array, "saves n"]
    out_active: Bool[Array, "saves m_h"]
    out_modes: Float[Array, "saves k"]
    filled: Bool[Array, " saves"]
    count: Int[Array, ""]  # events that happened
    failure: Failure
    steps: dict[str, Int[Array, ""]]  # diffrax's step counts, summed


class _SegmentRecord(eqx.Module):
    """What one segment leaves in the [`EventLog`][jaxlag.EventLog] (one row of the scan output)."""

    time: Float[Array, ""]
    kind: Int[Array, ""]
    index: Int[Array, ""]
    q: Float[Array, " n"]
    qd: Float[Array, " n"]
    active: Bool[Array, " m_h"]
    impulses: Float[Array, " m_h"]
    modes: Int[Array, " k"]


class _SolvedSegment(eqx.Module):
    """One segment's solve: where it ended, its saves and how it ended."""

    t: Float[Array, ""]
    q: Float[Array, " n"]
    qd: Float[Array, " n"]
    saved_q: Float[Array, "saves n"]
    saved_qd: Float[Array, "saves n"]
    fired: tuple[Bool[Array, ""], ...]  # diffrax's event mask (one or two conditions)
    failure: Failure  # the run's first failure so far
    broken: Bool[Array, ""]  # the run has failed: this segment's end is no state of the motion
    stats: dict[str, Int[Array, ""]]


class _Crossing(eqx.Module):
    """What ended a segment: which switch, and for a user condition which one and how."""

    released: Bool[Array, ""]
    contacted: Bool[Array, ""]
    frictioned: Bool[Array, ""]
    user_hit: Bool[Array, ""]  # a user condition crossed (recorded or not)
    recorded: Bool[Array, ""]  # ... in a direction it records
    silent: Bool[Array, ""]  # ... in the direction it ignores
    stop: Bool[Array, ""]  # ... and it is terminal
    user_index: Int[Array, ""]
    side: Float[Array, ""]  # the side the crossed condition was on
    residual: Float[Array, ""]  # |the switch quantity| at the located event


def _solve_segment(loop: _Loop, carry: _SegmentCarry, segment: SegmentConditions) -> _SolvedSegment:
    """One ``diffeqsolve`` from the carry's state to the first switch (or ``t1``)."""
    solver = stages_for_adjoint(loop.solver, loop.adjoint)  # diffrax does not see it in StepOnce
    if loop.projection is not None:
        solver = wrap_for_projection(solver, loop.system, loop.projection, loop.adjoint, carry.active)
    # The save times through SaveTimes and dt0 through the guard: diffrax's own checks of them
    # are compiled in as host callbacks, which keep the program out of JAX's persistent cache.
    save_ts = jnp.clip(loop.ts, carry.t, loop.t1)
    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(EquationsOfMotion(loop.system, loop.baumgarte, carry.active, carry.modes)),
        SaveTimes.for_adjoint(StepOnce(solver), save_ts, loop.adjoint),  # StepOnce: traced once
        carry.t,
        loop.t1,
        None,
        (carry.q, carry.qd),
        loop.args,
        saveat=diffrax.SaveAt(t1=True, solver_state=True, controller_state=True),
        stepsize_controller=guard(loop.controller, loop.dt0),
        adjoint=loop.adjoint,
        event=segment.diffrax_event(loop.root_finder),
        max_steps=loop.max_steps,
        throw=False,  # recorded in `failure`; simulate raises (jaxlag._errors)
        progress_meter=loop.progress_meter,
    )
    if solution.ts is None or solution.ys is None:  # the SaveAt above saves both
        raise RuntimeError("jaxlag: diffrax returned no final time or state for an event segment.")
    saved_q, saved_qd = saved_values(solution, save_ts, carry.t, loop.t1, (carry.q, carry.qd), loop.args)
    final_q, final_qd = solution.ys
    this = from_solution(
        solution,
        carry.t,
        loop.t1,
        carry.q,
        carry.qd,
        max_steps=loop.max_steps,
        max_segments=loop.max_segments,
    )
    this = eqx.tree_at(lambda f: f.code, this, jnp.where(carry.done, FailureCode.COMPLETED, this.code))
    failure = first_failure(carry.failure, this)
    broken = failure.code != FailureCode.COMPLETED
    fired = tuple(jnp.asarray(x) & ~carry.done & ~broken for x in jax.tree.leaves(solution.event_mask))
    return _SolvedSegment(
        t=jnp.where(broken, loop.t1, solution.ts[0]),
        q=jnp.where(broken, carry.q, final_q[0]),
        qd=jnp.where(broken, carry.qd, final_qd[0]),
        saved_q=saved_q,
        saved_qd=saved_qd,
        fired=fired,
        failure=failure,
        broken=broken,
        stats={key: solution.stats[key] for key in _STEP_COUNTS},
    )


def _fill_saves(loop: _Loop, carry: _SegmentCarry, solved: _SolvedSegment) -> _SegmentCarry:
    """The saves in ``[t_start, t_end]`` not filled before take this segment's values."""
    take = (loop.ts >= carry.t) & (loop.ts <= solved.t) & ~carry.filled & ~carry.done & ~solved.broken
    column = take[:, None]
    return eqx.tree_at(
        lambda c: (c.out_q, c.out_qd, c.out_active, c.out_modes, c.filled),
        carry,
        (
            jnp.where(column, solved.saved_q, carry.out_q),
            jnp.where(column, solved.saved_qd, carry.out_qd),
            jnp.where(column, carry.active[None, :], carry.out_active),
            jnp.where(column, carry.modes[None, :], carry.out_modes),
            carry.filled | take,
        ),
    )


def _which_switch(loop: _Loop, segment: SegmentConditions, carry: _SegmentCarry, solved: _SolvedSegment):
    """``(index, values)``: the switch at zero (the smallest) at the event among those
    decreasing there, in `SegmentConditions.switches` order. Near an event more than one can be
    ~0 within the root finder's tolerance (two conditions crossing at the same instant; the gap
    of a constraint just released, which grows from 0 quadratically, and a user condition
    crossing just after). The release and friction switches are taken as decreasing: their
    rates would need the derivative of the KKT solve."""
    t, y, args = solved.t, (solved.q, solved.qd), loop.args
    values = segment.switches(t, y, args)
    field = EquationsOfMotion(loop.system, loop.baumgarte, carry.active, carry.modes)

    def rated(s, x):  # contact gap and σ_k c_k: cheap to differentiate along the motion
        return segment.switches(s, x, args, release=False)

    _, rates = jax.jvp(rated, (t, y), (jnp.ones_like(t), field(t, y, args)))
    minus = -jnp.ones((1,), rates.dtype)
    num_friction = 1 if loop.system.friction else 0
    parts = [minus, rates[:1]] if loop.system.unilateral else []
    parts += [minus] * num_friction
    parts.append(rates[1:] if loop.system.unilateral else rates)
    rates = jnp.concatenate(parts)
    leaving = jnp.where(rates < 0, values, jnp.inf)
    which = jnp.where(jnp.any(jnp.isfinite(leaving)), jnp.argmin(leaving), jnp.argmin(values))
    return which, values


def _classify(
    loop: _Loop, segment: SegmentConditions, carry: _SegmentCarry, solved: _SolvedSegment
) -> _Crossing:
    """What ended the segment, from diffrax's event mask and the switch values at its end."""
    false = jnp.asarray(False)
    num_events = len(loop.events)
    if segment.paired:
        released, contacted = solved.fired
        return _Crossing(
            released,
            contacted,
            false,
            false,
            false,
            false,
            false,
            jnp.asarray(0),
            jnp.asarray(0.0),
            jnp.asarray(0.0),
        )
    hit = solved.fired[0]
    which, values = _which_switch(loop, segment, carry, solved)
    unilateral = bool(loop.system.unilateral)
    friction_at = 2 if unilateral else 0  # the friction switch's place in `switches`
    offset = friction_at + (1 if loop.system.friction else 0)
    released = hit & (which == 0) & unilateral
    contacted = hit & (which == 1) & unilateral
    frictioned = hit & (which == friction_at) & bool(loop.system.friction)
    if not num_events:
        return _Crossing(
            released,
            contacted,
            frictioned,
            false,
            false,
            false,
            false,
            jnp.asarray(0),
            jnp.asarray(0.0),
            jnp.abs(values[which]),
        )
    user_hit = hit & (which >= offset)
    index = jnp.clip(which - offset, 0, num_events - 1)
    side = carry.sides[index]
    # Recorded: every crossing of a condition without direction; one in the direction it names
    # (it leaves the side opposite to it). Otherwise the crossing only ends the segment.
    direction = jnp.array([_crossed_to(e.direction) for e in loop.events], condition_dtype())[index]
    counted = (direction == 0) | (direction == -side)
    terminal = jnp.array([e.terminal for e in loop.events], bool)[index]
    return _Crossing(
        released=released,
        contacted=contacted,
        frictioned=frictioned,
        user_hit=user_hit,
        recorded=user_hit & counted,
        silent=user_hit & ~counted,
        stop=user_hit & counted & terminal,
        user_index=index,
        side=side,
        residual=jnp.abs(values[which]),
    )


def _crossed_to(direction: bool | None) -> float:
    """The side a condition is on after a crossing in ``direction`` (0: the opposite of before)."""
    return 0.0 if direction is None else (1.0 if direction else -1.0)


def _next_sides(loop: _Loop, carry: _SegmentCarry, crossing: _Crossing, jump: Jump, modes, reset, t) -> Array:
    """The side of each user condition in the next segment. The crossed condition is now on the
    other side; the others have not crossed before it. After a jump of the state (release,
    contact, reset) each is on the side the motion takes it to, by the rule at ``t0`` (0, never
    crossing, if ``c``, ``ċ``, ``c̈`` all vanish), or keeps its side if they are not finite. A
    condition at zero within round-off (``√ε``) crosses at this very instant, together with the
    switch: it keeps its side and is recorded next, at the same time."""
    sides = carry.sides
    if not loop.events:
        return sides
    after = loop.segment(jump.active, t, sides, modes)
    c, rate, curvature = values = condition_values(after, loop.baumgarte, jump.q, jump.qd, t, loop.args)
    tiny = jnp.sqrt(jnp.finfo(c.dtype).eps)
    by_rate = jnp.where(rate != 0, jnp.sign(rate), jnp.sign(curvature))
    at_zero = jnp.where(by_rate == 0, 0.0, jnp.where(sides != 0, sides, by_rate))
    jump_sides = jnp.where(jnp.abs(c) > tiny, jnp.sign(c), at_zero)
    finite = jnp.isfinite(c) & jnp.isfinite(rate) & jnp.isfinite(curvature)
    jump_sides = jnp.where(finite, jump_sides, sides).astype(sides.dtype)
    switched = crossing.released | crossing.contacted
    new_sides = jnp.where(
        crossing.user_hit,
        sides.at[crossing.user_index].set(-crossing.side),
        jnp.where(switched, jump_sides, sides),
    )
    return loop.resets.side_after(
        reset, crossing.user_index, new_sides, jump_sides, values, crossing.side, crossing.residual
    )


def _record(
    carry: _SegmentCarry, solved: _SolvedSegment, crossing: _Crossing, jump: Jump, friction
) -> _SegmentRecord:
    """The log entry of the segment (padding once the run has ended)."""
    over = carry.done | solved.broken
    kind = jnp.select(
        [
            over,
            crossing.frictioned,
            crossing.released,
            crossing.contacted & jump.rebounded,
            crossing.contacted,
            crossing.recorded,
            crossing.silent,
        ],
        [
            EventKind.NONE,
            jnp.where(friction.stuck, EventKind.STICK, EventKind.SLIP),
            EventKind.RELEASE,
            EventKind.IMPACT,
            EventKind.CONTACT,
            EventKind.USER,
            EventKind.SILENT,
        ],
        EventKind.END,
    )
    index = jnp.select(
        [crossing.frictioned, crossing.released, crossing.contacted, crossing.recorded],
        [friction.index, jump.release_index, jump.contact_index, crossing.user_index],
        -1,
    )
    return _SegmentRecord(
        time=jnp.where(over, jnp.inf, solved.t),
        kind=kind,
        index=index,
        q=jump.q,
        qd=friction.qd,
        active=jump.active,
        impulses=jump.impulses,
        modes=friction.modes.astype(jnp.int32),
    )


def _advance(loop, carry, solved, crossing, jump, friction, sides) -> _SegmentCarry:
    """The carry of the next segment."""
    happened = crossing.released | crossing.contacted | crossing.recorded | crossing.frictioned
    reached_end = ~happened & ~crossing.silent & ~carry.done
    ran = ~carry.done
    done = carry.done | reached_end | crossing.stop | solved.broken
    steps = {
        key: value + jnp.where(ran, solved.stats[key], 0).astype(value.dtype)
        for key, value in carry.steps.items()
    }
    return eqx.tree_at(
        lambda c: (c.t, c.q, c.qd, c.active, c.modes, c.done, c.sides, c.count, c.failure, c.steps),
        carry,
        (
            jnp.where(done, loop.t1, solved.t),
            jump.q,
            friction.qd,
            jump.active,
            friction.modes,
            done,
            sides,
            carry.count + happened.astype(carry.count.dtype),
            solved.failure,
            steps,
        ),
    )


def _run_segment(loop: _Loop, carry: _SegmentCarry) -> tuple[_SegmentCarry, _SegmentRecord]:
    """One segment: solve to the first switch, fill the saves, classify the switch, jump,
    update the friction modes and the conditions' sides, record, advance."""
    segment = loop.segment(carry.active, carry.t, carry.sides, carry.modes, loop.departing(carry))
    solved = _solve_segment(loop, carry, segment)
    carry = _fill_saves(loop, carry, solved)
    crossing = _classify(loop, segment, carry, solved)
    q_r, qd_r, reset = loop.resets.apply(
        crossing.user_index, crossing.recorded, solved.q, solved.qd, solved.t, loop.args
    )
    solved = _checked_reset(solved, crossing, reset, q_r, qd_r)
    end = SegmentEnd(solved.t, solved.q, solved.qd, q_r, qd_r, crossing.released, crossing.contacted, reset)
    jump = loop.jumps(
        loop.system,
        loop.args,
        end,
        active=carry.active,
        modes=carry.modes,
        unilateral=loop.unilateral,
        resets=loop.resets,
        zeno=loop.zeno,
        tolerance=loop.tolerance,
    )
    friction = loop.friction.after_switch(
        loop.system,
        loop.args,
        q_e=solved.q,
        qd_e=solved.qd,
        q=jump.q,
        qd=jump.qd,
        t=solved.t,
        active=carry.active,
        new_active=jump.active,
        modes=carry.modes,
        switched=crossing.frictioned,
        jumped=crossing.released | crossing.contacted | reset,
        tolerance=loop.tolerance,
    )
    jump = eqx.tree_at(lambda j: j.qd, jump, friction.qd)
    sides = _next_sides(loop, carry, crossing, jump, friction.modes, reset, solved.t)
    record = _record(carry, solved, crossing, jump, friction)
    return _advance(loop, carry, solved, crossing, jump, friction, sides), record


def _checked_reset(solved: _SolvedSegment, crossing: _Crossing, reset, q_r, qd_r) -> _SolvedSegment:
    """``solved``, failed with `FailureCode.RESET` if the reset that fired returned a non-finite
    state (the record keeps the state it was given and the event's index). Without this the
    next segment started from NaN and the run ended in ``max_steps`` far from the cause."""
    bad = reset & ~solved.broken & ~(jnp.all(jnp.isfinite(q_r)) & jnp.all(jnp.isfinite(qd_r)))
    failure = solved.failure
    failed = eqx.tree_at(
        lambda f: (f.code, f.t, f.dt, f.q, f.qd, f.index),
        failure,
        (
            jnp.asarray(FailureCode.RESET, failure.code.dtype),
            jnp.asarray(solved.t, failure.t.dtype),
            jnp.asarray(jnp.nan, failure.dt.dtype),
            solved.q,
            solved.qd,
            jnp.asarray(crossing.user_index, jnp.int32),
        ),
    )
    failure = jax.tree.map(lambda a, b: jnp.where(bad, a, b), failed, failure)
    return eqx.tree_at(lambda s: (s.failure, s.broken), solved, (failure, solved.broken | bad))


def _parameter_failure(system, m_h: int, dtype) -> tuple[Array, Array, Array]:
    """``(code, index, value)`` of the contact laws' coefficients: `FailureCode.RESTITUTION`
    for a restitution outside ``[0, 1]`` or not finite, `FailureCode.FRICTION_COEFFICIENT` for
    a negative or non-finite ``μ``, else ``COMPLETED``. Concrete coefficients were checked
    when ``jl.Unilateral`` / ``jl.Coulomb`` were built; these are the traced ones."""
    bad_e, e_index, e = bad_restitution(system, m_h, dtype)
    bad_mu, mu_index, mu = bad_friction_coefficient(system, dtype)
    code = jnp.where(
        bad_e,
        FailureCode.RESTITUTION,
        jnp.where(bad_mu, FailureCode.FRICTION_COEFFICIENT, FailureCode.COMPLETED),
    )
    return (
        jnp.asarray(code, jnp.int32),
        jnp.where(bad_e, e_index, jnp.where(bad_mu, mu_index, -1)).astype(jnp.int32),
        jnp.where(bad_e, e, jnp.where(bad_mu, mu, jnp.nan)).astype(dtype),
    )


def _initial_carry(loop: _Loop, q0, qd0, t0, active0, modes0, parameters) -> _SegmentCarry:
    """The carry of the first segment. ``parameters``: `_parameter_failure`; a run whose
    coefficients are out of range fails at ``t0`` and runs no segment (each solve is empty)."""
    num_saves, n, dtype = loop.ts.shape[0], q0.shape[0], q0.dtype
    sides = jnp.zeros((0,), condition_dtype())
    if loop.events:
        start = loop.segment(active0, t0, None, modes0)
        sides = sides_from(condition_values(start, loop.baumgarte, q0, qd0, t0, loop.args))
    inf = jnp.full((num_saves, n), jnp.inf, dtype)
    code, index, value = parameters
    refused = code != FailureCode.COMPLETED
    none = Failure(
        code=code,
        t=jnp.where(refused, jnp.asarray(t0, dtype), jnp.asarray(loop.t1, dtype)),
        dt=jnp.asarray(jnp.nan, dtype),
        q=q0,
        qd=qd0,
        t0=jnp.asarray(t0, dtype),
        t1=jnp.asarray(loop.t1, dtype),
        num_steps=jnp.asarray(0, jnp.int32),
        result=jnp.asarray(0, jnp.int32),
        max_steps=loop.max_steps,
        max_segments=loop.max_segments,
        index=index,
        value=value,
    )
    return _SegmentCarry(
        t=jnp.where(refused, jnp.asarray(loop.t1, dtype), jnp.asarray(t0, dtype)),
        q=q0,
        qd=qd0,
        active=active0,
        modes=modes0,
        done=refused,
        sides=sides,
        out_q=inf,
        out_qd=inf,
        out_active=jnp.zeros((num_saves, active0.shape[0]), bool),
        out_modes=jnp.zeros((num_saves, modes0.shape[0]), dtype),
        filled=jnp.zeros((num_saves,), bool),
        count=jnp.asarray(0, jnp.int32),
        failure=none,
        steps={key: jnp.asarray(0, jnp.int32) for key in _STEP_COUNTS},
    )


def _out_of_segments(loop: _Loop, carry: _SegmentCarry, t0) -> Failure:
    """The run's failure, ``MAX_SEGMENTS`` if it had not ended after the last segment (from the
    run's start to where it got). If it stopped in an accumulation of impacts (a ball
    bouncing), ``value`` is the number of segments the geometric series says the run needs
    (`jaxlag._mechanics.impacts.impacts_to_rest`) and ``index`` the row."""
    failure = carry.failure
    out = ~carry.done & (failure.code == FailureCode.COMPLETED)
    needed, row = failure.value, failure.index
    if loop.system.unilateral and needed is not None and row is not None:
        # Advice, not a result: no derivative flows through it (its logarithms would give
        # NaN tangents where the where() below discards them).
        q, qd, t = jax.lax.stop_gradient((carry.q, carry.qd, carry.t))
        impacts, bouncing = impacts_to_rest(
            loop.system,
            q,
            qd,
            t,
            loop.t1,
            loop.args,
            carry.active,
            loop.unilateral,
            loop.zeno,
            loop.tolerance,
        )
        impacts = jax.lax.stop_gradient(impacts)
        # The segments so far, one per impact to come, and the end.
        total = (loop.max_segments + 1.0 + impacts).astype(needed.dtype)
        needed = jnp.where(out, total, needed)
        row = jnp.where(out, bouncing, row)
    return eqx.tree_at(
        lambda f: (f.code, f.t0, f.t, f.q, f.qd, f.value, f.index),
        failure,
        (
            jnp.where(out, FailureCode.MAX_SEGMENTS, failure.code),
            jnp.where(out, jnp.asarray(t0, failure.t0.dtype), failure.t0),
            jnp.where(out, carry.t, failure.t),
            jnp.where(out, carry.q, failure.q),
            jnp.where(out, carry.qd, failure.qd),
            needed,
            row,
        ),
        is_leaf=lambda x: x is None,
    )


def _projected_saves(loop: _Loop, carry: _SegmentCarry) -> tuple[Array, Array]:
    """The saved states, projected onto the rows acting at each save (``inf`` stays ``inf``)."""
    if loop.projection is None:
        return carry.out_q, carry.out_qd
    projection = loop.projection
    out_q, out_qd = jax.vmap(lambda t, x, v, a: projection(loop.system, x, v, t, loop.args, a))(
        loop.ts, carry.out_q, carry.out_qd, carry.out_active
    )
    # Saves after a terminal event stay inf rather than turning into NaN.
    finite = jnp.isfinite(loop.ts)[:, None] & jnp.all(jnp.isfinite(out_q), axis=1, keepdims=True)
    return jnp.where(finite, out_q, jnp.inf), jnp.where(finite, out_qd, jnp.inf)


def _event_log(records: _SegmentRecord, count) -> EventLog:
    """The log of the run: the unrecorded crossings leave it (a stable sort puts them behind
    the real entries), then read as padding."""
    silent = records.kind == EventKind.SILENT
    order = jnp.argsort(silent, stable=True)
    records = jax.tree.map(lambda x: x[order], records)
    silent = silent[order]
    return EventLog(
        time=jnp.where(silent, jnp.inf, records.time),
        kind=jnp.where(silent, EventKind.NONE, records.kind),
        index=jnp.where(silent, -1, records.index),
        q=records.q,
        qd=records.qd,
        active=records.active,
        impulses=records.impulses,
        count=count,
        modes=records.modes,
    )


@runtime_checkable
class _RunOptions(Protocol):
    """The options of a run that are not inputs (``simulate``'s ``_Run``)."""

    max_steps: int | None
    progress_meter: diffrax.AbstractProgressMeter
    check: bool
    tolerance: float | Float[Array, ""]
    compiled: AbstractOnFailure


class _SegmentedSolution(eqx.Module):
    """What the compiled segment loop returns (the trajectory's arrays)."""

    q: Float[Array, "saves n"]
    qd: Float[Array, "saves n"]
    active: Bool[Array, "saves m_h"]
    modes: Int[Array, "saves k"]
    log: EventLog
    failure: Failure
    # diffrax's step counts summed over the segments, "num_segments", and the static "max_steps".
    stats: dict[str, Int[Array, ""] | int | None]


def _save_times(inputs: SimulationInputs) -> Float[Array, " saves"]:
    if inputs.ts is None:  # simulate refuses a segmented run without them
        raise RuntimeError("jaxlag: a segmented run needs save times ts.")
    return inputs.ts


@compilation.filter_jit
def _solve_segments(
    inputs: SimulationInputs, events: Events, run: _RunOptions, adjoint
) -> _SegmentedSolution:
    with on_failure(run.compiled):  # for the checks inside the user's functions
        return _solve_segments_checked(inputs, events, run, adjoint)


def _solve_segments_checked(
    inputs: SimulationInputs, events: Events, run: _RunOptions, adjoint
) -> _SegmentedSolution:
    """The body of `_solve_segments`."""
    i = inputs
    system, q0, qd0, t0, args = i.system, i.q0, i.qd0, i.t0, i.args
    system.check(q0, qd0, t0, args)
    if run.check:
        q0, qd0 = validate_initial_state(system, q0, qd0, t0, args, run.tolerance)
    # From here on a state-independent M is inverted once (jaxlag._mechanics.constant_mass).
    system = with_constant_mass(system, q0, qd0, t0, args)
    m_h = system.num_holonomic(q0, t0, args)
    unilateral = jnp.zeros((m_h,), bool).at[jnp.asarray(system.unilateral, jnp.int32)].set(True)
    active0 = initial_activity(system, q0, qd0, t0, args, run.tolerance)
    # Traced coefficients out of range: the run fails at t0 (FailureCode.RESTITUTION, ...).
    parameters = _parameter_failure(system, m_h, q0.dtype)
    state0 = (q0, qd0)  # the failure record's state, before the friction projection
    friction = friction_modes_for(system)
    modes0, qd0 = friction.initial(system, q0, qd0, t0, args, active0, run.tolerance)
    resets = resets_for(tuple(e.reset for e in events.conditions))
    dtype = q0.dtype
    loop = _Loop(
        system=system,
        args=args,
        ts=_save_times(i),
        t1=jnp.asarray(i.t1, dtype),
        dt0=i.dt0,
        solver=i.solver,
        controller=i.stepsize_controller,
        adjoint=adjoint,
        progress_meter=run.progress_meter,
        baumgarte=i.baumgarte,
        projection=i.projection,
        events=events.conditions,
        root_finder=root_finder_for(events.root_finder, dtype),
        max_steps=run.max_steps,
        max_segments=events.max_segments,
        tolerance=run.tolerance,
        unilateral=unilateral,
        # Impacts that end an accumulation (Zeno) are plastic: see Events' zeno_time.
        zeno=events.zeno_time,
        friction=friction,
        resets=resets,
        jumps=jump_law_for(system, m_h, resets),
    )
    carry = _initial_carry(loop, q0, qd0, t0, active0, modes0, parameters)
    carry = eqx.tree_at(lambda c: (c.failure.q, c.failure.qd), carry, state0)
    carry, records = jax.lax.scan(lambda c, _: _run_segment(loop, c), carry, None, length=events.max_segments)
    out_q, out_qd = _projected_saves(loop, carry)
    ran = jnp.sum(records.kind != EventKind.NONE).astype(jnp.int32)
    return _SegmentedSolution(
        q=out_q,
        qd=out_qd,
        active=carry.out_active,
        modes=carry.out_modes.astype(jnp.int32),
        log=_event_log(records, carry.count),
        failure=_out_of_segments(loop, carry, t0),
        # The statistics of the whole run: diffrax's, summed over the segments that ran.
        stats={**carry.steps, "max_steps": run.max_steps, "num_segments": ran},
    )


def solve_segments(*, inputs: SimulationInputs, events: Events, run: _RunOptions, adjoint) -> Trajectory:
    """Integrate across releases, contacts, friction switches and user events (see the module
    docstring); the trajectory has ``events`` (an [`EventLog`][jaxlag.EventLog]), ``active``,
    ``failure`` and ``stats`` (summed over the segments) set."""
    solution = _solve_segments(inputs, events, run, adjoint)
    return Trajectory.from_states(
        inputs.system,
        _save_times(inputs),
        solution.q,
        solution.qd,
        inputs.args,
        stats=solution.stats,
        active=solution.active,
        events=solution.log,
        failure=solution.failure,
        modes=solution.modes if inputs.system.friction else None,
    )
