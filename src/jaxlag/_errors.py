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
* inside a transformation (``jit``, ``vmap``, ``grad``), as ``jl.Checks(compiled=...)`` says
  (`AbstractOnFailure`): with `RaiseOnFailure` (the default) from the compiled
  program (``eqx.branched_error_if``, a host callback) with the static `FailureCode.message` of
  the cause; with `NaNOnFailure` not at all: the floating-point outputs are NaN and the code
  says why, and the program holds no host callback (JAX's persistent cache keeps it,
  ``jax.export`` serializes it). Either way the numbers stay in the returned record. With
  ``throw=False`` nothing is raised and ``traj.raise_if_failed()`` raises the full message, with
  the numbers, later and eagerly.

The input checks of ``simulate`` follow the same choice: compiled as values they end the record
with `FailureCode.INITIAL_STATE`, `FailureCode.SAVE_TIMES` or `FailureCode.PARAMETER`
(`refused`). A check site that no argument reaches (inside a user's function, a ``System``
method called in a force) reads the choice from a trace-time context that ``simulate`` sets
while it traces (`on_failure`, `compiled_check`).
"""

import abc
import contextlib
import contextvars
import dataclasses
import enum
from collections.abc import Iterator, Sequence
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PyTree

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
    program (`error_if_failed`); the eager message, with the numbers, is built on the host
    (see [How errors surface][how-errors-surface-under-jit-vmap-and-gpu]).

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

    The last three are the input checks of [`simulate`][jaxlag.simulate] compiled as values:
    they appear only under ``jl.Checks(compiled=jl.NaNOnFailure())`` inside ``jit``/``vmap``
    (eagerly, and with the default ``jl.RaiseOnFailure()``, the check raises instead). The run
    stops at ``t0`` (``t``, ``q``, ``qd`` are the initial state); ``traj.raise_if_failed()``,
    called outside the transformation on the returned record, checks that state again on the
    host and raises the full message with the numbers.

    - ``INITIAL_STATE`` (9): ``(q0, qd0)`` failed the initial-state check
      (``jl.Checks(initial_state=True)``); ``index`` says which, in the order of the eager
      diagnosis: 0 a check of the Lagrangian's own (rigid bodies' masses, inertias and poses,
      [`lagrangian_from_positions`][jaxlag.coordinates.lagrangian_from_positions]), 1 a
      non-finite state, 2 a non-finite mass matrix, 3 a singular or indefinite one, 4 a
      non-finite constraint Jacobian, 5 non-finite constraints, 6 ``diagonal_mass=True`` with
      off-diagonal entries, 7 redundant constraints, 8 a violated unilateral constraint, 9 off
      the constraint manifold, 10 a unilateral constraint that would pull.
    - ``SAVE_TIMES`` (10): traced save times ``ts`` are not strictly increasing
      (``jl.Checks(times=True)``); ``index`` is the first ``k`` with ``ts[k + 1] <= ts[k]`` (or a
      NaN), ``value`` is ``ts[k]``.
    - ``PARAMETER`` (11): a floating-point leaf of ``args`` is not finite (NaN or inf);
      ``index`` is its position among the floating-point leaves of ``args``
      (``jax.tree.leaves`` order).
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
    INITIAL_STATE = (
        9,
        "jaxlag: the simulation did not start: the initial state failed its check (non-finite, "
        "a singular mass matrix, redundant constraints, off the constraint manifold, a "
        "unilateral constraint violated or pulling, or a check of the Lagrangian's own bodies)."
        + _COMPILED_HINT,
    )
    SAVE_TIMES = (
        10,
        "jaxlag: the simulation did not start: the save times ts are not strictly increasing "
        "and finite." + _COMPILED_HINT,
    )
    PARAMETER = (
        11,
        "jaxlag: the simulation did not start: a floating-point parameter in args is not finite "
        "(NaN or inf); traj.failure.index says which leaf." + _COMPILED_HINT,
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


def refused(
    failure: Failure,
    code: Int[ArrayLike, "*batch"],
    index: Int[ArrayLike, "*batch"],
    value: Float[ArrayLike, "*batch"],
    q0: Float[Array, "*batch n"],
    qd0: Float[Array, "*batch n"],
) -> Failure:
    """``failure`` (a run's record), or where ``code`` is not ``COMPLETED`` the refusal of an
    input check compiled as a value (`NaNOnFailure`): the run did not start, so the record
    says ``code`` at ``t0``, from ``(q0, qd0)``, with ``index`` and ``value``."""
    no = jnp.asarray(code) == FailureCode.COMPLETED
    dtype = failure.t.dtype

    def pick(mine, theirs):
        return jnp.where(no, theirs, jnp.asarray(mine, jnp.result_type(theirs)))

    return dataclasses.replace(
        failure,
        code=pick(code, failure.code),
        t=pick(failure.t0, failure.t),
        dt=pick(jnp.asarray(jnp.nan, dtype), failure.dt),
        q=jnp.where(no[..., None], failure.q, q0),
        qd=jnp.where(no[..., None], failure.qd, qd0),
        index=pick(index, jnp.asarray(-1, jnp.int32) if failure.index is None else failure.index),
        value=pick(value, jnp.asarray(jnp.nan, dtype) if failure.value is None else failure.value),
    )


# ----------------------------------------------------------------------------- compiled checks: raise or NaN
class AbstractOnFailure(eqx.Module):
    """What a check compiled into a program does when it fails: ``jl.Checks(compiled=...)``.

    Concrete inputs are always checked on the host, and a concrete failure record always raises
    there (with the numbers and a diagnosis): this chooses only for the checks that the values
    leave inside a compiled program, those of a call traced by the user's ``jax.jit``,
    ``jax.vmap`` or ``jax.export``. [`RaiseOnFailure`][jaxlag.RaiseOnFailure] (the default)
    raises with a static message, through a host callback
    (``eqx.branched_error_if``); [`NaNOnFailure`][jaxlag.NaNOnFailure] returns NaN and a
    [`FailureCode`][jaxlag.FailureCode] in ``traj.failure.code``, with no host callback.

    Two methods, one per kind of check site: `check` for a value with a flag (the input
    checks), `outputs` for the outputs of a run with its failure record.
    """

    #: Whether a failed check is recorded (NaN outputs and a `FailureCode`) instead of raised:
    #: ``simulate`` then compiles its input checks as values (`refused`), not as checks.
    records: ClassVar[bool]

    @abc.abstractmethod
    def check(
        self, x: PyTree, failed: Bool[ArrayLike, ""], index: Int[ArrayLike, ""], messages: Sequence[str]
    ) -> PyTree:
        """``x`` (any pytree), checked: ``failed`` a boolean scalar, ``messages[index]`` the
        static message of the failure."""

    @abc.abstractmethod
    def outputs(self, failure: Failure, x: PyTree[Array | np.ndarray]) -> PyTree[Array | np.ndarray]:
        """``x`` (the floating-point outputs of a run, batch axes first, as in ``failure``),
        checked against the run's ``failure`` record. The check must survive dead-code
        elimination in programs that use only derivatives of ``x`` (``jax.jit(jax.grad(...))``
        of an event time reads no primal output): the tangents of ``x`` are multiplied by a
        checked exact 1.0, so the derivative program runs the check too."""


class RaiseOnFailure(AbstractOnFailure):
    """A failed compiled check raises (the default of [`Checks`][jaxlag.Checks]): the program
    holds ``eqx.branched_error_if``, a host callback that raises the static message of the
    cause (`FailureCode.message` for a failed run) when the program runs. The numbers stay
    in the returned record; call outside the transformation for the full diagnosis. JAX's
    persistent cache does not keep such a program, and ``jax.export`` cannot serialize it."""

    records: ClassVar[bool] = False

    def check(
        self, x: PyTree, failed: Bool[ArrayLike, ""], index: Int[ArrayLike, ""], messages: Sequence[str]
    ) -> PyTree:
        """``eqx.branched_error_if(x, failed, index, messages)``."""
        return eqx.branched_error_if(x, failed, index, tuple(messages))

    def outputs(self, failure: Failure, x: PyTree[Array | np.ndarray]) -> PyTree[Array | np.ndarray]:
        """``x``, raising `FailureCode.message` of the record's code when the program runs."""
        return _checked(x, failure.code)


class NaNOnFailure(AbstractOnFailure):
    """A failed compiled check returns NaN: the floating-point outputs of a run that failed (or
    did not start) are NaN, their derivatives too, and ``traj.failure.code`` says why (a
    [`FailureCode`][jaxlag.FailureCode]; ``traj.failure`` keeps the numbers). Under ``jax.vmap``
    each member fails on its own. The program holds no host callback, so JAX's persistent
    cache can keep it and ``jax.export`` can serialize it. Test the outputs yourself, e.g.
    ``traj.failure.code == jl.FailureCode.COMPLETED`` or ``jnp.isnan(traj.q)``."""

    records: ClassVar[bool] = True

    def check(
        self, x: PyTree, failed: Bool[ArrayLike, ""], index: Int[ArrayLike, ""], messages: Sequence[str]
    ) -> PyTree:
        """``x`` with its floating-point arrays NaN where ``failed`` (the message is not used)."""
        del index, messages
        dynamic, static = eqx.partition(x, eqx.is_inexact_array)
        return eqx.combine(_nan_if(dynamic, jnp.asarray(failed)), static)

    def outputs(self, failure: Failure, x: PyTree[Array | np.ndarray]) -> PyTree[Array | np.ndarray]:
        """``x`` NaN where the record's code is not ``COMPLETED`` (per batch member)."""
        return _nan_if(x, failure.code != FailureCode.COMPLETED)


#: The choice in force while jaxlag traces a program: set by ``simulate`` (`on_failure`) for the
#: check sites it cannot reach by an argument, those inside the user's functions (a ``System``
#: method called in a force) and inside jaxlag's own programs; read by `compiled_check` only.
_ON_FAILURE: contextvars.ContextVar[AbstractOnFailure] = contextvars.ContextVar(
    "jaxlag_on_failure", default=RaiseOnFailure()
)


@contextlib.contextmanager
def on_failure(choice: AbstractOnFailure) -> Iterator[None]:
    """Trace the body with ``choice`` for every `compiled_check` in it (a ``with`` block:
    the previous choice is restored on exit). Programs compiled by `jaxlag._compile.filter_jit`
    are cached per choice, so programs with different choices never share a trace."""
    token = _ON_FAILURE.set(choice)
    try:
        yield
    finally:
        _ON_FAILURE.reset(token)


def current_on_failure() -> AbstractOnFailure:
    """The choice in force (`on_failure`); `RaiseOnFailure` outside every ``simulate``."""
    return _ON_FAILURE.get()


def compiled_check(
    x: PyTree, failed: Bool[ArrayLike, ""], index: Int[ArrayLike, ""], messages: Sequence[str]
) -> PyTree:
    """A check compiled into the program being traced, as the choice in force says
    (`current_on_failure`): every compiled check of jaxlag calls this (or the choice it
    was given) instead of ``eqx.error_if``. ``failed``: a boolean scalar; ``messages[index]``:
    the static message."""
    return _ON_FAILURE.get().check(x, failed, index, messages)


def error_if_failed(failure: Failure, x: PyTree[Array | np.ndarray]) -> PyTree[Array | np.ndarray]:
    """``RaiseOnFailure().outputs(failure, x)``: compiled counterpart of
    `jaxlag._diagnosis.raise_if_failed`."""
    return RaiseOnFailure().outputs(failure, x)


#: The static messages indexed by code, as ``eqx.branched_error_if`` takes them.
_MESSAGES = tuple(code.message for code in FailureCode)


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


def _leading(failed: Array, x: Array) -> Array:
    """``failed`` (batch axes) broadcastable against ``x`` (batch axes first); a leaf without
    the batch axes fails where any member does."""
    if x.ndim >= failed.ndim and x.shape[: failed.ndim] == failed.shape:
        return failed.reshape(failed.shape + (1,) * (x.ndim - failed.ndim))
    return jnp.any(failed)


@jax.custom_jvp
def _nan_if(x, failed):
    return jax.tree_util.tree_map(
        lambda a: jnp.where(_leading(failed, a), jnp.asarray(jnp.nan, a.dtype), a), x
    )


@_nan_if.defjvp
def _nan_if_jvp(primals, tangents):
    x, failed = primals
    tx, _ = tangents
    # NaN tangents where failed (a gradient of a failed run is NaN, not a silent 0); linear in
    # the tangents, so it transposes for reverse mode.
    tx = jax.tree_util.tree_map(
        lambda t: t * jnp.where(_leading(failed, t), jnp.asarray(jnp.nan, t.dtype), jnp.ones((), t.dtype)), tx
    )
    return _nan_if(x, failed), tx
