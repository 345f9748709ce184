r"""Run-time failures of a simulation: detected where they happen, reported with the numbers.

Three things can stop an integration after the initial state has passed its checks
(:mod:`jaxlag._checks`):

* **non-finite equations of motion** (code 1): a step produces NaN/inf (``q**1.5`` of a negative
  coordinate, a mass matrix that becomes exactly singular, a NaN that a force function returns)
  and no smaller step helps;
* **the step size collapses** (code 5): steps are rejected down to round-off of ``t`` although
  every trial state is finite, the signature of a finite-time singularity (``M`` becoming
  singular, a velocity blowing up);
* **``max_steps``** (code 2) and **``max_segments``** (code 4) are reached, or diffrax reports
  another failure (code 3).

Detection costs a few scalar operations per step: the user's step-size controller is wrapped in
:class:`FiniteStepGuard`, which ends the solve (diffrax result ``dt_min_reached``) as soon as a
step is non-finite and cannot be shrunk further (at once for a constant step size), and which
carries the time reached, the last step size and the last accepted state in its state. Without
it an adaptive controller rejects NaN steps by shrinking ``dt`` until ``t + dt == t`` and then
spins until ``max_steps`` (65,536 wasted steps and the wrong message).

Every simulation returns a :class:`Failure` record in ``Trajectory.failure``; ``simulate`` then
raises :class:`SimulationError` (``throw=True``, the default):

* called eagerly (concrete inputs), after the compiled call, synchronously on every backend, with
  the numbers and a diagnosis of the failing state (which quantity is non-finite: ``L``, ``M``,
  ``F``, constraints or accelerations; the eigenvalues of ``M``; the steps that would be needed);
* inside a transformation (``jit``, ``vmap``, ``grad``), from the compiled program by
  ``eqx.branched_error_if`` with the static message of the cause (:data:`RESULT_MESSAGES`); the
  numbers stay in the returned record. With ``throw=False`` nothing is raised and
  ``traj.raise_if_failed()`` raises the full message, with the numbers, later and eagerly.
"""

from __future__ import annotations

from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _compile as compilation
from ._solver.guard import GuardState
from ._mechanics import constraints as _constraints
from ._mechanics.kkt import accelerations_and_multipliers
from ._mechanics.lagrangian import mass_matrix, unconstrained_accelerations
from ._tolerances import MASS_RCOND, rcond

#: The results enumeration of a simulation: ``Failure.code`` takes one of these values.
NONE, NONFINITE, MAX_STEPS, SOLVER, MAX_SEGMENTS, COLLAPSED = 0, 1, 2, 3, 4, 5

#: Inside a compiled program the message is static (it names the cause); the numbers stay in the
#: returned object.
COMPILED_HINT = (
    " (Raised inside a compiled program: the numbers are in the returned object. Pass "
    "throw=False and read traj.failure, or call traj.raise_if_failed() outside jit/vmap/grad, "
    "for the full diagnosis.)"
)

#: The static message of each result, indexed by its code.
RESULT_MESSAGES: tuple[str, ...] = (
    "",
    "jaxlag: the simulation stopped: the equations of motion became non-finite (NaN or inf) and "
    "a smaller step did not help." + COMPILED_HINT,
    "jaxlag: the simulation stopped: max_steps was reached before the end time." + COMPILED_HINT,
    "jaxlag: the simulation stopped: the diffrax solver reported a failure." + COMPILED_HINT,
    "jaxlag: the simulation stopped: it needed more segments (events, releases, contacts) than "
    "events=jl.Events(..., max_segments=...) allows." + COMPILED_HINT,
    "jaxlag: the simulation stopped: the step size collapsed to round-off although every trial "
    "state was finite, the signature of a finite-time singularity (a mass matrix becoming "
    "singular, a velocity blowing up)." + COMPILED_HINT,
)


class SimulationError(RuntimeError):
    """A simulation could not be completed; the message says where, why and what to change."""


# ----------------------------------------------------------------------------- the record
class Failure(eqx.Module):
    """How a simulation ended. ``code``: 0 completed, 1 non-finite equations of motion,
    2 ``max_steps`` reached, 3 other solver failure (``result``), 4 ``max_segments`` reached,
    5 step size collapsed. ``t``: time reached; ``dt``: last step size tried; ``q``, ``qd``:
    last accepted state; ``t0``, ``t1``: the interval; ``num_steps``: steps taken."""

    code: Any
    t: Any
    dt: Any
    q: Any
    qd: Any
    t0: Any
    t1: Any
    num_steps: Any
    result: Any
    max_steps: Any = eqx.field(static=True, default=None)
    max_segments: Any = eqx.field(static=True, default=None)


