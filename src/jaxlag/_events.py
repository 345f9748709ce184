r"""Events and unilateral constraints: integrate in segments between switches.

A unilateral constraint ``f_i(q, t) ≥ 0`` acts (``f_i = 0``) only while its multiplier keeps
the sign ``λ_i ≥ 0`` (it pushes, never pulls). The simulation runs in segments; each segment is
one ``diffrax.diffeqsolve`` with a fixed set of active constraints and a ``diffrax.Event`` whose
conditions are

* release: ``min_i λ_i`` over the active unilateral constraints crossing zero downwards;
* contact: ``min_i f_i`` over the inactive ones crossing zero downwards;
* every user :class:`Event` condition.

The event time is located by a root find on the solver's dense output (differentiable through
diffrax). At a release the constraint is switched off; at a contact it is switched on with a
perfectly plastic impact, the velocity jump ``q̇⁺ = q̇⁻ − M⁻¹Jᵀ(JM⁻¹Jᵀ)⁻¹J q̇⁻`` (the
mass-weighted projection onto the constraint's tangent space, coefficient of restitution 0). If
the newly engaged constraint would have to pull it is released again at once. A terminal user
event ends the simulation; saved times after it hold ``inf`` (diffrax's convention).

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
KIND_NAMES = {_NO_EVENT: "none", _END: "end", _RELEASE: "release", _CONTACT: "contact", _USER: "user"}


class Event(eqx.Module):
    """A user event: fires when ``condition(q, qd, [t], [args], [multipliers])`` crosses zero.

    ``multipliers`` (if declared) receives the holonomic multipliers ``λ`` at the state, so
    "the constraint force exceeds a limit" is ``lambda q, qd, multipliers: limit − multipliers[0]``.
    ``direction``: ``None`` (either way), ``True`` (upward crossing), ``False`` (downward).
    ``terminal``: stop the simulation at the event (otherwise it is only recorded).
    """

    condition: UserFunction
    terminal: bool = eqx.field(static=True)
    direction: bool | None = eqx.field(static=True)

    def __init__(self, condition: Callable, terminal: bool = True, direction: bool | None = None):
        self.condition = wrap_event_function(condition)
        self.terminal = bool(terminal)
        self.direction = direction


_DEFAULT_ROOT_FINDER = optx.Newton(rtol=1e-13, atol=1e-13)


class Events(eqx.Module):
    """The events of :func:`~jaxlag.simulate` (``events=jl.Events(...)``): user conditions and
    how the segmented integration that handles them (and unilateral constraints) runs.

    Construct it with the conditions as positional arguments::

        jl.Events(jl.Event(hits_floor), jl.Event(too_fast, terminal=False), max_segments=16)
        jl.Events(*conditions)  # from a list
        jl.Events(max_segments=32)  # no user condition: a system with unilateral constraints

    - ``conditions``: :class:`~jaxlag.Event` s (terminal or only recorded), stored as a tuple.
    - ``max_segments``: the integration runs in at most this many segments between switches
      (releases, contacts, events); the segments are a ``lax.scan`` of this static length.
      Needing more is a failure (``SimulationError``), not a silent truncation.
    - ``root_finder``: the ``optimistix`` root finder that locates each event on the solver's
      dense output (default ``optimistix.Newton(rtol=1e-13, atol=1e-13)``).

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
    """What happened at the end of each segment (``max_segments`` entries).

    ``kind[k]``: 0 the end time was reached, 1 a unilateral constraint was released, 2 one made
    contact, 3 a user event fired, −1 nothing (the simulation had already finished).
    ``index[k]``: which constraint (holonomic index) or which user event.
    ``time[k]``, ``q[k]``, ``qd[k]``: the switch time and the state just after the switch.
    ``active[k]``: holonomic activity mask after the switch. ``count``: number of switches and
    events (kinds 1–3).
    """

    time: Float[Array, "*batch segments"]
    kind: Int[Array, "*batch segments"]
    index: Int[Array, "*batch segments"]
    q: Float[Array, "*batch segments n"]
    qd: Float[Array, "*batch segments n"]
    active: Bool[Array, "*batch segments m_h"]
    count: Int[Array, "*batch"]

    def kinds(self) -> list[str]:
        """The kinds as strings (host-side helper for an unbatched log)."""
        return [KIND_NAMES[int(k)] for k in jax.device_get(self.kind)]


def _masked_min(values, mask):
    return jnp.min(jnp.where(mask, values, jnp.inf), initial=jnp.inf)


