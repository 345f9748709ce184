r"""Events and unilateral constraints: integrate in segments between switches.

A unilateral constraint ``f_i(q, t) ≥ 0`` acts (``f_i = 0``) only while its multiplier keeps
the sign ``λ_i ≥ 0`` (it pushes, never pulls). The simulation runs in segments; each segment is
one ``diffrax.diffeqsolve`` with a fixed set of active constraints, ended by the first of

* release: ``min_i λ_i`` over the active unilateral constraints reaching zero from above;
* contact: ``min_i f_i`` over the inactive ones reaching zero from above;
* a crossing of a user :class:`Event` condition ``c_k``: ``σ_k c_k`` reaching zero from above,
  where ``σ_k = ±1`` is the side ``c_k`` starts the segment on.

With user conditions these are given to diffrax as one condition, their minimum, so that the
root find on the solver's dense output (differentiable through diffrax) locates the earliest of
them even when several happen within one solver step; which one it was is read off at the
event. (Releases and contacts alone are two diffrax conditions, as the minimum of each is
already one quantity per kind.)

At a release the constraint is switched off; at a contact it is switched on with a
perfectly plastic impact, the velocity jump ``q̇⁺ = q̇⁻ − M⁻¹Jᵀ(JM⁻¹Jᵀ)⁻¹J q̇⁻`` (the
mass-weighted projection onto the constraint's tangent space, coefficient of restitution 0). If
the newly engaged constraint would have to pull it is released again at once. A terminal user
event ends the simulation; saved times after it hold ``inf`` (diffrax's convention). Each user
condition carries the side (sign) it is on into the next segment, so that the ~0 it starts
from after its own event, or an exact 0 at ``t0``, is not taken for a crossing
(:class:`Event` states the semantics).

The segments are a ``lax.scan`` of fixed length ``max_segments``, so the whole thing compiles
once and works under ``vmap`` (each batch member switching at its own times) and ``grad``.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _compile as compilation
from . import _errors as failures
from ._solver.guard import guard
from ._checks import initial_activity, validate_initial_state
from ._mechanics.constant_mass import with_constant_mass
from ._mechanics.constraints import holonomic_residual
from ._conventions import UserFunction, wrap_event_function
from ._mechanics.kkt import accelerations_and_multipliers
from ._stabilization import project_state, stages_for_adjoint, wrap_for_projection
from ._solver.step_once import StepOnce
from ._vector_field import EquationsOfMotion

_NO_EVENT, _END, _RELEASE, _CONTACT, _USER = -1, 0, 1, 2, 3
_SILENT = -2  # a crossing in the direction its condition ignores: removed from the log
KIND_NAMES = {_NO_EVENT: "none", _END: "end", _RELEASE: "release", _CONTACT: "contact", _USER: "user"}


class Event(eqx.Module):
    r"""A user event: fires when ``c = condition(q, qd, [t], [args], [multipliers])`` crosses zero.

    ``multipliers`` (if declared) receives the holonomic multipliers ``λ`` at the state, so
    "the constraint force exceeds a limit" is ``lambda q, qd, multipliers: limit − multipliers[0]``.

    **What counts as a crossing.** A crossing is a change of the sign of ``c`` *after* the
    start time ``t0``; ``t0`` itself is never an event time. A condition that is exactly 0 at
    ``t0`` starts on the side it moves to: the sign of the first non-zero of ``c``, ``ċ``,
    ``c̈`` at ``t0`` (derivatives along the motion), so ``c = q[0]`` with ``q0[0] = 0`` and
    ``q̇0[0] > 0`` first fires when ``q[0]`` comes back down through 0. After a non-terminal
    event the condition continues from the side it crossed to, so each crossing is recorded
    exactly once. Crossings of several conditions are recorded in the order they happen,
    also within one solver step; two at the same instant give two entries at that time.

    - ``direction``: ``None`` (every crossing), ``True`` (upward only: ``c`` goes from
      negative to positive), ``False`` (downward only: positive to negative). Crossings in
      the other direction are not recorded (each still ends a segment, see
      :class:`~jaxlag.Events`' ``max_segments``).
    - ``terminal``: stop the simulation at the event (saved times after it hold ``inf``);
      otherwise the event is only recorded in :class:`~jaxlag.EventLog` and the integration
      continues from the event state.

    The event time is a root of ``c`` on the solver's dense output, found by
    :class:`~jaxlag.Events`' ``root_finder`` and differentiable (``jax.grad`` of an event time
    or of the state there works).
    """

    condition: UserFunction
    terminal: bool = eqx.field(static=True)
    direction: bool | None = eqx.field(static=True)

    def __init__(self, condition: Callable, terminal: bool = True, direction: bool | None = None):
        self.condition = wrap_event_function(condition)
        self.terminal = bool(terminal)
        self.direction = direction


_DEFAULT_ROOT_FINDER = optx.Newton(rtol=1e-13, atol=1e-13)


def default_root_tolerance(dtype) -> float:
    """``rtol = atol`` of the default root finder: 1e-13 in float64; ``√ε`` of lower
    precisions (3.5e-4 in float32). optimistix's Newton stops when both the last step in ``t``
    and ``|c|`` are below the tolerance: 1e-13 is below float32 round-off of any ``c`` of
    order 1, so the float32 root find never stopped. Newton converges quadratically: the time
    it returns is far more accurate than its last step, and below the solver's own error."""
    eps = float(jnp.finfo(dtype).eps)
    return 1e-13 if eps <= float(jnp.finfo(jnp.float64).eps) else eps**0.5