def from_solution(
    solution, t0, t1, q0, qd0, saved_t=None, saved_q=None, saved_qd=None, max_steps=None, max_segments=None
) -> Failure:
    """The :class:`Failure` of one ``diffeqsolve`` (run with ``throw=False`` and the guard's
    state saved; a ``StepTo`` controller has none and is judged by its saved states)."""
    state = solution.controller_state
    result = solution.result
    ok = diffrax.is_successful(result) | diffrax.is_event(result)
    dtype = q0.dtype
    if isinstance(state, GuardState):
        t, dt, q, qd = state.t, state.dt, state.q, state.qd
        guarded, nonfinite = state.failed, state.nonfinite
    else:
        t, dt, q, qd = jnp.asarray(t1, dtype), jnp.asarray(jnp.nan, dtype), q0, qd0
        guarded = nonfinite = jnp.asarray(False)
    max_reached = result == diffrax.RESULTS.max_steps_reached
    code = jnp.where(
        ok,
        NONE,
        jnp.where(
            guarded, jnp.where(nonfinite, NONFINITE, COLLAPSED), jnp.where(max_reached, MAX_STEPS, SOLVER)
        ),
    )
    if saved_q is not None:
        if saved_t is None or saved_qd is None:
            raise ValueError("from_solution: saved_q needs saved_t and saved_qd as well.")
        # Non-finite saved states of a solve that reports success (StepTo, a projection that
        # failed at a save time). Saves that were not reached (terminal event) hold inf in t.
        reached = jnp.isfinite(saved_t)
        bad = reached & ~(jnp.all(jnp.isfinite(saved_q), axis=-1) & jnp.all(jnp.isfinite(saved_qd), axis=-1))
        first = jnp.argmax(bad)
        late = (code == NONE) & jnp.any(bad)
        code = jnp.where(late, NONFINITE, code)
        before = jnp.maximum(first - 1, 0)
        t = jnp.where(late, saved_t[before], t)
        q = jnp.where(late, jnp.where(first > 0, saved_q[before], q0), q)
        qd = jnp.where(late, jnp.where(first > 0, saved_qd[before], qd0), qd)
    return Failure(
        code=jnp.asarray(code, jnp.int32),
        t=jnp.asarray(t, dtype),
        dt=jnp.asarray(dt, dtype),
        q=q,
        qd=qd,
        t0=jnp.asarray(t0, dtype),
        t1=jnp.asarray(t1, dtype),
        num_steps=jnp.asarray(solution.stats["num_steps"], jnp.int32),
        result=jnp.asarray(result._value, jnp.int32),
        max_steps=max_steps,
        max_segments=max_segments,
    )


def first_failure(earlier: Failure, later: Failure) -> Failure:
    """``earlier`` if it failed, else ``later`` (for simulations made of several solves)."""
    failed = earlier.code != NONE
    pick = lambda a, b: jnp.where(failed, a, b)  # noqa: E731
    merged = jax.tree.map(pick, earlier, later)
    return eqx.tree_at(lambda f: f.num_steps, merged, earlier.num_steps + later.num_steps)


# ----------------------------------------------------------------------------- diagnosis
@compilation.filter_jit
def _probe(system, q, qd, t, dt, args):
    """Which quantity is non-finite at ``(q, q̇, t)`` and one Euler step of size ``dt`` later."""

    def at(q, qd, t):
        finite = lambda x: jnp.all(jnp.isfinite(x))  # noqa: E731
        L = system.lagrangian(q, qd, t=t, args=args)
        M = mass_matrix(system, q, qd, t, args)
        if system.is_constrained:
            f, f_dot, g = _constraints.constraint_residuals(system, q, qd, t, args)
            constraints_ok = finite(f) & finite(f_dot) & finite(g)
            qdd = accelerations_and_multipliers(system, q, qd, t, args)[0]
        else:
            constraints_ok = jnp.asarray(True)
            qdd = unconstrained_accelerations(system, q, qd, t, args)
        eig = jnp.linalg.eigvalsh(jnp.where(jnp.isfinite(M), M, 0.0))
        flags = dict(
            state=finite(q) & finite(qd),
            lagrangian=finite(L),
            mass_matrix=finite(M),
            constraints=constraints_ok,
            accelerations=finite(qdd),
        )
        return flags, eig, qdd

    flags, eig, qdd = at(q, qd, t)
    step = jnp.where(jnp.isfinite(dt) & (dt > 0), dt, 0.0)
    q1 = q + step * qd
    qd1 = qd + step * jnp.where(jnp.isfinite(qdd), qdd, 0.0)
    flags1, eig1, _ = at(q1, qd1, t + step)
    return (flags, eig, qdd), (flags1, eig1, q1, qd1)


