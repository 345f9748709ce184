r"""Saving at given times from inside the solver's state: ``diffrax.SaveAt(ts=ts)`` without its
run-time checks.

``diffrax.diffeqsolve`` checks ``SaveAt(ts=ts)`` inside the compiled program (``ts`` increasing,
within ``[t0, t1]``) with ``equinox``'s run-time errors, which are host callbacks even when the
check passes (and whatever ``throw`` is), and JAX's persistent compilation cache keeps no program
that holds a host callback. jaxlag checks its save times itself (on the host when they are
concrete, once in the program when they are traced), so it saves them this way instead:

`SaveTimes` wraps the solver. Its state carries the wrapped solver's state, the index of the
next save time and a ``(T, ...)`` buffer of saved values. After each step from ``tₙ`` to
``tₙ₊₁`` it evaluates the step's dense output (the solver's own interpolation, as diffrax's
saving does) at every save time ``tₙ ≤ t_s ≤ tₙ₊₁`` not saved yet, and stores
``fn(t_s, y(t_s), args)``. diffrax keeps the solver state of accepted steps only, so a rejected
step's saves are discarded with it; return the buffer with ``SaveAt(t1=True,
solver_state=True)`` and read it with `saved_values`. The values are bit-for-bit those of
``SaveAt(ts=ts)`` (same interpolant, same arithmetic), and the steps are the same (the save
times do not clip steps). Unreached save times hold ``inf``, as in diffrax.

The save loop inside a step is an ``equinox.internal.while_loop`` of at most ``T`` iterations,
of the kind diffrax uses for its own saves under the same adjoint (checkpointed under reverse
mode, a plain ``lax.while_loop`` otherwise).
"""

from collections.abc import Callable
from typing import Literal

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int, PyTree

from .forwarding import ForwardingSolver
from .unit_time import Clock, real_time_solution


class SavedTimesState(eqx.Module):
    """The state of `SaveTimes`: the wrapped solver's, the next save index, the buffer."""

    inner: PyTree
    index: Int[Array, ""]
    values: PyTree[Array]


_LoopKind = Literal["lax", "checkpointed", "bounded"]


def _loop_kind(adjoint: diffrax.AbstractAdjoint) -> _LoopKind:
    """The kind of ``eqxi.while_loop`` that diffrax uses for its own save loop under ``adjoint``."""
    if isinstance(adjoint, diffrax.RecursiveCheckpointAdjoint):
        return "checkpointed"
    if isinstance(adjoint, diffrax.DirectAdjoint):
        return "bounded"
    return "lax"


def _save_y(t, y, args):
    del t, args
    return y


class SaveTimes(ForwardingSolver, diffrax.AbstractWrappedSolver):
    """``solver``, also saving ``fn(t, y(t), args)`` at the increasing times ``ts`` (see module)."""

    solver: diffrax.AbstractSolver  # pyright: ignore[reportIncompatibleVariableOverride]
    ts: Float[Array, " T"]
    fn: Callable = eqx.field(static=True, default=_save_y)
    loop_kind: _LoopKind = eqx.field(static=True, default="lax")

    @classmethod
    def for_adjoint(cls, solver, ts, adjoint, fn: Callable = _save_y) -> "SaveTimes":
        """`SaveTimes` whose save loop is the kind diffrax would use under ``adjoint``."""
        return cls(solver, ts, fn, _loop_kind(adjoint))

    def init(self, terms, t0, t1, y0, args):
        inner = self.solver.init(terms, t0, t1, y0, args)
        shapes = jax.eval_shape(lambda t, y: self.fn(t, y, args), t0, y0)  # args may hold functions
        count = self.ts.shape[0]
        values = jax.tree.map(lambda s: jnp.full((count, *s.shape), jnp.inf, s.dtype), shapes)
        return SavedTimesState(inner, jnp.zeros((), jnp.int32), values)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        y1, y_error, dense_info, inner, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state.inner, made_jump
        )
        interpolation = self.solver.interpolation_cls(t0=t0, t1=t1, **dense_info)
        ts, count = self.ts, self.ts.shape[0]

        def pending(carry):
            index, _ = carry
            return (index < count) & (ts[jnp.minimum(index, count - 1)] <= t1)

        def save(carry):
            index, values = carry
            t = ts[index]
            value = self.fn(t, interpolation.evaluate(t), args)
            values = jax.tree.map(lambda x, buffer: buffer.at[index].set(x), value, values)
            return index + 1, values

        index, values = eqxi.while_loop(
            pending,
            save,
            (solver_state.index, solver_state.values),
            max_steps=count,
            buffers=lambda carry: carry[1],
            kind=self.loop_kind,
            checkpoints=count if self.loop_kind == "checkpointed" else None,
        )
        return y1, y_error, dense_info, SavedTimesState(inner, index, values), result