def _is_default(root_finder) -> bool:
    """Whether ``root_finder`` equals the default (compared by value: inside ``filter_jit`` it
    is a rebuilt copy; array tolerances, traced or not, are never the default)."""
    if type(root_finder) is not optx.Newton:
        return False
    try:
        return bool(root_finder == _DEFAULT_ROOT_FINDER)
    except Exception:  # noqa: BLE001 - array-valued tolerances: not the default
        return False


def root_finder_for(root_finder: optx.AbstractRootFinder, dtype) -> optx.AbstractRootFinder:
    """The root finder a run uses: the default's tolerances follow ``dtype``
    (:func:`default_root_tolerance`); any other root finder is used as given."""
    if _is_default(root_finder):
        tol = default_root_tolerance(dtype)
        return optx.Newton(rtol=tol, atol=tol)
    return root_finder


class Events(eqx.Module):
    """The events of :func:`~jaxlag.simulate` (``events=jl.Events(...)``): user conditions and
    how the segmented integration that handles them (and unilateral constraints) runs.

    Construct it with the conditions as positional arguments::

        jl.Events(jl.Event(hits_floor), jl.Event(too_fast, terminal=False), max_segments=16)
        jl.Events(*conditions)  # from a list
        jl.Events(max_segments=32)  # no user condition: a system with unilateral constraints

    - ``conditions``: :class:`~jaxlag.Event` s (terminal or only recorded), stored as a tuple.
    - ``max_segments``: the integration runs in at most this many segments (default 8). A
      segment ends at each release, contact or event (terminal or not), at each crossing in
      the direction a condition ignores (``direction=True``/``False``; not recorded) and at
      the end time, so a run with ``k`` of these needs ``k + 1`` segments. The segments
      are a ``lax.scan`` of this static length: it is compiled in, the compile time does not
      grow with it, and segments left over after the end are empty solves that cost next to
      nothing at run time, so a generous value is cheap. Needing more is a failure
      (``SimulationError``), never a silent truncation; the message says how far the run got
      with the segments it had and the value to pass.
    - ``root_finder``: the ``optimistix`` root finder that locates each event on the solver's
      dense output (default ``optimistix.Newton(rtol=1e-13, atol=1e-13)``; in lower precision
      than float64 the default's tolerances are ``√ε``, 3.5e-4 in float32, as 1e-13 is below
      round-off there: the default, or a ``Newton`` equal to it, is adapted to the dtype).
      Any other root finder is used as given.

    The segmented mode runs when the system has ``unilateral`` constraints or ``conditions`` is
    non-empty; it needs save times ``ts``. ``simulate(..., events=...)`` also takes a single
    :class:`~jaxlag.Event` or a sequence of them, as ``Events(*conditions)``.
    """

    conditions: tuple[Event, ...]
    max_segments: int = eqx.field(static=True)
    root_finder: optx.AbstractRootFinder

    def __init__(
        self,
        *conditions: Event,
        max_segments: int = 8,
        root_finder: optx.AbstractRootFinder = _DEFAULT_ROOT_FINDER,
    ):
        for condition in conditions:
            if not isinstance(condition, Event):
                hint = (
                    " Pass the conditions as separate arguments: jl.Events(*conditions)."
                    if isinstance(condition, (tuple, list))
                    else ""
                )
                raise TypeError(f"jl.Events takes jl.Event conditions; got {type(condition).__name__}.{hint}")
        integer = isinstance(max_segments, numbers.Integral) and not isinstance(max_segments, bool)
        if not integer or max_segments < 1:
            raise ValueError(f"max_segments must be a positive integer; got {max_segments!r}.")
        if not isinstance(root_finder, optx.AbstractRootFinder):
            raise TypeError(
                f"root_finder must be an optimistix root finder; got {type(root_finder).__name__}."
            )
        self.conditions = tuple(conditions)
        self.max_segments = int(max_segments)
        self.root_finder = root_finder


