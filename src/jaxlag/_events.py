r"""Events and unilateral constraints: integrate in segments between switches.

A unilateral constraint ``f_i(q, t) ≥ 0`` acts (``f_i = 0``) only while its multiplier keeps
the sign ``λ_i ≥ 0`` (it pushes, never pulls). The simulation runs in segments; each segment is
one ``diffrax.diffeqsolve`` with a fixed set of active constraints, ended by the first of

* release: ``min_i λ_i`` over the active unilateral constraints reaching zero from above;
* contact: ``min_i f_i`` over the inactive ones reaching zero from above;
* a friction switch of a [`Coulomb`][jaxlag.Coulomb] contact (`jaxlag._mechanics.friction`):
  ``s v_t`` of a slipping one or ``μ λ_N − |λ_t|`` of a sticking one reaching zero from above
  (the mode of each contact, 0 stick or ``s = ±1`` slip, is fixed in a segment);
* a crossing of a user `Event` condition ``c_k``: ``σ_k c_k`` reaching zero from above,
  where ``σ_k = ±1`` is the side ``c_k`` starts the segment on.

With user conditions these are given to diffrax as one condition, their minimum, so that the
root find on the solver's dense output (differentiable through diffrax) locates the earliest of
them even when several happen within one solver step; which one it was is read off at the
event. (Releases and contacts alone are two diffrax conditions, as the minimum of each is
already one quantity per kind.)

At a release the constraint is switched off; at a contact the impact law of
[`Unilateral`][jaxlag.Unilateral] (`jaxlag._mechanics.impacts`) gives the velocity jump: with
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
(`Event` states the semantics).

This module holds what users write and read (`Event`, `Events`, `EventLog`);
the loop that runs the segments, a ``lax.scan`` of fixed length ``max_segments`` that compiles
once and works under ``vmap`` and ``grad``, is `jaxlag._segment_loop`.
"""

import enum
import math
import numbers
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _compile as compilation
from ._conventions import UserFunction, wrap_event_function, wrap_state_function
from ._custom_types import Validated


class EventKind(enum.IntEnum):
    """What ended a segment of the segmented integration: the values of
    [`EventLog.kind`][jaxlag.EventLog]. ``traj.events.kind`` is an integer array (one entry
    per segment, batch axes first); compare it with these members by name, inside or outside
    ``jit``: ``traj.events.kind == jl.EventKind.CONTACT``. (An ``IntEnum``, not an
    ``eqx.Enumeration``, so that the comparison works on the integer arrays of the log.)

    - ``END`` (0): the end time was reached; ``NONE`` (−1): padding after the run ended.
    - ``RELEASE`` (1): a unilateral constraint was released.
    - ``CONTACT`` (2): a unilateral constraint was hit and engaged: a plastic impact
      (restitution 0, or the impact that ends an accumulation of impacts), after which the
      contact persists.
    - ``USER`` (3): a user [`Event`][jaxlag.Event] fired.
    - ``STICK`` (4), ``SLIP`` (5): a [`Coulomb`][jaxlag.Coulomb] contact started to stick / slip.
    - ``IMPACT`` (6): a unilateral constraint was hit and the body rebounded (restitution
      ``e > 0``: the constraint stays inactive). The bounces of a ball are ``IMPACT`` entries;
      the last one, at rest, a ``CONTACT``. [`EventLog.impact_times`][jaxlag.EventLog] gives
      the times of both.
    - ``SILENT`` (−2): a crossing in the direction its condition ignores; it never reaches the
      log (it ends a segment, and the log drops it).
    """

    SILENT = -2  # a crossing in the direction its condition ignores: removed from the log
    NONE = -1  # padding: the run had already ended
    END = 0
    RELEASE = 1
    CONTACT = 2
    USER = 3
    STICK = 4
    SLIP = 5
    IMPACT = 6

    @property
    def label(self) -> str:
        """The name `EventLog.kinds` gives the kind: ``"contact"``, ``"end"``, ..."""
        return self.name.lower()


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
      [`Events`][jaxlag.Events]' ``max_segments``).
    - ``terminal``: stop the simulation at the event (saved times after it hold ``inf``);
      otherwise the event is only recorded in [`EventLog`][jaxlag.EventLog] and the integration
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
      (``f < 0``) goes through an impact ([`Unilateral`][jaxlag.Unilateral]). After the reset the
      condition continues from the side the motion takes it to (the sign of ``c`` if the reset
      moved it off zero, else of ``ċ``), so a reversal ``q̇⁺ = −e q̇`` at ``c = q[0] = 0`` fires
      again at the next downward crossing.

    The event time is a root of ``c`` on the solver's dense output, found by
    [`Events`][jaxlag.Events]' ``root_finder`` and differentiable (``jax.grad`` of an event time
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