class _Segment(eqx.Module):
    """Condition functions of one segment (a module so diffrax's compile cache is reused)."""

    system: Any
    events: tuple
    unilateral: Any  # (m_h,) bool
    active: Any  # (m_h,) bool
    t_start: Any
    locks: Any  # (num_events,) sign each user condition starts from at t_start (0: its own value)

    def release(self, t, y, args, **kwargs):
        return _release_value(self.system, y, t, args, self.active, self.unilateral)

    def contact(self, t, y, args, **kwargs):
        q, _ = y
        f = holonomic_residual(self.system, q, t, args)
        value = _masked_min(f, ~self.active & self.unilateral)
        return jnp.where(jnp.isfinite(value), value, 1.0)

    def user(self, j, t, y, args):
        q, qd = y
        event = self.events[j]
        available = {"t": t, "args": args}
        if "multipliers" in event.condition.keywords:
            available["multipliers"] = accelerations_and_multipliers(
                self.system, q, qd, t, args, active=self.active
            )[1]
        value = jnp.asarray(event.condition(q, qd, **available), q.dtype)
        # Just after a non-terminal event the condition is ~0; pin it to the side it moved to.
        return jnp.where((t == self.t_start) & (self.locks[j] != 0), self.locks[j], value)

    def diffrax_event(self, root_finder):
        conds, directions = [], []
        if self.system.unilateral:
            conds += [self.release, self.contact]
            directions += [False, False]
        for j, event in enumerate(self.events):
            conds.append(lambda t, y, args, _j=j, **kwargs: self.user(_j, t, y, args))
            directions.append(event.direction)
        return diffrax.Event(conds, root_finder=root_finder, direction=directions)


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


def _first(mask):
    return jnp.argmax(mask), jnp.any(mask)


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

    def lam_of(q, qd, t, active):
        return accelerations_and_multipliers(system, q, qd, t, args, active=active)[1]

    def run_segment(carry, _):
        (t_s, q, qd, active, done, locks, out_q, out_qd, out_active, filled, count, failure) = carry
        segment = _Segment(system, tuple(events), unilateral, active, t_s, locks)
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

        fired = solution.event_mask if solution.event_mask is not None else []
        fired = [jnp.asarray(x) & ~done for x in fired]
        offset = 2 if system.unilateral else 0
        released = fired[0] if system.unilateral else jnp.asarray(False)
        contacted = fired[1] if system.unilateral else jnp.asarray(False)
        user_fired = jnp.stack(fired[offset:]) if num_events else jnp.zeros((0,), bool)

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

        user_index, any_user = _first(user_fired) if num_events else (0, jnp.asarray(False))
        terminal = jnp.array([e.terminal for e in events], bool) if num_events else user_fired
        stop = jnp.any(user_fired & terminal) if num_events else jnp.asarray(False)
        happened = switched | any_user
        reached_end = ~happened & ~done
        # New locks: the side each fired non-terminal condition moved to (opposite of its start).
        if num_events:
            start_values = jnp.stack([segment.user(j, t_s, (q, qd), args) for j in range(num_events)])
            new_locks = jnp.where(user_fired, -jnp.sign(start_values), 0.0).astype(dtype)
        else:
            new_locks = locks
        kind = jnp.where(
            done,
            _NO_EVENT,
            jnp.where(released, _RELEASE, jnp.where(contacted, _CONTACT, jnp.where(any_user, _USER, _END))),
        )
        index = jnp.where(
            released, release_index, jnp.where(contacted, contact_index, jnp.where(any_user, user_index, -1))
        )
        record = (jnp.where(done, jnp.inf, t_e), kind, index, q_next, qd_next, new_active)
        count = count + happened.astype(count.dtype)
        done = done | reached_end | stop | broken
        t_next = jnp.where(done, t1, t_e)
        carry = (
            t_next,
            q_next,
            qd_next,
            new_active,
            done,
            new_locks,
            out_q,
            out_qd,
            out_active,
            filled,
            count,
            failure,
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
        jnp.zeros((num_events,), dtype),
        inf,
        inf,
        jnp.zeros((num_saves, m_h), bool),
        jnp.zeros((num_saves,), bool),
        jnp.asarray(0, jnp.int32),
        none,
    )
    carry, records = jax.lax.scan(run_segment, carry0, None, length=max_segments)
    t_last, q_last, qd_last, _, done, _, out_q, out_qd, out_active, _, count, failure = carry
    out_of_segments = ~done & (failure.code == failures.NONE)
    failure = eqx.tree_at(
        lambda f: (f.code, f.t, f.q, f.qd),
        failure,
        (
            jnp.where(out_of_segments, failures.MAX_SEGMENTS, failure.code),
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
    time, kind, index, q_rec, qd_rec, active_rec = records
    log = EventLog(time, kind, index, q_rec, qd_rec, active_rec, count)
    return ts, out_q, out_qd, out_active, log, failure
