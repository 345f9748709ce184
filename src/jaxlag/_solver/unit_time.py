r"""Solving on the unit interval: diffrax sees ``s ∈ [0, 1]``, the solver steps real time.

``diffrax.diffeqsolve`` computes, in every solve program, the time ``t1 − 100 ulps`` above which
a step is clipped to ``t1``, as 100 chained ``equinox.internal.prevbefore`` calls on ``t1``. When
``t1`` is an input of the program (jaxlag's programs take the times as inputs, so that a new
horizon compiles nothing) that chain is about 600 of the program's operations and a quarter
second of XLA compile time per solve program, more than the equations of motion. With ``t1`` a
constant, XLA folds it away.

So the solve is posed on the unit interval: diffrax integrates from ``s = 0`` to ``s = 1`` (two
constants) and `UnitTimeSolver` steps the wrapped solver from ``t(s₀)`` to ``t(s₁)``, with

    t(s) = t0 + s (t1 − t0)        (t(0) = t0 and t(1) = t1 exactly),

the same real-time step as before. An explicit Runge–Kutta step and its dense output depend on
the step only through its end points and the normalized position ``θ`` inside it (the stored
stages are increments ``h fᵢ``), so the states, the interpolated saves and the error estimates are
those of the real-time solve; the step-size controller works in ``s``, with its absolute
durations (``dt0``, ``dtmin``, ``dtmax``) divided by ``t1 − t0`` and the vector field it sees at
the start (``func``, for the first step size) multiplied by it, ``dy/ds = (t1 − t0) f(t(s), y)``.
diffrax's clipping threshold becomes ``1 − 100 ulps``, i.e. ``t1 − 100 ulps(1)·(t1 − t0)``:
relative to the length of the run rather than to ``|t1|``.

Only solves whose every time-valued option is known take this form (`unit_time_applies`):
Runge–Kutta solvers, jaxlag's guard around a ``PIDController`` (without breakpoints) or a
``ConstantStepSize``, or ``StepTo``; saving the state at times or at the end; no diffrax
``Event``; the forward, direct or recursive-checkpoint adjoints. Anything else is solved in real
time as given.
"""

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .forwarding import ForwardingSolver
from .guard import FiniteFixedStepGuard, FiniteStepGuard, GuardState


class Clock(eqx.Module):
    """The map ``t(s) = t0 + s (t1 − t0)`` between the unit interval and the run's times."""

    t0: Float[Array, ""]
    t1: Float[Array, ""]

    @property
    def span(self) -> Float[Array, ""]:
        return self.t1 - self.t0

    def time(self, s):
        """``t(s)``, with the ends exact (``t(1)`` is ``t1``, not ``t0 + (t1 − t0)``)."""
        s = jnp.asarray(s, self.t0.dtype)
        return jnp.where(s == 1, self.t1, self.t0 + s * self.span)

    def unit(self, t):
        """``s(t) = (t − t0) / (t1 − t0)``; 0 for a run of length 0."""
        span = self.span
        return jnp.where(span == 0, 0, (t - self.t0) / jnp.where(span == 0, 1, span))

    def unit_duration(self, dt):
        """A duration in units of the run's length (0 for a run of length 0)."""
        span = self.span
        return jnp.where(span == 0, 0, dt / jnp.where(span == 0, 1, span))


class UnitTimeSolver(ForwardingSolver, diffrax.AbstractWrappedSolver):
    """``solver`` stepping real time while diffrax integrates ``s ∈ [0, 1]`` (see module)."""

    solver: diffrax.AbstractSolver  # pyright: ignore[reportIncompatibleVariableOverride]
    clock: Clock

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, self.clock.time(t0), self.clock.time(t1), y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        time = self.clock.time
        return self.solver.step(terms, time(t0), time(t1), y0, args, solver_state, made_jump)

    def func(self, terms, t0, y0, args):
        return self.seen_from_outside(self.solver.func)(terms, t0, y0, args)

    def seen_from_outside(self, func: Callable) -> Callable:
        """``func(terms, t, y, args)`` of the wrapped solver as a field in ``s``:
        ``(t1 − t0) func(terms, t(s), y, args)``."""

        def in_unit_time(terms, s, y, args):
            field = func(terms, self.clock.time(s), y, args)
            return jax.tree.map(lambda f: f * self.clock.span.astype(f.dtype), field)

        return in_unit_time


def _base_solver(solver):
    """The user's solver inside jaxlag's wrappers."""
    while isinstance(getattr(solver, "solver", None), diffrax.AbstractSolver):
        solver = solver.solver
    return solver


