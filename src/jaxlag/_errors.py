r"""Run-time failures of a simulation: the results enumeration, the record and the compiled check.

Three things can stop an integration after the initial state has passed its checks
(`jaxlag._checks`):

* **non-finite equations of motion** (`FailureCode.NONFINITE`): a step produces NaN/inf
  (``q**1.5`` of a negative coordinate, a mass matrix that becomes exactly singular, a NaN that
  a force function returns) and no smaller step helps;
* **the step size collapses** (`FailureCode.STEP_SIZE_COLLAPSED`): steps are rejected down
  to round-off of ``t`` although every trial state is finite, the signature of a finite-time
  singularity (``M`` becoming singular, a velocity blowing up);
* **``max_steps``** (`FailureCode.MAX_STEPS`) and **``max_segments``**
  (`FailureCode.MAX_SEGMENTS`) are reached, or diffrax reports another failure
  (`FailureCode.SOLVER`);
* **a parameter of the contact laws is out of its range** (`FailureCode.RESTITUTION`,
  `FailureCode.FRICTION_COEFFICIENT`): a traced restitution ``e ∉ [0, 1]`` or friction
  coefficient ``μ < 0`` (or NaN), which ``jl.Unilateral`` and ``jl.Coulomb`` could not check
  when they were built; the segment loop checks them before the first step;
* **a user's reset returned a non-finite state** (`FailureCode.RESET`).

Detection costs a few scalar operations per step: the user's step-size controller is wrapped in
`FiniteStepGuard`, which ends the solve (diffrax result
``dt_min_reached``) as soon as a step is non-finite and cannot be shrunk further (at once for a
constant step size), and which carries the time reached, the last step size and the last
accepted state in its state. Without it an adaptive controller rejects NaN steps by shrinking
``dt`` until ``t + dt == t`` and then spins until ``max_steps`` (65,536 wasted steps and the
wrong message).

Every simulation returns a `Failure` record in ``Trajectory.failure``; ``simulate`` then
raises `SimulationError` (``throw=True``, the default):

* called eagerly (concrete inputs), after the compiled call, synchronously on every backend, with
  the numbers and a diagnosis of the failing state (`jaxlag._diagnosis`: which quantity is
  non-finite, the eigenvalues of ``M``, the steps that would be needed);
* inside a transformation (``jit``, ``vmap``, ``grad``), from the compiled program by
  `error_if_failed` (``eqx.branched_error_if``) with the static
  `FailureCode.message` of the cause; the numbers stay in the returned record. With
  ``throw=False`` nothing is raised and ``traj.raise_if_failed()`` raises the full message, with
  the numbers, later and eagerly.
"""

import enum

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PyTree

from ._solver.guard import GuardState

#: Ends every compiled message: inside a compiled program the message is static (it names the
#: cause); the numbers stay in the returned object.
_COMPILED_HINT = (
    " (Raised inside a compiled program: the numbers are in the returned object. Pass "
    "throw=False and read traj.failure, or call traj.raise_if_failed() outside jit/vmap/grad, "
    "for the full diagnosis.)"
)