def as_events(events) -> Events:
    """``simulate``'s ``events=``: a :class:`Events`, or one :class:`Event` or a sequence of them
    (``Events(*events)``)."""
    if isinstance(events, Events):
        return events
    if isinstance(events, Event):
        return Events(events)
    if isinstance(events, (tuple, list)) and all(isinstance(e, Event) for e in events):
        return Events(*events)
    got = type(events).__name__
    if isinstance(events, (tuple, list)):
        got = f"a {got} holding " + ", ".join(
            sorted({type(e).__name__ for e in events if not isinstance(e, Event)})
        )
    raise TypeError(f"events must be a jl.Events, a jl.Event or a sequence of jl.Event; got {got}.")


def multiplier_limit(index: int, limit: float, terminal: bool = True, below: bool = False) -> Event:
    """An event for "the constraint force exceeds a limit": ``λ_index`` rises above ``limit``
    (or, with ``below=True``, falls below it). E.g. the g-load on a roller-coaster car."""

    def condition(q, qd, multipliers):
        return multipliers[index] - limit

    return Event(condition, terminal=terminal, direction=not below)


class EventLog(eqx.Module):
    """What happened at the end of each segment: arrays of ``max_segments`` entries (with the
    batch axes first for a log from ``jax.vmap``), in the order the segments ran.

    - ``kind[k]``: 0 the end time was reached, 1 a unilateral constraint was released, 2 one
      made contact, 3 a user event fired, −1 padding (the run had already ended, at the end
      time, a terminal event or a failure). :meth:`kinds` gives the names of the real entries.
    - ``index[k]``: which constraint (holonomic index) or which user event (position in
      ``Events.conditions``); −1 for the end.
    - ``time[k]``, ``q[k]``, ``qd[k]``: the switch time and the state just after the switch
      (after the plastic impact of a contact); ``time`` is ``inf`` for padding.
    - ``active[k]``: holonomic activity mask after the switch.
    - ``count``: the number of switches and events (kinds 1–3).
    """

    time: Float[Array, "*batch segments"]
    kind: Int[Array, "*batch segments"]
    index: Int[Array, "*batch segments"]
    q: Float[Array, "*batch segments n"]
    qd: Float[Array, "*batch segments n"]
    active: Bool[Array, "*batch segments m_h"]
    count: Int[Array, "*batch"]

    def kinds(self) -> list[str] | list[list[str]]:
        """The names of the real entries (``"release"``, ``"contact"``, ``"user"``, ``"end"``),
        without the padding: ``["user", "user", "end"]``. A terminal event is the last entry;
        a completed run ends with ``"end"``. For a batched log, one list per member, nested
        like the batch axes (a list of lists after one ``vmap``). Host-side: call it outside
        ``jit``."""
        kind = jax.device_get(self.kind)

        def names(row):
            return [KIND_NAMES[int(k)] for k in row if int(k) != _NO_EVENT]

        def nested(x) -> list:
            return names(x) if x.ndim == 1 else [nested(member) for member in x]

        return nested(np.asarray(kind))  # deeper lists for more than one batch axis


