r"""Events and unilateral constraints: integrate in segments between switches.

A unilateral constraint ``f_i(q, t) ≥ 0`` acts (``f_i = 0``) only while its multiplier keeps
the sign ``λ_i ≥ 0`` (it pushes, never pulls). The simulation runs in segments; each segment is
one ``diffrax.diffeqsolve`` with a fixed set of active constraints, ended by the first of

* release: ``min_i λ_i`` over the active unilateral constraints reaching zero from above;
* contact: ``min_i f_i`` over the inactive ones reaching zero from above;
* a friction switch of a :class:`~jaxlag.Coulomb` contact (:mod:`jaxlag._mechanics.friction`):
  ``s v_t`` of a slipping one or ``μ λ_N − |λ_t|`` of a sticking one reaching zero from above
  (the mode of each contact, 0 stick or ``s = ±1`` slip, is fixed in a segment);
* a crossing of a user :class:`Event` condition ``c_k``: ``σ_k c_k`` reaching zero from above,
  where ``σ_k = ±1`` is the side ``c_k`` starts the segment on.

With user conditions these are given to diffrax as one condition, their minimum, so that the
root find on the solver's dense output (differentiable through diffrax) locates the earliest of
them even when several happen within one solver step; which one it was is read off at the
event. (Releases and contacts alone are two diffrax conditions, as the minimum of each is
already one quantity per kind.)

At a release the constraint is switched off; at a contact the impact law of
:class:`~jaxlag.Unilateral` (:mod:`jaxlag._mechanics.impacts`) gives the velocity jump: with
restitution 0 (the default) the perfectly plastic ``q̇⁺ = q̇⁻ − M⁻¹Jᵀ(JM⁻¹Jᵀ)⁻¹J q̇⁻`` (the
mass-weighted projection onto the constraint's tangent space) and the constraint engages; with
``e > 0`` Newton's law ``ḟ⁺ = −e ḟ⁻`` and the body leaves (the constraint stays off), unless the
rebound would fly less than ``Events.zeno_time`` (an accumulation of impacts: plastic, engaged).
If a newly engaged constraint would have to pull it is released again at once. A recorded
crossing of a condition with a ``reset`` maps the state, which is then projected onto the
constraints acting after it. The impulse of each jump is recorded (``EventLog.impulses``). A terminal user
event ends the simulation; saved times after it hold ``inf`` (diffrax's convention). Each user
condition carries the side (sign) it is on into the next segment, so that the ~0 it starts
from after its own event, or an exact 0 at ``t0``, is not taken for a crossing
(:class:`Event` states the semantics).

The segments are a ``lax.scan`` of fixed length ``max_segments``, so the whole thing compiles
once and works under ``vmap`` (each batch member switching at its own times) and ``grad``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from typing import Any, cast

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
from ._conventions import UserFunction, wrap_event_function, wrap_state_function
from ._mechanics.constraints import holonomic_terms
from ._mechanics.friction import (
    decide_modes,
    friction_count,
    project_tangent_velocity,
    solve_with_modes,
    switch_values,
    tangent_terms,
)
from ._mechanics.impacts import impact
from ._stabilization import project_state, stages_for_adjoint, wrap_for_projection
from ._solver.step_once import StepOnce
from ._vector_field import EquationsOfMotion

_NO_EVENT, _END, _RELEASE, _CONTACT, _USER, _STICK, _SLIP = -1, 0, 1, 2, 3, 4, 5
_SILENT = -2  # a crossing in the direction its condition ignores: removed from the log
KIND_NAMES = {
    _NO_EVENT: "none",
    _END: "end",
    _RELEASE: "release",
    _CONTACT: "contact",
    _USER: "user",
    _STICK: "stick",
    _SLIP: "slip",
}


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
    - ``reset``: for a non-terminal event, the state map ``(q⁺, q̇⁺) = reset(q, qd, [t],
      [args])`` applied at each recorded crossing (switching systems: a thermostat, a velocity
      reversal, a mode variable). The integration continues from ``(q⁺, q̇⁺)``, which the log
      records. It runs inside the compiled program: ``jit``, ``vmap`` and ``grad`` (through the
      event time and the map) work. A reset that leaves the constraint manifold is
      **projected** back onto it (mass-weighted, as at every switch): onto ``f = 0``, ``ḟ = 0``
      of the holonomic constraints acting after it and ``g = 0`` of the velocity constraints.
      An acting unilateral constraint whose gap the reset opens (``ḟ⁺ >`` the constraint
      tolerance) is released; an inactive one that it touches while approaching or violates
      (``f < 0``) goes through an impact (:class:`~jaxlag.Unilateral`). After the reset the
      condition continues from the side the motion takes it to (the sign of ``c`` if the reset
      moved it off zero, else of ``ċ``), so a reversal ``q̇⁺ = −e q̇`` at ``c = q[0] = 0`` fires
      again at the next downward crossing.

    The event time is a root of ``c`` on the solver's dense output, found by
    :class:`~jaxlag.Events`' ``root_finder`` and differentiable (``jax.grad`` of an event time
    or of the state there works).
    """

    condition: UserFunction
    terminal: bool = eqx.field(static=True)
    direction: bool | None = eqx.field(static=True)
    reset: UserFunction | None = None

    def __init__(
        self,
        condition: Callable,
        terminal: bool = True,
        direction: bool | None = None,
        reset: Callable | None = None,
    ):
        self.condition = wrap_event_function(condition)
        self.terminal = bool(terminal)
        self.direction = direction
        if reset is not None and self.terminal:
            raise ValueError(
                "jl.Event(reset=...) maps the state at a crossing to the state the integration "
                "continues from: it needs a non-terminal event. Pass terminal=False."
            )
        self.reset = wrap_state_function(reset, "event reset")


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
      nothing at run time, so a generous value is cheap. Each friction switch
      (:class:`~jaxlag.Coulomb`: ``"stick"``, ``"slip"``) ends a segment too. Needing more is a failure
      (``SimulationError``), never a silent truncation; the message says how far the run got
      with the segments it had and the value to pass.
    - ``root_finder``: the ``optimistix`` root finder that locates each event on the solver's
      dense output (default ``optimistix.Newton(rtol=1e-13, atol=1e-13)``; in lower precision
      than float64 the default's tolerances are ``√ε``, 3.5e-4 in float32, as 1e-13 is below
      round-off there: the default, or a ``Newton`` equal to it, is adapted to the dtype).
      Any other root finder is used as given.
    - ``zeno_time``: an impact on a unilateral constraint with restitution (see
      :class:`~jaxlag.Unilateral`) whose rebound would fly for less than ``zeno_time`` is taken
      as the end of an accumulation of impacts (a ball bouncing to rest, infinitely many
      impacts in finite time): it is plastic and the contact persists. The flight is predicted
      at the impact as ``τ = 2 e |ḟ⁻| / |f̈|`` (``ḟ⁻`` the approach rate, ``f̈ < 0`` the normal
      acceleration pressing the body onto the constraint; exact under gravity, where it is
      ``2 e v / g``); bodies not pressed on (``f̈ ≥ 0``) never count. Default ``None``:
      ``10⁻³ (t1 − t0)`` of the run, so the bounces cut off are shorter than a thousandth of the
      simulated time (a ball is then at rest after ``log(τ / (2√(2h/g))) / log e`` bounces: 24
      for ``e = 0.8``, ``h = 1``, 5 s; each bounce is a segment, count them in
      ``max_segments``).

    The segmented mode runs when the system has ``unilateral`` constraints or ``conditions`` is
    non-empty; it needs save times ``ts``. ``simulate(..., events=...)`` also takes a single
    :class:`~jaxlag.Event` or a sequence of them, as ``Events(*conditions)``.
    """

    conditions: tuple[Event, ...]
    max_segments: int = eqx.field(static=True)
    root_finder: optx.AbstractRootFinder
    zeno_time: float | None = eqx.field(static=True)

    def __init__(
        self,
        *conditions: Event,
        max_segments: int = 8,
        root_finder: optx.AbstractRootFinder = _DEFAULT_ROOT_FINDER,
        zeno_time: float | None = None,
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
        if zeno_time is not None:
            if not isinstance(zeno_time, numbers.Real) or isinstance(zeno_time, bool):
                raise TypeError(f"zeno_time must be a number of seconds or None; got {zeno_time!r}.")
            if not (math.isfinite(zeno_time) and zeno_time >= 0):
                raise ValueError(f"zeno_time must be finite and non-negative; got {zeno_time!r}.")
            zeno_time = float(zeno_time)
        self.conditions = tuple(conditions)
        self.max_segments = int(max_segments)
        self.root_finder = root_finder
        self.zeno_time = zeno_time


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
      made contact, 3 a user event fired, 4 a Coulomb contact started to stick, 5 one started
      to slip (from sticking, or reversing at ``v_t = 0``), −1 padding (the run had already
      ended, at the end time, a terminal event or a failure). :meth:`kinds` gives the names of
      the real entries.
    - ``index[k]``: which constraint (holonomic index), which user event (position in
      ``Events.conditions``) or which Coulomb contact (position in ``System.friction``); −1
      for the end.
    - ``time[k]``, ``q[k]``, ``qd[k]``: the switch time and the state just after the switch
      (after the plastic impact of a contact); ``time`` is ``inf`` for padding.
    - ``active[k]``: holonomic activity mask after the switch. After a contact with
      restitution the constraint is inactive if the body rebounds (``e > 0``) and active if it
      stays (``e = 0``, or the end of an accumulation of impacts: ``Events.zeno_time``).
    - ``impulses[k]``: the impulse ``Λ`` (m_h,) on each holonomic row at the switch,
      ``M(q̇⁺ − q̇⁻) = JᵀΛ (+ Aᵀ·)``, in momentum units with the sign of ``λ`` (``Λ_i ≥ 0``
      pushes on a unilateral row); zero where nothing jumped (ends, releases, events without
      reset). For a ball of mass ``m`` hitting the floor at speed ``v`` with restitution ``e``,
      ``Λ = (1 + e) m v``.
    - ``count``: the number of switches and events (kinds 1–5).
    - ``modes[k]``: the friction mode of each Coulomb contact (k,) after the switch: 0
      sticking, +1 slipping with ``v_t > 0``, −1 with ``v_t < 0`` (0 also where the contact's
      normal row does not act: see ``active``). Shape (segments, 0) without friction.
    """

    time: Float[Array, "*batch segments"]
    kind: Int[Array, "*batch segments"]
    index: Int[Array, "*batch segments"]
    q: Float[Array, "*batch segments n"]
    qd: Float[Array, "*batch segments n"]
    active: Bool[Array, "*batch segments m_h"]
    impulses: Float[Array, "*batch segments m_h"]
    count: Int[Array, "*batch"]
    modes: Int[Array, "*batch segments k"] | None = None

    def kinds(self) -> list[str] | list[list[str]]:
        """The names of the real entries (``"release"``, ``"contact"``, ``"user"``, ``"stick"``,
        ``"slip"``, ``"end"``),
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
    # (m_h,) inactive unilateral constraints that touch (f ≈ 0) at t_start: just rebounded,
    # released or reset there. None: none.
    departing: Any = None
    # (k,) friction mode of each Coulomb contact in the segment (0 stick, ±1 slip); None: none.
    modes: Any = None

    def release(self, t, y, args, **kwargs):
        """``min λ`` over the active unilateral constraints; 1 if there is none (a diffrax
        condition of its own: a constant that never crosses)."""
        value = self.release_raw(t, y, args)
        return jnp.where(jnp.isfinite(value), value, 1.0).astype(_condition_dtype())

    def release_raw(self, t, y, args):
        return _release_value(self.system, y, t, args, self.active, self.unilateral, self.modes).astype(
            _condition_dtype()
        )

    def contact(self, t, y, args, **kwargs):
        """:meth:`contact_raw`, 1 where it is ``inf`` (a diffrax condition of its own)."""
        value = self.contact_raw(t, y, args)
        return jnp.where(jnp.isfinite(value), value, 1.0).astype(_condition_dtype())

    def contact_raw(self, t, y, args):
        """``min_i f_i`` over the inactive unilateral constraints (``inf`` at ``t_start`` and
        where there is none), ``f_i / (t − t_start)`` for the :attr:`departing` ones.

        The division keeps the roots of ``f_i`` after ``t_start`` but not the one at ``t_start``
        of a body that has just rebounded from ``f_i = 0``: there ``f_i ≈ ḟ⁺ δ − ½|f̈| δ²``
        (``δ = t − t_start``), ``f_i ≤ 0`` at both ends of a solver step longer than the flight
        (the landing would be missed), while the quotient starts at ``ḟ⁺ > 0`` and is close to
        linear (Newton, started at the step's end, converges at once). The other rows keep
        ``f_i``: concave and decreasing at a landing, where Newton from the right converges
        monotonically (``f/δ`` is convex there and Newton would overshoot)."""
        q, _ = y
        f = holonomic_residual(self.system, q, t, args)
        later = t > self.t_start
        if self.departing is not None:
            elapsed = jnp.where(later, t - self.t_start, 1.0).astype(f.dtype)
            f = jnp.where(self.departing, f / elapsed, f)
        value = _masked_min(f, ~self.active & self.unilateral)
        return jnp.where(later, value, jnp.inf).astype(_condition_dtype())

    def raw(self, j, t, y, args):
        """The user's condition ``c_j`` at ``(t, q, q̇)``."""
        q, qd = y
        event = self.events[j]
        available = {"t": t, "args": args}
        if "multipliers" in event.condition.keywords:
            available["multipliers"] = solve_with_modes(
                self.system, q, qd, t, args, active=self.active, modes=self.modes
            )[1]
        return jnp.asarray(event.condition(q, qd, **available), _condition_dtype())

    def signed(self, t, y, args):
        """``σ_k c_k`` for each user condition: positive on the side it starts the segment on
        (``+inf`` where that side is unknown, ``σ_k = 0``); it turns ≤ 0 when ``c_k`` crosses."""
        values = jnp.stack([self.raw(j, t, y, args) for j in range(len(self.events))])
        return jnp.where(self.sides != 0, self.sides * values, jnp.inf)

    def friction_raw(self, t, y, args):
        """``min`` over the Coulomb contacts of ``s v_t`` (slipping) and ``μ λ_N − |λ_t|``
        (sticking); ``inf`` if no contact acts (:func:`jaxlag._mechanics.friction.switch_values`)."""
        return _friction_value(self.system, y, t, args, self.active, self.modes).astype(_condition_dtype())

    def switches(self, t, y, args, release: bool = True):
        """The quantities that end the segment when they reach 0 from above: ``[min λ`` over the
        active unilateral constraints, ``min f`` over the inactive ones``]`` (if the system has
        unilateral constraints), the friction switch (if it has Coulomb contacts), then
        ``σ_k c_k`` for each user condition. ``release=False``: without the two that need the
        KKT solve (``min λ`` and the friction switch)."""
        values = []
        if self.system.unilateral:
            values = [self.release_raw(t, y, args)] if release else []
            values.append(self.contact_raw(t, y, args))
        if self.system.friction and release:
            values.append(self.friction_raw(t, y, args))
        if self.events:
            values.append(self.signed(t, y, args))
        if not values:
            return jnp.zeros((0,), _condition_dtype())
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
        # The minimum over the finite terms (``inf``: no constraint of that kind, a side not
        # known); 1 if there is none. A constant placeholder among them would cap the minimum
        # and stall the root find where the real terms are above it.
        smallest = jnp.min(jnp.where(jnp.isfinite(values), values, jnp.inf))
        return jnp.where(jnp.isfinite(smallest), smallest, 1.0)

    def diffrax_event(self, root_finder):
        if not self.events and not self.system.friction:  # releases and contacts: min λ, min f
            return diffrax.Event([self.release, self.contact], root_finder=root_finder, direction=[False] * 2)
        return diffrax.Event(self.crossing, root_finder=root_finder, direction=False)


@compilation.filter_jit
def _release_value(system, y, t, args, active, unilateral, modes=None):
    """The release condition ``min λ`` over the active unilateral constraints (``inf`` if none).

    Jitted on its own: diffrax traces event conditions a dozen times per solve (its checks, the
    loop body's static analysis, the root finder), and each trace is a full KKT solve; JAX's
    tracing cache serves the repeats (the sphere release simulation traces 1.3 → 1.1 s)."""
    q, qd = y
    lam = solve_with_modes(system, q, qd, t, args, active=active, modes=modes)[1]
    return _masked_min(lam, active & unilateral)


@compilation.filter_jit
def _friction_value(system, y, t, args, active, modes):
    """The friction switch: ``min`` over the contacts of ``s v_t`` and ``μ λ_N − |λ_t|``
    (``inf`` if none acts). Jitted on its own, as :func:`_release_value` (traced once)."""
    q, qd = y
    return jnp.min(switch_values(system, q, qd, t, args, active, modes), initial=jnp.inf)


_STEP_COUNTS = ("num_steps", "num_accepted_steps", "num_rejected_steps")


def _reset_branch(event: Event, j: int, n: int, dtype):
    """``(q, q̇, t, args) ↦ (q⁺, q̇⁺)`` of user event ``j``: its reset, checked (shapes), or the
    identity (a ``lax.switch`` branch)."""

    def identity(q, qd, t, args):
        return q, qd

    reset = event.reset
    if reset is None:
        return identity

    def apply(q, qd, t, args):
        out = reset(q, qd, t=t, args=args)
        if not (isinstance(out, (tuple, list)) and len(out) == 2):
            raise ValueError(
                f"The reset of event {j} ({reset.fn!r}) must return a pair (q, qd); got {type(out).__name__}."
            )
        q_new, qd_new = (jnp.asarray(x) for x in out)
        if q_new.shape != (n,) or qd_new.shape != (n,):
            raise ValueError(
                f"The reset of event {j} ({reset.fn!r}) must return q and qd of shape ({n},), like "
                f"the state; got {q_new.shape} and {qd_new.shape}."
            )
        return q_new.astype(dtype), qd_new.astype(dtype)

    return apply


def _crossed_to(direction: bool | None) -> float:
    """The side a condition is on after a crossing in ``direction`` (0: the opposite of before)."""
    return 0.0 if direction is None else (1.0 if direction else -1.0)


def initial_sides(segment: _Segment, baumgarte, q0, qd0, t0, args, with_values: bool = False):
    r"""The side (±1) each user condition starts on at ``t0``: the sign of the first non-zero of
    ``c``, ``ċ``, ``c̈`` there, the derivatives along the motion (Lie derivatives along the
    equations of motion ``ẏ = (q̇, q̈)``, by nested ``jax.jvp``); 0 if all three vanish.

    So ``t0`` is never a crossing: a condition that is exactly 0 at ``t0`` is on the side it
    leaves to, and its first event is its next sign change. The same rule gives the sides
    after a jump of the state (a contact, a release, a reset). ``with_values``: also return
    ``(c, ċ, c̈)``."""
    num_events = len(segment.events)
    dtype = _condition_dtype()
    if not num_events:
        return jnp.zeros((0,), dtype)
    field = EquationsOfMotion(segment.system, baumgarte, segment.active, segment.modes)
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
    side = jnp.where(jnp.isfinite(side), side, 0.0).astype(dtype)
    if with_values:
        return side, (c0, c1, c2)
    return side


class _SegmentCarry(eqx.Module):
    """What one segment of :func:`solve_segments` hands to the next (the ``lax.scan`` carry)."""

    t: Array  # the segment's start (t1 once done)
    q: Array
    qd: Array
    active: Array  # (m_h,) acting one-sided rows
    modes: Array  # (contacts,) friction modes: 0 stick, ±1 slip
    done: Array
    sides: Array  # (events,) the side of each user condition
    out_q: Array  # (saves, n): the saves filled so far, inf elsewhere
    out_qd: Array
    out_active: Array
    out_modes: Array
    filled: Array  # (saves,) which saves are filled
    count: Array  # events that happened
    failure: failures.Failure
    steps: dict[str, Array]  # diffrax's step counts, summed


class _SegmentRecord(eqx.Module):
    """What one segment leaves in the :class:`EventLog` (one row of the ``lax.scan`` output)."""

    time: Array
    kind: Array
    index: Array
    q: Array
    qd: Array
    active: Array
    impulses: Array
    modes: Array


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
    zeno_time=None,
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

    def lam_of(q, qd, t, active, modes):
        return solve_with_modes(system, q, qd, t, args, active=active, modes=modes)[1]

    # Coulomb friction (jaxlag._mechanics.friction): the mode of each contact, 0 stick, ±1 slip.
    num_friction = friction_count(system)
    has_friction = num_friction > 0
    contacts = jnp.asarray([e.contact for e in system.friction], jnp.int32)

    def normal_acting(active):
        return active[contacts] if has_friction else jnp.zeros((0,), bool)

    def tangent_velocity(q, qd, t):
        return tangent_terms(system, q, qd, t, args)[1]

    if has_friction:
        # At t0: a contact at rest (|v_t| ≤ the constraint tolerance) sticks if it can; the
        # sticking contacts' v_t is then made exactly 0 (a mass-weighted projection).
        acting0 = normal_acting(active0)
        t0_ = jnp.asarray(t0, dtype)
        v0 = tangent_velocity(q0, qd0, t0_)
        modes0 = decide_modes(system, q0, qd0, t0_, args, active0, acting0 & (jnp.abs(v0) <= tolerance), v0)
        modes0 = jnp.where(acting0, modes0, 0.0)
        sticking0 = acting0 & (modes0 == 0)
        qd0 = jnp.where(
            jnp.any(sticking0),
            project_tangent_velocity(system, q0, qd0, t0_, args, active0, sticking0),
            qd0,
        )
    else:
        modes0 = jnp.zeros((0,), dtype)

    # Impacts that end an accumulation (Zeno) are plastic: see Events' zeno_time.
    span = jnp.asarray(t1, dtype) - jnp.asarray(t0, dtype)
    zeno = 1e-3 * span if zeno_time is None else jnp.asarray(zeno_time, dtype)
    has_reset = any(e.reset is not None for e in events)
    newton = 4 if has_reset else 2
    reset_branches = [_reset_branch(e, j, n, dtype) for j, e in enumerate(events)]

    def run_segment(carry: _SegmentCarry, _) -> tuple[_SegmentCarry, _SegmentRecord]:
        t_s, q, qd, active, modes = carry.t, carry.q, carry.qd, carry.active, carry.modes
        done, sides, filled, count, failure, steps = (
            carry.done,
            carry.sides,
            carry.filled,
            carry.count,
            carry.failure,
            carry.steps,
        )
        out_q, out_qd, out_active, out_modes = carry.out_q, carry.out_qd, carry.out_active, carry.out_modes
        departing = (
            unilateral & ~active & (holonomic_residual(system, q, t_s, args) <= tolerance) if m_h else None
        )
        segment = _Segment(system, tuple(events), unilateral, active, t_s, sides, departing, modes)
        this_solver = stages_for_adjoint(solver, adjoint)  # diffrax does not see it in StepOnce
        if projection is not None:
            this_solver = wrap_for_projection(this_solver, system, projection, adjoint, active)
        this_solver = StepOnce(this_solver)  # traced once, not once per diffrax body trace
        controller = guard(stepsize_controller)
        solution = diffrax.diffeqsolve(
            diffrax.ODETerm(EquationsOfMotion(system, baumgarte, active, modes)),
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
        out_modes = jnp.where(take[:, None], modes[None, :], out_modes)
        filled = filled | take

        # A failed segment records nothing: its events are not events of the motion.
        fired = [jnp.asarray(x) & ~done & ~broken for x in jax.tree.leaves(solution.event_mask)]
        friction_at = 2 if system.unilateral else 0  # the friction switch's place in `switches`
        offset = friction_at + (1 if has_friction else 0)
        if num_events or has_friction:
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
            field = EquationsOfMotion(system, baumgarte, active, modes)

            def rated(t, y):  # contact gap and σ_k c_k: cheap to differentiate along the motion
                return segment.switches(t, y, args, release=False)

            _, rates = jax.jvp(rated, (t_e, y_e), (jnp.ones_like(t_e), field(t_e, y_e, args)))
            # The release and friction switches are taken as decreasing (their rates would need
            # the derivative of the KKT solve).
            minus = -jnp.ones((1,), rates.dtype)
            parts = [minus, rates[:1]] if system.unilateral else []
            parts += [minus] if has_friction else []
            parts.append(rates[1:] if system.unilateral else rates)
            rates = jnp.concatenate(parts)
            leaving = jnp.where(rates < 0, values_e, jnp.inf)
            which = jnp.where(jnp.any(jnp.isfinite(leaving)), jnp.argmin(leaving), jnp.argmin(values_e))
            released = hit & (which == 0) if system.unilateral else jnp.asarray(False)
            contacted = hit & (which == 1) if system.unilateral else jnp.asarray(False)
            user_hit = hit & (which >= offset) if num_events else jnp.asarray(False)
            frictioned = hit & (which == friction_at) if has_friction else jnp.asarray(False)
        else:
            which = jnp.asarray(0)
            values_e = jnp.zeros((1,), _condition_dtype())  # read only with user conditions
            released, contacted = fired[0], fired[1]
            user_hit = frictioned = jnp.asarray(False)

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
        else:
            user_index, any_user, side = jnp.asarray(0), jnp.asarray(False), jnp.asarray(0.0)
            silent = stop = jnp.asarray(False)
        # A recorded crossing of a condition with a reset: the user's map of the state.
        if has_reset:
            reset_fired = any_user & jnp.array([e.reset is not None for e in events], bool)[user_index]
            q_r, qd_r = jax.lax.switch(user_index, reset_branches, q_e, qd_e, t_e, args)
            q_r, qd_r = jnp.where(reset_fired, q_r, q_e), jnp.where(reset_fired, qd_r, qd_e)
        else:
            reset_fired = jnp.asarray(False)
            q_r, qd_r = q_e, qd_e
        switched = released | contacted
        jumped = switched | reset_fired

        new_active = active
        release_index = contact_index = jnp.asarray(0)
        impulses = jnp.zeros((m_h,), dtype)
        q_p, qd_p = q_r, qd_r
        if m_h:
            # Which constraint switched: the one whose multiplier / gap is at its minimum.
            lam_e = lam_of(q_e, qd_e, t_e, active, modes)
            f_e = holonomic_residual(system, q_e, t_e, args)
            release_index = jnp.argmin(jnp.where(active & unilateral, lam_e, jnp.inf))
            contact_index = jnp.argmin(jnp.where(~active & unilateral, f_e, jnp.inf))
            rows_h = jnp.arange(m_h)
            released_row = released & (rows_h == release_index)
            forced = contacted & (rows_h == contact_index)
            if has_reset:  # an acting unilateral constraint whose gap the reset opens lets go
                f_dot_r = holonomic_terms(system, q_r, qd_r, t_e, args)[1]
                leaving = reset_fired & unilateral & active & (f_dot_r > tolerance)
            else:
                leaving = jnp.zeros((m_h,), bool)
            before = active & ~released_row & ~leaving
            # The impulse (restitution, simultaneous impacts, Zeno: jaxlag._mechanics.impacts);
            # at a release or a reset without impact, the velocity projection onto the acting rows.
            qd_i, impulses, after_impact, rebound = impact(
                system, q_r, qd_r, t_e, args, before, unilateral, forced, released_row, zeno, tolerance
            )
            # Positions onto the rows that touch (acting or rebounding from f = 0), velocities onto
            # the acting ones (a rebound keeps ḟ⁺ = e|ḟ⁻|).
            # (A reset may move q far off: 4 Newton steps take 10% to round-off; else 2.)
            q_p = project_state(system, q_r, qd_i, t_e, args, newton, after_impact | rebound)[0]
            qd_p = project_state(system, q_p, qd_i, t_e, args, 0, after_impact, refresh_mass=True)[1]
            # A constraint that would have to pull right after engaging separates again.
            lam_p = lam_of(q_p, qd_p, t_e, after_impact, modes)
            pulls = after_impact & ~before & unilateral & (lam_p < 0)
            new_active = jnp.where(jumped, after_impact & ~pulls, active)
            impulses = jnp.where(jumped, impulses, 0.0)
        elif has_reset and system.velocity_constraints is not None:
            qd_p = project_state(system, q_r, qd_r, t_e, args, 0, refresh_mass=True)[1]
        q_next = jnp.where(jumped, q_p, q_e)
        qd_next = jnp.where(jumped, qd_p, qd_e)

        new_modes, friction_index = modes, jnp.asarray(0)
        if has_friction:
            # The friction modes after the switch (jaxlag._mechanics.friction). The contact whose
            # switch ended the segment: slip → try stick (else slip the other way); stick →
            # slip where the net force drives it, s = −sign λ_t. A contact that has just
            # engaged sticks if at rest, else slips along v_t; the others keep their mode
            # (sticking ones are tested again: a jump may break them loose).
            friction_index = jnp.argmin(switch_values(system, q_e, qd_e, t_e, args, active, modes))
            lam_t_e = solve_with_modes(system, q_e, qd_e, t_e, args, active=active, modes=modes)[3]
            event_row = frictioned & (jnp.arange(num_friction) == friction_index)
            was_acting, acting = normal_acting(active), normal_acting(new_active)
            v_next = tangent_velocity(q_next, qd_next, t_e)
            newly = acting & ~was_acting
            candidates = jnp.where(newly, jnp.abs(v_next) <= tolerance, modes == 0)
            directions = jnp.where(newly, v_next, modes)
            candidates = jnp.where(event_row, modes != 0, candidates)
            directions = jnp.where(event_row & (modes == 0), -lam_t_e, directions)
            decided = decide_modes(
                system, q_next, qd_next, t_e, args, new_active, acting & candidates, directions
            )
            decided = jnp.where(acting, decided, 0.0)
            # v_t = 0 exactly where a contact sticks, or starts to slip from rest.
            zero = acting & ((decided == 0) | event_row)
            qd_f = project_tangent_velocity(system, q_next, qd_next, t_e, args, new_active, zero)
            changed = jumped | frictioned
            qd_next = jnp.where(changed & jnp.any(zero), qd_f, qd_next)
            new_modes = jnp.where(changed, decided, modes)

        if num_events:
            # The sides for the next segment: the crossed condition is now on the other side;
            # the others have not crossed before it. After a jump of the state (release,
            # contact, reset) each is on the side the motion takes it to, by the rule at t0
            # (the first non-zero of c, ċ, c̈; 0, never crossing, if all vanish), or keeps its
            # own side if the values are not finite.
            after = _Segment(system, tuple(events), unilateral, new_active, t_e, sides, modes=new_modes)
            _, (c_after, rate_after, curvature_after) = initial_sides(
                after, baumgarte, q_next, qd_next, t_e, args, with_values=True
            )
            # A condition at zero within round-off (√ε) crosses at this very instant, together
            # with the switch: it keeps its side and is recorded next, at the same time; one
            # that stays at zero (ċ = c̈ = 0, at rest) never crosses (side 0); one the jump
            # moved off zero takes the side of its value.
            tiny = jnp.sqrt(jnp.finfo(c_after.dtype).eps)
            by_rate = jnp.where(rate_after != 0, jnp.sign(rate_after), jnp.sign(curvature_after))
            at_zero = jnp.where(by_rate == 0, 0.0, jnp.where(sides != 0, sides, by_rate))
            jump_sides = jnp.where(jnp.abs(c_after) > tiny, jnp.sign(c_after), at_zero)
            finite = jnp.isfinite(c_after) & jnp.isfinite(rate_after) & jnp.isfinite(curvature_after)
            jump_sides = jnp.where(finite, jump_sides, sides).astype(sides.dtype)
            new_sides = jnp.where(
                user_hit, sides.at[user_index].set(-side), jnp.where(switched, jump_sides, sides)
            )
            if has_reset:
                # The crossed condition of a reset sits at its root (c ≈ 0 up to the root
                # finder's residual, of either sign) unless the reset moved it off zero (beyond
                # 10³ × that residual): then the sign of c, else of ċ (c̈), along the motion.
                c_k, rate_k, curvature_k = (
                    c_after[user_index],
                    rate_after[user_index],
                    curvature_after[user_index],
                )
                residual = jnp.abs(values_e[which])
                moved = jnp.abs(c_k) > 1e3 * (
                    jnp.where(jnp.isfinite(residual), residual, 0.0) + jnp.finfo(c_k.dtype).eps
                )
                by_rate = jnp.where(rate_k != 0, jnp.sign(rate_k), jnp.sign(curvature_k))
                side_k = jnp.where(moved, jnp.sign(c_k), jnp.where(by_rate != 0, by_rate, -side))
                new_sides = jnp.where(reset_fired, jump_sides.at[user_index].set(side_k), new_sides)
        else:
            new_sides = sides
        happened = switched | any_user | frictioned
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
        if has_friction:
            stuck = new_modes[friction_index] == 0
            kind = jnp.where(frictioned & ~done & ~broken, jnp.where(stuck, _STICK, _SLIP), kind)
        index = jnp.where(
            released, release_index, jnp.where(contacted, contact_index, jnp.where(any_user, user_index, -1))
        )
        index = jnp.where(frictioned, friction_index, index)
        record = _SegmentRecord(
            time=jnp.where(done | broken, jnp.inf, t_e),
            kind=kind,
            index=index,
            q=q_next,
            qd=qd_next,
            active=new_active,
            impulses=impulses,
            modes=new_modes.astype(jnp.int32),
        )
        count = count + happened.astype(count.dtype)
        ran = ~done
        steps = {
            key: value + jnp.where(ran, solution.stats[key], 0).astype(value.dtype)
            for key, value in steps.items()
        }
        done = done | reached_end | stop | broken
        t_next = jnp.where(done, t1, t_e)
        carry = _SegmentCarry(
            t=t_next,
            q=q_next,
            qd=qd_next,
            active=new_active,
            modes=new_modes,
            done=done,
            sides=new_sides,
            out_q=out_q,
            out_qd=out_qd,
            out_active=out_active,
            out_modes=out_modes,
            filled=filled,
            count=count,
            failure=failure,
            steps=steps,
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
    carry0 = _SegmentCarry(
        t=t0,
        q=q0,
        qd=qd0,
        active=active0,
        modes=modes0,
        done=jnp.asarray(False),
        sides=cast(
            Array,
            initial_sides(
                _Segment(system, tuple(events), unilateral, active0, t0, None, modes=modes0),
                baumgarte,
                q0,
                qd0,
                t0,
                args,
            ),
        ),
        out_q=inf,
        out_qd=inf,
        out_active=jnp.zeros((num_saves, m_h), bool),
        out_modes=jnp.zeros((num_saves, num_friction), dtype),
        filled=jnp.zeros((num_saves,), bool),
        count=jnp.asarray(0, jnp.int32),
        failure=none,
        steps={key: jnp.asarray(0, jnp.int32) for key in _STEP_COUNTS},
    )
    carry, records = jax.lax.scan(run_segment, carry0, None, length=max_segments)
    t_last, q_last, qd_last, done, failure = carry.t, carry.q, carry.qd, carry.done, carry.failure
    out_q, out_qd, out_active, out_modes = carry.out_q, carry.out_qd, carry.out_active, carry.out_modes
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
    ran = jnp.sum(records.kind != _NO_EVENT).astype(jnp.int32)
    # The unrecorded crossings leave the log (a stable sort puts them behind the real
    # entries), then read as padding.
    silent = records.kind == _SILENT
    order = jnp.argsort(silent, stable=True)
    records = jax.tree.map(lambda x: x[order], records)
    silent = silent[order]
    log = EventLog(
        time=jnp.where(silent, jnp.inf, records.time),
        kind=jnp.where(silent, _NO_EVENT, records.kind),
        index=jnp.where(silent, -1, records.index),
        q=records.q,
        qd=records.qd,
        active=records.active,
        impulses=records.impulses,
        count=carry.count,
        modes=records.modes,
    )
    # The statistics of the whole run: diffrax's, summed over the segments that ran.
    stats = {**carry.steps, "max_steps": max_steps, "num_segments": ran}
    return ts, out_q, out_qd, out_active, log, failure, stats, out_modes.astype(jnp.int32)