class FailureCode(enum.IntEnum):
    """How a simulation ended: the values of ``traj.failure.code``, each with its static message.

    ``traj.failure.code`` is an ``int32`` array (one entry per batch member); compare it with
    these members, e.g. ``traj.failure.code == jl.FailureCode.MAX_STEPS``, inside or outside
    ``jit``. That is why this is an ``int`` enumeration and not an ``eqx.Enumeration`` (as
    diffrax's ``RESULTS``): its members are plain integers that ``jnp.where`` and ``==`` take as
    they are. Each member's `message` is the static message raised from a compiled
    program (`error_if_failed`); the eager message, with the numbers, is
    built on the host (`jaxlag._diagnosis`).

    - ``COMPLETED`` (0): the run reached its end time (or a terminal event).
    - ``NONFINITE`` (1): the equations of motion became non-finite (NaN or inf) and a smaller
      step did not help.
    - ``MAX_STEPS`` (2): ``max_steps`` was reached before the end time.
    - ``SOLVER`` (3): the diffrax solver reported another failure (``traj.failure.result``).
    - ``MAX_SEGMENTS`` (4): more segments (events, releases, contacts) were needed than
      ``jl.Events(max_segments=...)`` allows.
    - ``STEP_SIZE_COLLAPSED`` (5): the step size fell to round-off of ``t`` although every trial
      state was finite (a finite-time singularity, stiffness below the dtype's time resolution,
      or a state stuck at a discontinuous force).
    - ``RESTITUTION`` (6): a coefficient of restitution of [`Unilateral`][jaxlag.Unilateral] is
      outside ``[0, 1]`` or not finite (one that came in traced, through ``jit``, ``vmap`` or
      ``grad``: a concrete one is refused when the ``Unilateral`` is built). The run stops at
      ``t0``; ``traj.failure.index`` is the position of the row in ``Unilateral.indices`` and
      ``traj.failure.value`` the coefficient.
    - ``FRICTION_COEFFICIENT`` (7): the friction coefficient ``mu`` of a [`Coulomb`][jaxlag.Coulomb]
      contact is negative or not finite (traced, as for ``RESTITUTION``); ``index`` is the
      position of the contact in ``System.friction``, ``value`` its ``mu``.
    - ``RESET`` (8): the ``reset`` of a user [`Event`][jaxlag.Event] returned a non-finite state;
      ``index`` is the event's position in ``Events.conditions``, and ``t``, ``q``, ``qd`` the
      state it was given.
    """

    #: The static message raised for this result inside a compiled program (empty for
    #: ``COMPLETED``).
    message: str

    def __new__(cls, value: int, message: str):
        member = int.__new__(cls, value)
        member._value_ = value
        member.message = message
        return member

    COMPLETED = 0, ""
    NONFINITE = (
        1,
        "jaxlag: the simulation stopped: the equations of motion became non-finite (NaN or inf) "
        "and a smaller step did not help." + _COMPILED_HINT,
    )
    MAX_STEPS = (
        2,
        "jaxlag: the simulation stopped: max_steps was reached before the end time (too few "
        "steps, or steps held small by stiffness or by a state stuck at a discontinuous force, "
        "which more steps do not cure)." + _COMPILED_HINT,
    )
    SOLVER = 3, "jaxlag: the simulation stopped: the diffrax solver reported a failure." + _COMPILED_HINT
    MAX_SEGMENTS = (
        4,
        "jaxlag: the simulation stopped: it needed more segments (events, releases, contacts) "
        "than events=jl.Events(..., max_segments=...) allows." + _COMPILED_HINT,
    )
    STEP_SIZE_COLLAPSED = (
        5,
        "jaxlag: the simulation stopped: the step size collapsed to round-off although every "
        "trial state was finite: a finite-time singularity (a mass matrix becoming singular, a "
        "velocity blowing up), stiffness that needs steps below the time resolution of the "
        "dtype, or a discontinuous force." + _COMPILED_HINT,
    )
    RESTITUTION = (
        6,
        "jaxlag: the simulation did not start: a coefficient of restitution "
        "(jl.Unilateral(..., restitution=e)) is outside [0, 1] or not finite. e must lie in "
        "[0, 1] (0 plastic, 1 elastic): e > 1 adds energy at every impact, e < 0 lets the body "
        "through the constraint. It came in traced (jit/vmap/grad), so jl.Unilateral could not "
        "check it when it was built." + _COMPILED_HINT,
    )
    FRICTION_COEFFICIENT = (
        7,
        "jaxlag: the simulation did not start: a friction coefficient "
        "(jl.Coulomb(..., mu)) is negative or not finite. mu must be finite and >= 0: with "
        "mu < 0 friction would drive the slip instead of opposing it. It came in traced "
        "(jit/vmap/grad), so jl.Coulomb could not check it when it was built." + _COMPILED_HINT,
    )
    RESET = (
        8,
        "jaxlag: the simulation stopped: the reset of a jl.Event (reset=...) returned a "
        "non-finite state (NaN or inf); traj.failure.index says which event." + _COMPILED_HINT,
    )


class SimulationError(RuntimeError):
    """A simulation could not be completed; the message says where, why and what to change."""


# ----------------------------------------------------------------------------- the record
class Failure(eqx.Module):
    """How a simulation ended. ``code``: a `FailureCode` value; ``t``: time reached;
    ``dt``: last step size tried; ``q``, ``qd``: last accepted state; ``t0``, ``t1``: the
    interval; ``num_steps``: steps taken; ``result``: diffrax's result (for
    `FailureCode.SOLVER`); ``max_steps``, ``max_segments``: the limits the run had (for the
    messages); ``index``, ``value``: what the failure concerns, where its code says (the event
    whose reset failed, the row whose restitution or the contact whose ``mu`` is out of range
    and that coefficient; for `FailureCode.MAX_SEGMENTS` of an accumulation of impacts,
    ``value`` is the number of segments the geometric series of the impacts needs in all),
    else −1 and NaN. Every array carries the batch axes first (``*batch``); after
    ``jax.device_get`` they are NumPy arrays."""

    code: Int[Array, "*batch"]
    t: Float[Array, "*batch"]
    dt: Float[Array, "*batch"]
    q: Float[Array, "*batch n"]
    qd: Float[Array, "*batch n"]
    t0: Float[Array, "*batch"]
    t1: Float[Array, "*batch"]
    num_steps: Int[Array, "*batch"]
    result: Int[Array, "*batch"]
    max_steps: int | None = eqx.field(static=True, default=None)
    max_segments: int | None = eqx.field(static=True, default=None)
    index: Int[Array, "*batch"] | None = None
    value: Float[Array, "*batch"] | None = None