_CAUSES = {
    "state": "the state itself",
    "lagrangian": "the Lagrangian L",
    "mass_matrix": "the mass matrix M = ∂²L/∂q̇²",
    "constraints": "the constraint functions (f, ḟ or g)",
    "accelerations": "the accelerations q̈ (L, M and the constraints are finite: the solve "
    "M q̈ = F + Jᵀλ failed, or a force or dissipation function returned NaN)",
}


def _fmt(x) -> str:
    return np.array2string(np.asarray(x), precision=6, separator=", ", max_line_width=200)


def _singular(eig) -> bool:
    """The initial-state check's criterion (``checks.MASS_RCOND``, scaled to the dtype)."""
    eig = np.asarray(eig)
    threshold = rcond(MASS_RCOND, eig.dtype) if eig.size else 0.0
    return bool(eig.size) and not eig[0] > threshold * max(np.max(np.abs(eig)), 1e-300)


def _x64_hint(dtype) -> str:
    if np.dtype(dtype) == np.float64:
        return ""
    return (
        f" (The simulation runs in {np.dtype(dtype).name}: jax_enable_x64 is off. Mechanics "
        "in single precision keeps ~7 digits; enable float64 with "
        "jax.config.update('jax_enable_x64', True) before creating arrays.)"
    )


def describe(failure: Failure, system=None, args=None) -> str:
    """The message for one (unbatched, concrete) failure record."""
    code = int(failure.code)
    t, dt = float(failure.t), float(failure.dt)
    t0, t1 = float(failure.t0), float(failure.t1)
    q, qd = np.asarray(failure.q), np.asarray(failure.qd)
    hint = _x64_hint(q.dtype)
    where = f"at t = {t:.10g} (interval [{t0:g}, {t1:g}])"
    if code == MAX_STEPS:
        done = (t - t0) / (t1 - t0) if t1 != t0 else 0.0
        steps = int(failure.num_steps)
        msg = (
            f"The simulation reached max_steps = {failure.max_steps or steps} steps {where}, "
            f"{100 * done:.1f}% of the way"
        )
        if done > 1e-3:
            needed = int(np.ceil(steps / done))
            suggestion = int(2 ** np.ceil(np.log2(needed * 1.2)))
            msg += (
                f": at this rate about {needed:,} steps are needed. Pass max_steps="
                f"{suggestion} (or more), or loosen the step-size controller's rtol/atol "
                "(default 1e-10), or use a constant step size."
            )
        else:
            msg += (
                f"; the last step size was {dt:.3g}. The steps are far too small for the "
                "interval: the system may be stiff or singular near this state "
                f"(q = {_fmt(q)}, q̇ = {_fmt(qd)})."
            )
        return msg + hint
    if code == MAX_SEGMENTS:
        return (
            f"The simulation needed more than max_segments = {failure.max_segments} "
            "segments (releases, contacts and events) before the end time; it reached "
            f"t = {t:.10g} of [{t0:g}, {t1:g}]. Increase it: events=jl.Events(..., max_segments=...)."
        )
    if code == SOLVER:
        text = _result_text(int(failure.result))
        return f"The diffrax solver failed {where}: {text}" + hint
    state = f"q = {_fmt(q)}, q̇ = {_fmt(qd)}"
    if code == NONFINITE:
        msg = f"The equations of motion became non-finite (NaN or inf) {where}, from {state}"
        msg += f"; no step, down to dt = {dt:.3g}, gave a finite state." if np.isfinite(dt) else "."
    else:  # COLLAPSED
        msg = (
            f"The step size collapsed to dt = {dt:.3g} {where}: every step from {state} "
            "was rejected although finite. The solution appears to reach a singularity "
            "here (a velocity or acceleration blowing up, a mass matrix becoming singular)."
        )
    if system is not None:
        msg += " " + _diagnosis(system, failure, args)
    return msg + hint