def _default_save(saveat: diffrax.SaveAt, allowed: tuple) -> bool:
    """Every save of ``saveat`` is one of ``allowed`` (save functions whose times the caller maps
    itself) or saves the state at ``t0``, ``t1`` or the steps; none gives times of its own
    (diffrax would read them as values of ``s``) or asks for dense output or the solver state."""
    subs = jax.tree.leaves(saveat.subs, is_leaf=lambda x: isinstance(x, diffrax.SubSaveAt))
    default = diffrax.SubSaveAt(t1=True).fn

    def mapped(sub) -> bool:
        if not isinstance(sub, diffrax.SubSaveAt):
            return False
        return sub.fn in allowed or (sub.fn is default and sub.ts is None)

    return not (saveat.dense or saveat.solver_state) and all(mapped(sub) for sub in subs)


def unit_time_applies(solver, controller, saveat, adjoint, event, allowed_saves: tuple = ()) -> bool:
    """Whether a solve may be posed on the unit interval (see module)."""
    if event is not None or not _default_save(saveat, allowed_saves):
        return False
    known = (diffrax.RecursiveCheckpointAdjoint, diffrax.DirectAdjoint, diffrax.ForwardMode)
    if not isinstance(adjoint, known):
        return False
    if not isinstance(_base_solver(solver), diffrax.AbstractRungeKutta):
        return False
    if isinstance(controller, diffrax.StepTo):
        return True
    if isinstance(controller, (FiniteStepGuard, FiniteFixedStepGuard)):
        return type(controller.controller) in (diffrax.PIDController, diffrax.ConstantStepSize)
    return False


def _unit_pid(controller: diffrax.PIDController, clock: Clock) -> diffrax.PIDController:
    durations = {name: getattr(controller, name) for name in ("dtmin", "dtmax")}
    given = {name: clock.unit_duration(value) for name, value in durations.items() if value is not None}
    return eqx.tree_at(lambda c: [getattr(c, name) for name in given], controller, list(given.values()))


def unit_time_controller(controller, clock: Clock):
    """``controller`` (one for which `unit_time_applies`) working in ``s``: its durations
    divided by the run's length, the guard's round-off scale taken relative to it."""
    if isinstance(controller, diffrax.StepTo):
        return diffrax.StepTo(clock.unit(jnp.asarray(controller.ts, clock.t0.dtype)))
    inner = controller.controller
    if isinstance(inner, diffrax.PIDController):
        inner = _unit_pid(inner, clock)
    step = controller.initial_step
    step = None if step is None else clock.unit_duration(jnp.asarray(step, clock.t0.dtype))
    span = clock.span
    scale = jnp.maximum(jnp.maximum(jnp.abs(clock.t0), jnp.abs(clock.t1)), jnp.abs(span))
    scale = jnp.where(span == 0, 1, scale / jnp.where(span == 0, 1, span))
    return type(controller)(inner, step, scale)


def real_time_solution(solution: diffrax.Solution, clock: Clock) -> diffrax.Solution:
    """A solution of the unit-interval solve with its times in the run's (the saved times,
    the ends, the guard's record)."""
    state = solution.controller_state
    if isinstance(state, GuardState):
        t, dt = clock.time(state.t).astype(state.t.dtype), state.dt * clock.span.astype(state.dt.dtype)
        state = eqx.tree_at(lambda s: (s.t, s.dt), state, (t, dt))
    ts = solution.ts
    if ts is not None:
        ts = jnp.where(jnp.isfinite(ts), clock.time(ts), ts)
    return eqx.tree_at(
        lambda s: (s.t0, s.t1, s.ts, s.controller_state),
        solution,
        (clock.t0, clock.t1, ts, state),
        is_leaf=lambda x: x is None,
    )


def default_time_dtype(t0) -> bool:
    """Whether the run's times have JAX's default float dtype, that of `unit_interval`'s
    constants in diffrax (a float32 run under ``jax_enable_x64`` is solved in real time)."""
    return jnp.asarray(t0).dtype == jnp.dtype(jnp.result_type(float))


def unit_interval() -> tuple[float, float]:
    """``(0.0, 1.0)``: Python floats, which ``diffeqsolve`` (an ``equinox.filter_jit``) takes as
    static, so that its threshold is computed from a constant and folded away (NumPy or JAX
    scalars would be inputs of its inner program). diffrax's time dtype is then JAX's default
    float; `Clock` casts ``s`` to the run's time dtype."""
    return 0.0, 1.0