def from_solution(
    solution: diffrax.Solution,
    t0: Float[ArrayLike, ""],
    t1: Float[ArrayLike, ""],
    q0: Float[Array, " n"],
    qd0: Float[Array, " n"],
    saved_t: Float[Array, " times"] | None = None,
    saved_q: Float[Array, "times n"] | None = None,
    saved_qd: Float[Array, "times n"] | None = None,
    max_steps: int | None = None,
    max_segments: int | None = None,
) -> Failure:
    """The `Failure` of one ``diffeqsolve`` (run with ``throw=False`` and the guard's
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
        FailureCode.COMPLETED,
        jnp.where(
            guarded,
            jnp.where(nonfinite, FailureCode.NONFINITE, FailureCode.STEP_SIZE_COLLAPSED),
            jnp.where(max_reached, FailureCode.MAX_STEPS, FailureCode.SOLVER),
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
        late = (code == FailureCode.COMPLETED) & jnp.any(bad)
        code = jnp.where(late, FailureCode.NONFINITE, code)
        before = jnp.maximum(first - 1, 0)
        t = jnp.where(late, saved_t[before], t)
        q = jnp.where(late, jnp.where(first > 0, saved_q[before], q0), q)
        qd = jnp.where(late, jnp.where(first > 0, saved_qd[before], qd0), qd)
    stats = solution.stats
    return Failure(
        code=jnp.asarray(code, jnp.int32),
        t=jnp.asarray(t, dtype),
        dt=jnp.asarray(dt, dtype),
        q=q,
        qd=qd,
        t0=jnp.asarray(t0, dtype),
        t1=jnp.asarray(t1, dtype),
        num_steps=jnp.asarray(stats["num_steps"], jnp.int32),
        result=jnp.asarray(result._value, jnp.int32),
        max_steps=max_steps,
        max_segments=max_segments,
        index=jnp.asarray(-1, jnp.int32),
        value=jnp.asarray(jnp.nan, dtype),
    )


def first_failure(earlier: Failure, later: Failure) -> Failure:
    """``earlier`` if it failed, else ``later`` (for simulations made of several solves)."""
    failed = earlier.code != FailureCode.COMPLETED
    pick = lambda a, b: jnp.where(failed, a, b)  # noqa: E731
    merged = jax.tree.map(pick, earlier, later)
    return eqx.tree_at(lambda f: f.num_steps, merged, earlier.num_steps + later.num_steps)


# ----------------------------------------------------------------------------- compiled check
#: The static messages indexed by code, as ``eqx.branched_error_if`` takes them.
_MESSAGES = tuple(code.message for code in FailureCode)


def error_if_failed(failure: Failure, x: PyTree[Array | np.ndarray]) -> PyTree[Array | np.ndarray]:
    """Compiled counterpart of `jaxlag._diagnosis.raise_if_failed`: ``x`` (a pytree of
    floating-point arrays: JAX arrays, or NumPy constants that tracing left on the host), or an
    ``eqx.branched_error_if`` with the static `FailureCode.message` of the failure's code (the
    record itself stays in the trajectory).

    The check must survive dead-code elimination in programs that use only derivatives of ``x``
    (``jax.jit(jax.grad(...))`` of an event time reads no primal output): the tangents of ``x``
    are multiplied by a checked exact 1.0, so the derivative program runs the check too."""
    return _checked(x, failure.code)


def _checked_one(code, dtype):
    return eqx.branched_error_if(jnp.ones((), dtype), code != FailureCode.COMPLETED, code, _MESSAGES)


@jax.custom_jvp
def _checked(x, code):
    return eqx.branched_error_if(x, code != FailureCode.COMPLETED, code, _MESSAGES)


@_checked.defjvp
def _checked_jvp(primals, tangents):
    x, code = primals
    tx, _ = tangents
    # Linear in the tangents (a product with a residual), so it transposes for reverse mode.
    tx = jax.tree_util.tree_map(lambda t: t * _checked_one(code, t.dtype), tx)
    return _checked(x, code), tx