class ResolvedNewton(optx.AbstractRootFinder):
    """optimistix's ``Newton``, which also stops, successfully, once its step in ``t`` is below
    the resolution of ``t`` (4 ulps) strictly inside the bracket of the event.

    ``Newton`` stops when its last step is below ``atol + rtol |t|`` *and* ``|c| < atol``. The
    second test has no relative part: near a root ``c`` cannot come closer to 0 than
    ``|ċ|`` times half the spacing of the floating-point numbers around ``t``, which grows with
    ``t`` (5.7e-14 s from t = 256 s on in float64). A ball landing at 4.4 m/s after t = 256 s
    has ``|c| ≥ 1.3e-13`` at every representable time near some of its landings: Newton's step
    rounds to 0 there, it repeats it until its step limit, and the run failed ("maximum number
    of steps ... nonlinear solver"), by chance, at some landing after 256 s (eagerly for some
    heights, under ``jit`` for others, as compiling changes the round-off). A step below the
    resolution of ``t`` means the root is located as well as ``t`` can say it. At an end of the
    bracket a zero step can also be Newton pointing out of it, which is no root: that case
    keeps ``Newton``'s own test."""

    rtol: float
    atol: float
    norm: Callable = optx.max_norm

    @property
    def newton(self) -> optx.Newton:
        return optx.Newton(rtol=self.rtol, atol=self.atol, norm=self.norm)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        state = self.newton.init(fn, y, args, options, f_struct, aux_struct, tags)
        return state, jax.tree.map(lambda x: jnp.full_like(x, jnp.inf), y)

    def step(self, fn, y, args, options, state, tags):
        inner, _ = state
        new_y, inner, aux = self.newton.step(fn, y, args, options, inner, tags)
        return new_y, (inner, jax.tree.map(jnp.subtract, new_y, y)), aux

    def terminate(self, fn, y, args, options, state, tags):
        inner, last_step = state
        stop, result = self.newton.terminate(fn, y, args, options, inner, tags)
        lower, upper = options.get("lower"), options.get("upper")

        def resolved(x, dx, low, high):
            eps = jnp.finfo(x.dtype).eps
            scale = jnp.maximum(jnp.maximum(jnp.abs(low), jnp.abs(high)), jnp.abs(x))
            inside = (x > low) & (x < high)
            return jnp.all((jnp.abs(dx) <= 4 * eps * scale) & inside)

        if lower is None or upper is None:
            return stop, result
        done = jax.tree.leaves(jax.tree.map(resolved, y, last_step, lower, upper))
        at_resolution = jnp.all(jnp.stack(done))
        return stop | at_resolution, optx.RESULTS.where(stop, result, optx.RESULTS.successful)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.newton.postprocess(fn, y, aux, args, options, state[0], tags, result)


def root_finder_for(root_finder: optx.AbstractRootFinder, dtype) -> optx.AbstractRootFinder:
    """The root finder a run uses: the default, `ResolvedNewton` with tolerances that follow
    ``dtype`` (`default_root_tolerance`); any other root finder is used as given."""
    if _is_default(root_finder):
        tol = default_root_tolerance(dtype)
        return ResolvedNewton(rtol=tol, atol=tol)
    return root_finder