def _condition_dtype():
    """The dtype of user condition values: JAX's default float. (diffrax pads untriggered
    conditions with a Python ``0.0`` inside a ``lax.cond``, which must match the condition's
    dtype: float32 states under ``jax_enable_x64`` would otherwise fail to trace.)"""
    return jax.dtypes.canonicalize_dtype(float)


def _masked_min(values, mask):
    return jnp.min(jnp.where(mask, values, jnp.inf), initial=jnp.inf)


class _Segment(eqx.Module):
    """Condition functions of one segment (a module so diffrax's compile cache is reused)."""

    system: Any
    events: tuple
    unilateral: Any  # (m_h,) bool
    active: Any  # (m_h,) bool
    t_start: Any
    sides: Any  # (num_events,) the side (±1; 0 unknown) each user condition is on at t_start

    def release(self, t, y, args, **kwargs):
        value = _release_value(self.system, y, t, args, self.active, self.unilateral)
        return value.astype(_condition_dtype())

    def contact(self, t, y, args, **kwargs):
        q, _ = y
        f = holonomic_residual(self.system, q, t, args)
        value = _masked_min(f, ~self.active & self.unilateral)
        return jnp.where(jnp.isfinite(value), value, 1.0).astype(_condition_dtype())

    def raw(self, j, t, y, args):
        """The user's condition ``c_j`` at ``(t, q, q̇)``."""
        q, qd = y
        event = self.events[j]
        available = {"t": t, "args": args}
        if "multipliers" in event.condition.keywords:
            available["multipliers"] = accelerations_and_multipliers(
                self.system, q, qd, t, args, active=self.active
            )[1]
        return jnp.asarray(event.condition(q, qd, **available), _condition_dtype())

    def signed(self, t, y, args):
        """``σ_k c_k`` for each user condition: positive on the side it starts the segment on
        (``+inf`` where that side is unknown, ``σ_k = 0``); it turns ≤ 0 when ``c_k`` crosses."""
        values = jnp.stack([self.raw(j, t, y, args) for j in range(len(self.events))])
        return jnp.where(self.sides != 0, self.sides * values, jnp.inf)

    def switches(self, t, y, args, release: bool = True):
        """The quantities that end the segment when they reach 0 from above: ``[min λ`` over the
        active unilateral constraints, ``min f`` over the inactive ones``]`` (if the system has
        unilateral constraints; ``release=False``: only the second), then ``σ_k c_k`` for each
        user condition."""
        values = []
        if self.system.unilateral:
            values = [self.release(t, y, args)] if release else []
            values.append(self.contact(t, y, args))
        if self.events:
            values.append(self.signed(t, y, args))
        return jnp.concatenate([jnp.reshape(v, (-1,)) for v in values])

    def crossing(self, t, y, args, **kwargs):
        """The one diffrax condition of the segment: ``φ = min`` of :meth:`switches`.

        ``φ > 0`` until the first switch (release, contact or crossing of a user condition)
        and reaches 0 there, so the root find locates the earliest one even when several
        happen within one solver step (diffrax, given the conditions separately, would locate
        the first in list order and the others would be lost). At ``t_start`` each term is put
        above 0 (``|value|``): after an event its quantity is ~0 with a residual of either
        sign, and a user condition may be exactly 0 at ``t0``; diffrax counts any change of
        sign, 0 included, as a crossing."""
        values = self.switches(t, y, args)
        tiny = jnp.finfo(values.dtype).tiny
        values = jnp.where(t == self.t_start, jnp.maximum(jnp.abs(values), tiny), values)
        return jnp.min(jnp.where(jnp.isfinite(values), values, 1.0))

    def diffrax_event(self, root_finder):
        if not self.events:  # releases and contacts only: min λ and min f, each from above
            return diffrax.Event([self.release, self.contact], root_finder=root_finder, direction=[False] * 2)
        return diffrax.Event(self.crossing, root_finder=root_finder, direction=False)