def saved_values(
    solution: diffrax.Solution, ts: Float[Array, " T"], t0, t1, y0, args, fn: Callable = _save_y
) -> PyTree[Array]:
    """The values `SaveTimes` saved in ``solution`` (solved with ``SaveAt(t1=True,
    solver_state=True)``), as diffrax's ``SaveAt(ts=ts)`` would return them: those after the
    solve's end (an event) are ``inf``; a solve with ``t0 == t1`` saves ``fn(t0, y0, args)`` at
    every time."""
    state = solution.solver_state
    if not isinstance(state, SavedTimesState) or solution.ts is None:
        raise RuntimeError("jaxlag: the solve did not return the SaveTimes state.")
    t_end = solution.ts[-1]
    after = ts > t_end

    def finish(values, start):
        mask = after.reshape(after.shape + (1,) * (values.ndim - 1))
        values = jnp.where(mask, jnp.inf, values)
        return jnp.where(t0 == t1, jnp.broadcast_to(start, values.shape), values)

    return jax.tree.map(finish, state.values, fn(t0, y0, args))


def save_checked_state(t, y, args):
    """The state as it is: the save function of a ``SubSaveAt(ts=ts, fn=save_checked_state)``
    whose ``ts`` jaxlag has checked itself (increasing, ``t0 = ts[0]``, ``t1 = ts[-1]``), which
    `checked_save_times` recognises and `solve_saving_times` saves without diffrax's checks."""
    del t, args
    return y


def checked_save_times(saveat: diffrax.SaveAt) -> Float[Array, " T"] | None:
    """The times of ``saveat`` when it is ``SaveAt(subs=SubSaveAt(ts=ts, fn=save_checked_state))``
    (the controller state may be asked for too), else None."""
    sub = saveat.subs
    if not isinstance(sub, diffrax.SubSaveAt) or sub.ts is None or sub.t0 or sub.t1 or sub.steps:
        return None
    if sub.fn is not save_checked_state or saveat.dense or saveat.solver_state or saveat.made_jump:
        return None
    return sub.ts


def solve_saving_times(
    ts: Float[Array, " T"], *, solver, saveat: diffrax.SaveAt, adjoint, clock: Clock | None = None, **kwargs
):
    """``diffrax.diffeqsolve(solver=solver, saveat=saveat, adjoint=adjoint, **kwargs)`` for a
    ``saveat`` that saves the state at increasing times ``ts`` from ``t0 = ts[0]`` to
    ``t1 = ts[-1]``, through `SaveTimes`: the returned ``Solution``'s ``ts`` and ``ys`` are those
    ``SaveAt(ts=ts)`` gives (its other fields as asked by ``saveat``, and the solver state).
    With a ``clock`` the solve is on the unit interval (`jaxlag._solver.unit_time`: ``kwargs``'s
    times are 0 and 1, ``solver`` a `UnitTimeSolver`), the returned times are the run's."""
    unit_ts = ts if clock is None else clock.unit(ts)
    wrapped = SaveTimes.for_adjoint(solver, unit_ts, adjoint)
    within = diffrax.SaveAt(t1=True, solver_state=True, controller_state=saveat.controller_state)
    solution = diffrax.diffeqsolve(solver=wrapped, saveat=within, adjoint=adjoint, **kwargs)
    t0, t1, y0, args = kwargs["t0"], kwargs["t1"], kwargs["y0"], kwargs.get("args")
    if clock is not None:
        t0, t1 = clock.t0, clock.t1  # for a run of length 0 (the save loop works in s)
    values = saved_values(solution, unit_ts, t0, t1, y0, args)
    if solution.ts is None:
        raise RuntimeError("jaxlag: the solve did not return its final time.")
    reached = (unit_ts <= solution.ts[-1]) | (t0 == t1)
    if clock is not None:
        solution = real_time_solution(solution, clock)
    return eqx.tree_at(lambda s: (s.ts, s.ys), solution, (jnp.where(reached, ts, jnp.inf), values))