class Events(eqx.Module):
    """The events of [`simulate`][jaxlag.simulate] (``events=jl.Events(...)``): user conditions and
    how the segmented integration that handles them (and unilateral constraints) runs.

    Construct it with the conditions as positional arguments::

        jl.Events(jl.Event(hits_floor), jl.Event(too_fast, terminal=False), max_segments=16)
        jl.Events(*conditions)  # from a list
        jl.Events(max_segments=32)  # no user condition: a system with unilateral constraints

    - ``conditions``: [`Event`][jaxlag.Event] s (terminal or only recorded), stored as a tuple.
    - ``max_segments``: the integration runs in at most this many segments (default 8). A
      segment ends at each release, contact or event (terminal or not), at each crossing in
      the direction a condition ignores (``direction=True``/``False``; not recorded) and at
      the end time, so a run with ``k`` of these needs ``k + 1`` segments. The segments
      are a ``lax.scan`` of this static length: it is compiled in, the compile time does not
      grow with it, and segments left over after the end are empty solves that cost next to
      nothing at run time, so a generous value is cheap. Each friction switch
      ([`Coulomb`][jaxlag.Coulomb]: ``"stick"``, ``"slip"``) ends a segment too. Needing more is a failure
      (``SimulationError``), never a silent truncation; the message says how far the run got
      with the segments it had and the value to pass.
    - ``root_finder``: the ``optimistix`` root finder that locates each event on the solver's
      dense output (default ``optimistix.Newton(rtol=1e-13, atol=1e-13)``; in lower precision
      than float64 the default's tolerances are ``√ε``, 3.5e-4 in float32, as 1e-13 is below
      round-off there: the default, or a ``Newton`` equal to it, is adapted to the dtype, and
      also stops once its step is below the resolution of ``t``, where ``|c| < atol`` may be
      out of reach: late in a long run). Any other root finder is used as given.
    - ``zeno_time``: when an impact on a unilateral constraint with restitution (see
      [`Unilateral`][jaxlag.Unilateral]) ends an accumulation of impacts (a ball bouncing to
      rest: infinitely many impacts in finite time, which no number of segments can run):
      that impact is plastic and the contact persists. The rebound is predicted at each impact
      from the approach rate ``ḟ⁻`` and the normal acceleration ``f̈ < 0`` pressing the body
      onto the constraint (exact under gravity): it would rise by ``(e ḟ⁻)² / (2|f̈|)`` and
      fly for ``τ = 2 e |ḟ⁻| / |f̈|``; bodies not pressed on (``f̈ ≥ 0``) never count.

      Default ``None``: the impact is plastic when the rise is within the constraint tolerance
      (``jl.Checks(constraint_tolerance=...)``; 1e-8 in float64, 3.5e-4 in float32), i.e.
      when the rebound speed is below ``√(2 tol |f̈|)``. Such a body does not leave the band in
      which jaxlag takes a constraint as touching (and projects onto it), so what is cut off
      is below what the run resolves anyway; and the rule depends on the impact alone, not on
      the time span or the save times (the same ball saved to 3 s or to 1000 s bounces the
      same way). A ball dropped from ``h`` with restitution ``e`` comes to rest at its
      ``⌈ln(tol/h) / (2 ln e)⌉``-th impact (88 for ``e = 0.9``, ``h = 1`` m; 42 for
      ``e = 0.8``), at ``√(2h/g) (1 + 2e/(1 − e))``, where the bounces accumulate (8.6 s for
      ``e = 0.9``); each impact ends a segment: count them in ``max_segments``.

      A number: a flight time in the units of ``t``; the impact is plastic when
      ``τ < zeno_time`` (fewer segments, a coarser end of the bouncing: the ball above rests
      after ``⌈ln(zeno_time / (2√(2h/g))) / ln e⌉`` impacts).

    The segmented mode runs when the system has ``unilateral`` constraints or ``conditions`` is
    non-empty; it needs save times ``ts``. ``simulate(..., events=...)`` also takes a single
    [`Event`][jaxlag.Event] or a sequence of them, as ``Events(*conditions)``.
    """

    conditions: tuple[Event, ...]
    max_segments: int = eqx.field(static=True)
    root_finder: optx.AbstractRootFinder
    zeno_time: float | None = eqx.field(static=True)

    def __init__(
        self,
        *conditions: Validated[Event],
        max_segments: Validated[int] = 8,
        root_finder: Validated[optx.AbstractRootFinder] = _DEFAULT_ROOT_FINDER,
        zeno_time: Validated[float | None] = None,
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
    """``simulate``'s ``events=``: a `Events`, or one `Event` or a sequence of them
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


@compilation.filter_jit  # one program per shapes (eagerly, each operation would be one)
def _impact_times(time, kind, row, size, index):
    """`EventLog.impact_times`: ``size`` is a static Python int; ``index`` a Python int (static)
    or an array (an input of the program, e.g. traced)."""
    hit = (kind == EventKind.IMPACT) | (kind == EventKind.CONTACT)
    if index is not None:
        hit = hit & (row == index)
    # The entries are in time order: a stable sort on "not a hit" moves the hits to the front in
    # their order, the rest (set to inf) behind them.
    order = jnp.argsort(~hit, axis=-1, stable=True)
    times = jnp.take_along_axis(jnp.where(hit, time, jnp.inf), order, axis=-1)
    length = times.shape[-1]
    if size > length:
        padding = jnp.full((*times.shape[:-1], size - length), jnp.inf, times.dtype)
        return jnp.concatenate([times, padding], axis=-1)
    return times[..., :size]


class EventLog(eqx.Module):
    """What happened at the end of each segment: arrays of ``max_segments`` entries (with the
    batch axes first for a log from ``jax.vmap``), in the order the segments ran.

    - ``kind[k]``: a [`EventKind`][jaxlag.EventKind] value, compared by name
      (``log.kind == jl.EventKind.CONTACT``): ``END`` (0) the end time was reached, ``RELEASE``
      (1) a unilateral constraint was released, ``CONTACT`` (2) one was hit and engaged
      (a plastic impact: the contact persists), ``IMPACT`` (6) one was hit and the body
      rebounded (restitution ``e > 0``), ``USER`` (3) a user event fired, ``STICK`` (4) a
      Coulomb contact started to stick, ``SLIP`` (5) one started to slip (from sticking, or
      reversing at ``v_t = 0``), ``NONE`` (−1) padding (the run had already ended, at the end
      time, a terminal event or a failure). `kinds` gives the names of the real entries.
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
    - ``count``: the number of switches and events (kinds 1–6).
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

    def impact_times(self, size: int | None = None, index: int | None = None) -> Float[Array, "*batch size"]:
        """The times at which a unilateral constraint was hit (``IMPACT`` and ``CONTACT``
        entries: the rebounds and the plastic impacts), in order, as a fixed-size array padded
        with ``inf``: ``size`` entries (default: the length of the log, ``max_segments``);
        with ``index``, only the impacts on that holonomic row.

        The shape is static and the entries are the log's event times, so it works inside
        ``jit``, ``vmap`` and ``grad``: the second bounce of a ball and its derivative with
        respect to a parameter ``p`` are::

            def second_bounce(p):
                traj = jl.simulate(make_system(p), q0, qd0, ts, events=jl.Events(max_segments=16))
                return traj.events.impact_times(2)[1]

            jax.grad(second_bounce)(p)

        (``inf``, with a zero derivative, if the run had fewer impacts than asked for.) A batched
        log (from ``jax.vmap``) gives one row per member."""
        size = self.time.shape[-1] if size is None else int(size)
        if size < 0:
            raise ValueError(f"impact_times: size must be a non-negative int; got {size}.")
        return _impact_times(self.time, self.kind, self.index, size, index)

    def kinds(self) -> list[str] | list[list[str]]:
        """The names of the real entries (``"release"``, ``"contact"``, ``"impact"``,
        ``"user"``, ``"stick"``, ``"slip"``, ``"end"``),
        without the padding: ``["user", "user", "end"]``. A terminal event is the last entry;
        a completed run ends with ``"end"``. For a batched log, one list per member, nested
        like the batch axes (a list of lists after one ``vmap``). Host-side: call it outside
        ``jit``."""
        kind = jax.device_get(self.kind)

        def names(row):
            return [EventKind(int(k)).label for k in row if int(k) != EventKind.NONE]

        def nested(x) -> list:
            return names(x) if x.ndim == 1 else [nested(member) for member in x]

        return nested(np.asarray(kind))  # deeper lists for more than one batch axis