@compilation.filter_jit
def _release_value(system, y, t, args, active, unilateral):
    """The release condition ``min λ`` over the active unilateral constraints (1 if none).

    Jitted on its own: diffrax traces event conditions a dozen times per solve (its checks, the
    loop body's static analysis, the root finder), and each trace is a full KKT solve; JAX's
    tracing cache serves the repeats (the sphere release simulation traces 1.3 → 1.1 s)."""
    q, qd = y
    _, lam, _ = accelerations_and_multipliers(system, q, qd, t, args, active=active)
    value = _masked_min(lam, active & unilateral)
    return jnp.where(jnp.isfinite(value), value, 1.0)


_STEP_COUNTS = ("num_steps", "num_accepted_steps", "num_rejected_steps")


def _crossed_to(direction: bool | None) -> float:
    """The side a condition is on after a crossing in ``direction`` (0: the opposite of before)."""
    return 0.0 if direction is None else (1.0 if direction else -1.0)


def initial_sides(segment: _Segment, baumgarte, q0, qd0, t0, args):
    r"""The side (±1) each user condition starts on at ``t0``: the sign of the first non-zero of
    ``c``, ``ċ``, ``c̈`` there, the derivatives along the motion (Lie derivatives along the
    equations of motion ``ẏ = (q̇, q̈)``, by nested ``jax.jvp``); 0 if all three vanish.

    So ``t0`` is never a crossing: a condition that is exactly 0 at ``t0`` is on the side it
    leaves to, and its first event is its next sign change."""
    num_events = len(segment.events)
    dtype = _condition_dtype()
    if not num_events:
        return jnp.zeros((0,), dtype)
    field = EquationsOfMotion(segment.system, baumgarte, segment.active)
    t0 = jnp.asarray(t0, q0.dtype)

    def values(t, y):
        return jnp.stack([segment.raw(j, t, y, args) for j in range(num_events)])

    def rate(fn):
        def along_motion(t, y):
            return jax.jvp(fn, (t, y), (jnp.ones_like(t), field(t, y, args)))[1]

        return along_motion

    y0 = (q0, qd0)
    c0, c1, c2 = values(t0, y0), rate(values)(t0, y0), rate(rate(values))(t0, y0)
    side = jnp.where(c0 != 0, jnp.sign(c0), jnp.where(c1 != 0, jnp.sign(c1), jnp.sign(c2)))
    return jnp.where(jnp.isfinite(side), side, 0.0).astype(dtype)


