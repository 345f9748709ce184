"""A step-size controller guard: stop a solve at a non-finite step of round-off size.

Wraps the user's controller (`guard`); the guard's state records the time reached, the last
step size and the last accepted state, which the failure record (``jaxlag._errors``) reports.

The guard also carries the initial step ``dt0`` and hands it to the wrapped controller's
``init``, so that ``diffeqsolve`` is called with ``dt0=None``: diffrax checks a given ``dt0``'s
sign against ``t1 − t0`` inside the program (a host callback when the times are traced, which
keeps the program out of JAX's persistent cache). ``simulate`` checks a concrete ``dt0`` on the
host; a traced one takes the direction of integration (``|dt0|·sign(t1 − t0)``).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, PyTree

from .forwarding import ForwardingAdaptiveController

_ULPS = 64  # a step at most this many ulps of the time scale is at round-off


class GuardState(eqx.Module):
    """What `FiniteStepGuard` carries from step to step (and returns at the end)."""

    inner: PyTree  # the wrapped controller's state
    t: Float[Array, ""]  # time reached: end of the last accepted step
    dt: Float[Array, ""]  # size of the last attempted step
    q: Float[Array, " n"]  # last accepted state
    qd: Float[Array, " n"]
    failed: Bool[Array, ""]  # the guard stopped the solve
    nonfinite: Bool[Array, ""]  # ... because a step was non-finite
    scale: Float[Array, ""]  # time scale of the solve: max(|t0|, |t1|, t1 − t0)


def _guarded_init(guard, terms, t0, t1, y0, dt0, args, func, error_order):
    """``init`` of either guard: the wrapped controller's, with the guard's ``dt0`` and record."""
    if guard.initial_step is not None:
        dt0 = guard.initial_step
    tnext, inner = guard.controller.init(terms, t0, t1, y0, dt0, args, func, error_order)
    q, qd = y0
    t0 = jnp.asarray(t0, q.dtype)
    scale = guard.time_scale
    if scale is None:
        scale = jnp.maximum(jnp.maximum(jnp.abs(t0), jnp.abs(t1)), jnp.abs(t1 - t0))
    record = jax.lax.stop_gradient((t0, jnp.asarray(tnext - t0, q.dtype), q, qd, jnp.asarray(scale, q.dtype)))
    state = GuardState(inner, *record[:4], jnp.asarray(False), jnp.asarray(False), record[4])
    return tnext, state


def _guarded_adapt(controller, adaptive, t0, t1, y0, y1_candidate, args, y_error, error_order, state):
    keep, tprev, tnext, jump, inner, result = controller.adapt_step_size(
        t0, t1, y0, y1_candidate, args, y_error, error_order, state.inner
    )
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(y1_candidate)]))
    dt = t1 - t0
    q0, qd0 = y0
    if adaptive:
        # Only at round-off step sizes is a failed step final: larger NaN steps (overshooting
        # into a region where L is undefined) are retried smaller, as diffrax does.
        tiny = dt <= _ULPS * jnp.finfo(q0.dtype).eps * state.scale
        fail = tiny & (~finite | ~keep | (t1 <= t0))
    else:
        fail = ~finite
    keep = keep & ~fail
    result = diffrax.RESULTS.where(fail, diffrax.RESULTS.dt_min_reached, result)
    # The record is for messages, never differentiated: no tangents carried through the loop.
    record = jax.lax.stop_gradient(
        (jnp.where(keep, t1, t0).astype(q0.dtype), jnp.asarray(dt, q0.dtype), q0, qd0)
    )
    new = GuardState(inner, *record, fail, fail & ~finite, state.scale)
    return keep, tprev, tnext, jump, new, result


class FiniteStepGuard(ForwardingAdaptiveController):
    """Wraps an adaptive controller: stop at a non-finite step of round-off size (see module)."""

    controller: diffrax.AbstractAdaptiveStepSizeController
    initial_step: Float[ArrayLike, ""] | None = None  # |dt0|, given the direction by `wrap`
    time_scale: Float[ArrayLike, ""] | None = None  # of round-off: default max(|t0|, |t1|, t1 − t0)

    def wrap(self, direction):
        wrapped, step = self.controller.wrap(direction), _directed(self.initial_step, direction)
        return FiniteStepGuard(wrapped, step, self.time_scale)  # pyright: ignore[reportCallIssue]

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        return _guarded_init(self, terms, t0, t1, y0, dt0, args, func, error_order)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        return _guarded_adapt(
            self.controller, True, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state
        )


class FiniteFixedStepGuard(diffrax.AbstractStepSizeController):
    """Wraps a non-adaptive controller (constant steps): stop at the first non-finite step."""

    controller: diffrax.AbstractStepSizeController
    initial_step: Float[ArrayLike, ""] | None = None  # |dt0|, given the direction by `wrap`
    time_scale: Float[ArrayLike, ""] | None = None  # of round-off: default max(|t0|, |t1|, t1 − t0)

    def wrap(self, direction):
        wrapped, step = self.controller.wrap(direction), _directed(self.initial_step, direction)
        return FiniteFixedStepGuard(wrapped, step, self.time_scale)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        return _guarded_init(self, terms, t0, t1, y0, dt0, args, func, error_order)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        return _guarded_adapt(
            self.controller, False, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state
        )


def _directed(initial_step, direction):
    """``|dt0|`` with the sign of the direction of integration (diffrax's ``wrap``)."""
    return None if initial_step is None else jnp.abs(initial_step) * direction


def guard(controller, dt0=None):
    """The controller wrapped in the matching guard, which carries the initial step ``dt0``
    (solve with ``dt0=None`` then: see module). ``StepTo`` stays as it is (diffrax ends its loop
    by counting its steps; a non-finite result is then caught on the saved states; it takes no
    ``dt0``)."""
    if isinstance(controller, (FiniteStepGuard, FiniteFixedStepGuard)):
        controller = controller.controller
    if isinstance(controller, diffrax.StepTo):
        return controller
    if isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        return FiniteStepGuard(controller, dt0)  # pyright: ignore[reportCallIssue]
    return FiniteFixedStepGuard(controller, dt0)


def saving_guard_state(saveat: diffrax.SaveAt) -> diffrax.SaveAt:
    """``saveat`` that also returns the final controller state (the guard's record)."""
    return eqx.tree_at(lambda s: s.controller_state, saveat, True)
