r"""The state resets of user events, as an object the segment loop calls.

A non-terminal [`Event`][jaxlag.Event] with a ``reset`` maps the state at each recorded crossing,
``(q⁺, q̇⁺) = reset(q, q̇, [t], [args])``; the segment loop then projects it onto the constraints
acting after it (`jaxlag._mechanics.jumps`). `NoResets` is the "does nothing"
implementation for runs whose events have no reset: the loop calls the same methods.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._conventions import UserFunction
from .constraints import holonomic_terms


class AbstractResets(eqx.Module):
    """The resets of a run's user conditions."""

    @property
    @abc.abstractmethod
    def newton_steps(self) -> int:
        """Newton steps of the position projection after a jump (a reset may move ``q`` far off
        the constraints: 4 steps take 10 % to round-off; else 2)."""

    @abc.abstractmethod
    def apply(
        self, index: Int[Array, ""], recorded: Bool[Array, ""], q, qd, t, args
    ) -> tuple[Array, Array, Bool[Array, ""]]:
        """``(q⁺, q̇⁺, fired)``: the state after a recorded crossing of condition ``index``."""

    @abc.abstractmethod
    def released(self, system, q, qd, t, args, fired, candidates, tolerance) -> Bool[Array, " m_h"]:
        """The acting unilateral rows (``candidates``) whose gap the reset opens
        (``ḟ⁺ >`` the constraint tolerance): they let go."""

    @abc.abstractmethod
    def side_after(
        self, fired, index, sides, jump_sides, values, crossed_side, residual
    ) -> Float[Array, " e"]:
        """The side (±1) of each condition after the reset of condition ``index``."""


class NoResets(AbstractResets):
    """No user condition has a reset: nothing is mapped."""

    @property
    def newton_steps(self) -> int:
        return 2

    def apply(self, index, recorded, q, qd, t, args):
        return q, qd, jnp.asarray(False)

    def released(self, system, q, qd, t, args, fired, candidates, tolerance):
        return jnp.zeros_like(candidates)

    def side_after(self, fired, index, sides, jump_sides, values, crossed_side, residual):
        return sides


def _checked_reset(reset: UserFunction, j: int, n: int, dtype):
    """``(q, q̇, t, args) ↦ (q⁺, q̇⁺)`` of condition ``j``, its output shapes checked."""

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


def _identity(q, qd, t, args):
    return q, qd


class EventResets(AbstractResets):
    """The resets of the user conditions, one per condition (``None``: the identity)."""

    resets: tuple[UserFunction | None, ...]

    @property
    def newton_steps(self) -> int:
        return 4

    def apply(self, index, recorded, q, qd, t, args):
        n, dtype = q.shape[0], q.dtype
        branches = [
            _identity if reset is None else _checked_reset(reset, j, n, dtype)
            for j, reset in enumerate(self.resets)
        ]
        has_reset = jnp.array([reset is not None for reset in self.resets], bool)
        fired = recorded & has_reset[index]
        q_r, qd_r = jax.lax.switch(index, branches, q, qd, t, args)
        return jnp.where(fired, q_r, q), jnp.where(fired, qd_r, qd), fired

    def released(self, system, q, qd, t, args, fired, candidates, tolerance):
        f_dot = holonomic_terms(system, q, qd, t, args)[1]
        return fired & candidates & (f_dot > tolerance)

    def side_after(self, fired, index, sides, jump_sides, values, crossed_side, residual):
        """The crossed condition of a reset sits at its root (``c ≈ 0`` up to the root finder's
        residual, of either sign) unless the reset moved it off zero (beyond 10³ × that
        residual): then the sign of ``c``, else of ``ċ`` (``c̈``), along the motion; the others
        take their sides after the jump. ``values``: ``(c, ċ, c̈)`` after the reset."""
        c, rate, curvature = (v[index] for v in values)
        residual = jnp.where(jnp.isfinite(residual), residual, 0.0)
        moved = jnp.abs(c) > 1e3 * (residual + jnp.finfo(c.dtype).eps)
        by_rate = jnp.where(rate != 0, jnp.sign(rate), jnp.sign(curvature))
        side = jnp.where(moved, jnp.sign(c), jnp.where(by_rate != 0, by_rate, -crossed_side))
        return jnp.where(fired, jump_sides.at[index].set(side), sides)


def resets_for(resets: tuple[UserFunction | None, ...]) -> AbstractResets:
    """`EventResets` if any condition has a reset, else `NoResets`."""
    if all(reset is None for reset in resets):
        return NoResets()
    return EventResets(resets=resets)