@compilation.filter_jit
def solve_segments(
    system,
    q0,
    qd0,
    t0,
    t1,
    ts,
    dt0,
    args,
    solver,
    stepsize_controller,
    max_steps,
    adjoint,
    progress_meter,
    baumgarte,
    projection,
    events,
    max_segments,
    root_finder,
    check,
    tolerance,
):
    """Integrate across releases, contacts and user events; see the module docstring."""
    system.check(q0, qd0, t0, args)
    if check:
        q0, qd0 = validate_initial_state(system, q0, qd0, t0, args, tolerance)
    # From here on a state-independent M is inverted once (jaxlag._mechanics.constant_mass).
    system = with_constant_mass(system, q0, qd0, t0, args)
    m_h = system.num_holonomic(q0, t0, args)
    unilateral = jnp.zeros((m_h,), bool)
    for i in system.unilateral:
        unilateral = unilateral.at[i].set(True)
    active0 = initial_activity(system, q0, t0, args, tolerance)
    num_events = len(events)
    n, num_saves = q0.shape[0], ts.shape[0]
    dtype = q0.dtype
    root_finder = root_finder_for(root_finder, dtype)

    def lam_of(q, qd, t, active):
        return accelerations_and_multipliers(system, q, qd, t, args, active=active)[1]

    def run_segment(carry, _):
        (t_s, q, qd, active, done, sides, out_q, out_qd, out_active, filled, count, failure, steps) = carry
        segment = _Segment(system, tuple(events), unilateral, active, t_s, sides)
        this_solver = stages_for_adjoint(solver, adjoint)  # diffrax does not see it in StepOnce
        if projection is not None:
            this_solver = wrap_for_projection(this_solver, system, projection, adjoint, active)
        this_solver = StepOnce(this_solver)  # traced once, not once per diffrax body trace
        controller = guard(stepsize_controller)
        solution = diffrax.diffeqsolve(
            diffrax.ODETerm(EquationsOfMotion(system, baumgarte, active)),
            this_solver,
            t_s,
            t1,
            dt0,
            (q, qd),
            args,
            saveat=diffrax.SaveAt(
                subs=[diffrax.SubSaveAt(ts=jnp.clip(ts, t_s, t1)), diffrax.SubSaveAt(t1=True)],
                controller_state=True,
            ),
            stepsize_controller=controller,
            adjoint=adjoint,
            event=segment.diffrax_event(root_finder),
            max_steps=max_steps,
            throw=False,  # recorded in `failure`; simulate raises (jaxlag._errors)
            progress_meter=progress_meter,
        )
        if solution.ts is None or solution.ys is None:  # the SaveAt above saves both
            raise RuntimeError("jaxlag: diffrax returned no saved times or states for an event segment.")
        (saved_q, saved_qd), (final_q, final_qd) = solution.ys
        t_e = solution.ts[1][0]
        q_e, qd_e = final_q[0], final_qd[0]
        this = failures.from_solution(
            solution, t_s, t1, q, qd, max_steps=max_steps, max_segments=max_segments
        )
        this = eqx.tree_at(lambda f: f.code, this, jnp.where(done, failures.NONE, this.code))
        failure = failures.first_failure(failure, this)
        # A failed segment ends the simulation: its end state is not a state of the motion.
        broken = failure.code != failures.NONE
        t_e = jnp.where(broken, t1, t_e)
        q_e = jnp.where(broken, q, q_e)
        qd_e = jnp.where(broken, qd, qd_e)

        take = (ts >= t_s) & (ts <= t_e) & ~filled & ~done & ~broken
        out_q = jnp.where(take[:, None], saved_q, out_q)
        out_qd = jnp.where(take[:, None], saved_qd, out_qd)
        out_active = jnp.where(take[:, None], active[None, :], out_active)
        filled = filled | take

        # A failed segment records nothing: its events are not events of the motion.
        fired = [jnp.asarray(x) & ~done & ~broken for x in jax.tree.leaves(solution.event_mask)]
        offset = 2 if system.unilateral else 0
        if num_events:
            hit = fired[0]
            # Which switch happened: the quantity at zero (the smallest) at the event among
            # those decreasing there. Near an event more than one can be ~0, within the root
            # finder's tolerance: two conditions crossing at the same instant (in the next
            # segment too; there the one that has just crossed moves away from zero), or the
            # gap of a constraint just released, which grows from 0 quadratically, and a user
            # condition crossing just after. (The release quantity, min λ, is taken as
            # decreasing: its rate would need the derivative of the KKT solve.)
            y_e = (q_e, qd_e)
            values_e = segment.switches(t_e, y_e, args)
            field = EquationsOfMotion(system, baumgarte, active)

            def rated(t, y):  # contact gap and σ_k c_k: cheap to differentiate along the motion
                return segment.switches(t, y, args, release=False)

            _, rates = jax.jvp(rated, (t_e, y_e), (jnp.ones_like(t_e), field(t_e, y_e, args)))
            rates = jnp.concatenate([-jnp.ones((offset - 1 if offset else 0,), rates.dtype), rates])
            leaving = jnp.where(rates < 0, values_e, jnp.inf)
            which = jnp.where(jnp.any(jnp.isfinite(leaving)), jnp.argmin(leaving), jnp.argmin(values_e))
            released = hit & (which == 0) if system.unilateral else jnp.asarray(False)
            contacted = hit & (which == 1) if system.unilateral else jnp.asarray(False)
            user_hit = hit & (which >= offset)
        else:
            which = jnp.asarray(0)
            released, contacted = fired[0], fired[1]
            user_hit = jnp.asarray(False)

        new_active = active
        release_index = contact_index = jnp.asarray(0)
        q_p, qd_p = q_e, qd_e
        if m_h:
            # Which constraint switched: the one whose multiplier / gap is at its minimum.
            lam_e = lam_of(q_e, qd_e, t_e, active)
            f_e = holonomic_residual(system, q_e, t_e, args)
            release_index = jnp.argmin(jnp.where(active & unilateral, lam_e, jnp.inf))
            contact_index = jnp.argmin(jnp.where(~active & unilateral, f_e, jnp.inf))
            new_active = jnp.where(released, new_active.at[release_index].set(False), new_active)
            new_active = jnp.where(contacted, new_active.at[contact_index].set(True), new_active)
            # Restore consistency with the new active set: at a contact, the plastic impact.
            q_p, qd_p = project_state(system, q_e, qd_e, t_e, args, 2, new_active, refresh_mass=True)
            # A constraint that would have to pull right after engaging separates again.
            lam_p = lam_of(q_p, qd_p, t_e, new_active)
            pulls = contacted & (lam_p[contact_index] < 0)
            new_active = jnp.where(pulls, new_active.at[contact_index].set(False), new_active)
        switched = released | contacted
        q_next = jnp.where(switched, q_p, q_e)
        qd_next = jnp.where(switched, qd_p, qd_e)

        if num_events:
            user_index = jnp.clip(which - offset, 0, num_events - 1)
            side = sides[user_index]
            direction = jnp.array([_crossed_to(e.direction) for e in events], _condition_dtype())
            # Recorded: every crossing of a condition without direction; one in the direction it
            # names (it leaves the side opposite to it). Otherwise the crossing only ends the
            # segment; the integration goes on, unrecorded.
            counted = (direction[user_index] == 0) | (direction[user_index] == -side)
            any_user = user_hit & counted
            silent = user_hit & ~counted
            terminal = jnp.array([e.terminal for e in events], bool)[user_index]
            stop = any_user & terminal
            # The sides for the next segment: the crossed condition is now on the other side;
            # the others have not crossed before it. After a release or contact (the state may
            # jump) each takes the side of its value there, or keeps its own if that is 0.
            after = _Segment(system, tuple(events), unilateral, new_active, t_e, sides)
            end_values = jnp.stack([after.raw(j, t_e, (q_next, qd_next), args) for j in range(num_events)])
            by_value = jnp.where(end_values != 0, jnp.sign(end_values), sides)
            new_sides = jnp.where(
                user_hit, sides.at[user_index].set(-side), jnp.where(switched, by_value, sides)
            )
        else:
            user_index, any_user = jnp.asarray(0), jnp.asarray(False)
            silent = stop = jnp.asarray(False)
            new_sides = sides
        happened = switched | any_user
        reached_end = ~happened & ~silent & ~done
        kind = jnp.where(
            done | broken,
            _NO_EVENT,
            jnp.where(
                released,
                _RELEASE,
                jnp.where(contacted, _CONTACT, jnp.where(any_user, _USER, jnp.where(silent, _SILENT, _END))),
            ),
        )
        index = jnp.where(
            released, release_index, jnp.where(contacted, contact_index, jnp.where(any_user, user_index, -1))
        )
        record = (jnp.where(done | broken, jnp.inf, t_e), kind, index, q_next, qd_next, new_active)
        count = count + happened.astype(count.dtype)
        ran = ~done
        steps = {
            key: value + jnp.where(ran, solution.stats[key], 0).astype(value.dtype)
            for key, value in steps.items()
        }
        done = done | reached_end | stop | broken
        t_next = jnp.where(done, t1, t_e)
        carry = (
            t_next,
            q_next,
            qd_next,
            new_active,
            done,
            new_sides,
            out_q,
            out_qd,
            out_active,
            filled,
            count,
            failure,
            steps,
        )
        return carry, record

    inf = jnp.full((num_saves, n), jnp.inf, dtype)
    none = failures.Failure(
        code=jnp.asarray(failures.NONE, jnp.int32),
        t=jnp.asarray(t1, dtype),
        dt=jnp.asarray(jnp.nan, dtype),
        q=q0,
        qd=qd0,
        t0=jnp.asarray(t0, dtype),
        t1=jnp.asarray(t1, dtype),
        num_steps=jnp.asarray(0, jnp.int32),
        result=jnp.asarray(0, jnp.int32),
        max_steps=max_steps,
        max_segments=max_segments,
    )
    carry0 = (
        t0,
        q0,
        qd0,
        active0,
        jnp.asarray(False),
        initial_sides(
            _Segment(system, tuple(events), unilateral, active0, t0, None), baumgarte, q0, qd0, t0, args
        ),
        inf,
        inf,
        jnp.zeros((num_saves, m_h), bool),
        jnp.zeros((num_saves,), bool),
        jnp.asarray(0, jnp.int32),
        none,
        {key: jnp.asarray(0, jnp.int32) for key in _STEP_COUNTS},
    )
    carry, records = jax.lax.scan(run_segment, carry0, None, length=max_segments)
    t_last, q_last, qd_last, _, done, _, out_q, out_qd, out_active, _, count, failure, steps = carry
    out_of_segments = ~done & (failure.code == failures.NONE)
    failure = eqx.tree_at(
        lambda f: (f.code, f.t0, f.t, f.q, f.qd),
        failure,
        (
            jnp.where(out_of_segments, failures.MAX_SEGMENTS, failure.code),
            jnp.where(out_of_segments, none.t0, failure.t0),  # the run's start, not the segment's
            jnp.where(out_of_segments, t_last, failure.t),
            jnp.where(out_of_segments, q_last, failure.q),
            jnp.where(out_of_segments, qd_last, failure.qd),
        ),
    )
    if projection is not None:
        out_q, out_qd = jax.vmap(lambda t, x, v, a: projection(system, x, v, t, args, a))(
            ts, out_q, out_qd, out_active
        )
        # Saves after a terminal event stay inf rather than turning into NaN.
        finite = jnp.isfinite(ts)[:, None] & jnp.all(jnp.isfinite(out_q), axis=1, keepdims=True)
        out_q = jnp.where(finite, out_q, jnp.inf)
        out_qd = jnp.where(finite, out_qd, jnp.inf)
    ran = jnp.sum(records[1] != _NO_EVENT).astype(jnp.int32)
    # The unrecorded crossings leave the log (a stable sort puts them behind the real
    # entries), then read as padding.
    silent = records[1] == _SILENT
    order = jnp.argsort(silent, stable=True)
    time, kind, index, q_rec, qd_rec, active_rec = (x[order] for x in records)
    silent = silent[order]
    time = jnp.where(silent, jnp.inf, time)
    kind = jnp.where(silent, _NO_EVENT, kind)
    index = jnp.where(silent, -1, index)
    log = EventLog(time, kind, index, q_rec, qd_rec, active_rec, count)
    # The statistics of the whole run: diffrax's, summed over the segments that ran.
    stats = {**steps, "max_steps": max_steps, "num_segments": ran}
    return ts, out_q, out_qd, out_active, log, failure, stats