def _result_text(value: int) -> str:
    messages = getattr(diffrax.RESULTS, "_index_to_message", None)
    if messages is not None and 0 <= value < len(messages):
        return messages[value]
    return f"diffrax result {value}"


def _diagnosis(system, failure: Failure, args) -> str:
    try:
        (flags, eig, qdd), (flags1, eig1, q1, qd1) = jax.device_get(
            _probe(system, failure.q, failure.qd, failure.t, failure.dt, args)
        )
    except Exception as error:  # noqa: BLE001 - the diagnosis must not hide the failure
        return f"(Evaluating the equations of motion there raised {type(error).__name__}: {error}.)"
    # The first non-finite quantity in the order of the computation (state, L, M, f, q̈).
    for name in _CAUSES:
        if not flags[name]:
            text = f"There, {_CAUSES[name]} is non-finite."
            if name in ("mass_matrix", "accelerations") and _singular(eig):
                text += f" M is singular there (eigenvalues {_fmt(eig)})."
            return text
    if _singular(eig):
        return (
            f"There M = ∂²L/∂q̇² is singular (eigenvalues {_fmt(eig)}): a coordinate "
            "singularity or a degenerate Lagrangian."
        )
    text = f"There everything is finite (|q̈| = {np.max(np.abs(qdd)):.3g}, M eigenvalues {_fmt(eig)})"
    for name in _CAUSES:
        if not flags1[name]:
            return (
                text + f"; one step dt further, at q = {_fmt(q1)}, {_CAUSES[name]} is "
                "non-finite: the motion leaves the region where the equations are defined "
                "(e.g. a fractional power or log of a negative number, a square root of a "
                "negative argument, a division by zero)."
            )
    if _singular(eig1):
        return text + f"; one step dt further M is singular (eigenvalues {_fmt(eig1)})."
    return text + "."


# ----------------------------------------------------------------------------- raising
def member(tree, index):
    """Member ``index`` of a batched host pytree. Leaves carry the batch axes first, of full size
    or of size 1 (shared by every member)."""

    def take(x):
        x = np.asarray(x)
        return x[tuple(i if x.shape[k] > 1 else 0 for k, i in enumerate(index))]

    return jax.tree.map(take, tree)


def failed_members(flags):
    """Indices (tuples) of the batch members whose flag is set (``[()]`` unbatched)."""
    flags = np.asarray(flags)
    if flags.ndim == 0:
        return [()] if bool(flags) else []
    return [tuple(int(i) for i in index) for index in zip(*np.nonzero(flags))]


def batch_prefix(index, flags, members) -> str:
    """``"3 of 64 batch members failed (first: member [5])."`` or ``""`` when unbatched."""
    if not index:
        return ""
    where = ", ".join(str(i) for i in index)
    return (
        f"{len(members)} of {np.asarray(flags).size} batch members failed (first: member "
        f"[{where}]). Member [{where}]: "
    )


def message(failure: Failure, system=None, args=None, *, args_batched=False) -> str | None:
    """The full message for a (possibly batched) host failure record, or None.

    ``args`` of a batched record are used for the diagnosis only when ``args_batched`` says
    that they carry the same batch axes."""
    flags = np.asarray(failure.code) != NONE
    members = failed_members(flags)
    if not members:
        return None
    index = members[0]
    if index and not args_batched:
        system = None  # which args belong to the member is unknown: no diagnosis
    member_args = member(args, index) if (index and args is not None) else args
    text = describe(member(failure, index), system, member_args)
    if index:
        text = (
            batch_prefix(index, flags, members) + text + " Pass throw=False to keep the "
            "other members' results (traj.failure.code says which failed)."
        )
    return text


def raise_if_failed(failure: Failure, system=None, args=None, *, args_batched=False) -> None:
    """Raise :class:`SimulationError` eagerly if the (concrete) record says the run failed."""
    host = jax.device_get(failure)  # one transfer; blocks until the simulation is done
    text = message(host, system, args, args_batched=args_batched)
    if text is not None:
        raise SimulationError(text)


def error_if_failed(failure: Failure, x):
    """Compiled counterpart of :func:`raise_if_failed`: ``x``, or an ``eqx.branched_error_if``
    with the static message of the failure's code (the record itself stays in the trajectory).
    ``x`` should be an output the caller uses, so that the check is not removed as dead code."""
    return eqx.branched_error_if(x, failure.code != NONE, failure.code, RESULT_MESSAGES)
