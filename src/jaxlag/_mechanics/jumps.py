r"""The jump of the state at the end of a segment, as an object the segment loop calls.

At a release, a contact or a reset the state jumps onto the constraints acting after it:
an impact on the rows that touch while approaching (Newton's law, `jaxlag._mechanics.impacts`),
then the mass-weighted projection of the positions onto the rows that touch (acting or rebounding
from ``f = 0``) and of the velocities onto the acting ones (a rebound keeps ``ḟ⁺ = e|ḟ⁻|``). A
newly engaged constraint that would have to pull separates again. The impulse on each holonomic
row, ``M(q̇⁺ − q̇⁻) = JᵀΛ (+ Aᵀ·)``, is recorded with the sign of ``λ``.

Three laws, chosen once per run by `jump_law_for`: `ImpactJump` (the system has
holonomic rows), `VelocityReprojection` (no holonomic row, velocity constraints and a
reset: ``g = 0`` again) and `NoJump` (nothing to project: the state is left as it is).
"""

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._stabilization import project_state
from .constraints import holonomic_residual
from .friction import solve_with_modes
from .impacts import impact
from .resets import AbstractResets, NoResets


class Jump(eqx.Module):
    """The state a segment continues from, and what the jump did."""

    q: Float[Array, " n"]
    qd: Float[Array, " n"]
    active: Bool[Array, " m_h"]  # the acting holonomic rows after the jump
    impulses: Float[Array, " m_h"]  # Λ; zero where nothing jumped
    release_index: Int[Array, ""]  # the released row (if one was)
    contact_index: Int[Array, ""]  # the row that made contact (if one did)
    rebounded: Bool[Array, ""]  # ... and rebounded from it (restitution): an IMPACT, not a CONTACT


class SegmentEnd(eqx.Module):
    """Where a segment ended and what ended it (see the segment loop)."""

    t: Float[Array, ""]
    q: Float[Array, " n"]  # the state at the end, before the jump
    qd: Float[Array, " n"]
    q_reset: Float[Array, " n"]  # after the user's reset (the end state if none fired)
    qd_reset: Float[Array, " n"]
    released: Bool[Array, ""]
    contacted: Bool[Array, ""]
    reset: Bool[Array, ""]


class AbstractJumpLaw(eqx.Module):
    """The map from a segment's end to the state the next segment starts from."""

    @abc.abstractmethod
    def __call__(
        self,
        system,
        args,
        end: SegmentEnd,
        *,
        active,
        modes,
        unilateral,
        resets: AbstractResets,
        zeno,
        tolerance,
    ) -> Jump:
        """The state after the end ``end`` of a segment run with the rows ``active``."""


def _unjumped(end: SegmentEnd, active) -> Jump:
    zero = jnp.asarray(0)
    return Jump(end.q, end.qd, active, jnp.zeros((0,), end.q.dtype), zero, zero, jnp.asarray(False))


class NoJump(AbstractJumpLaw):
    """No holonomic row and nothing to project: the state after a reset as it is."""

    def __call__(self, system, args, end, *, active, modes, unilateral, resets, zeno, tolerance):
        jump = _unjumped(end, active)
        return eqx.tree_at(lambda j: (j.q, j.qd), jump, (end.q_reset, end.qd_reset))


class VelocityReprojection(AbstractJumpLaw):
    """No holonomic row: after a reset the velocities are projected onto ``g = 0`` again."""

    def __call__(self, system, args, end, *, active, modes, unilateral, resets, zeno, tolerance):
        qd = project_state(system, end.q_reset, end.qd_reset, end.t, args, 0, refresh_mass=True)[1]
        jump = _unjumped(end, active)
        return eqx.tree_at(
            lambda j: (j.q, j.qd),
            jump,
            (jnp.where(end.reset, end.q_reset, end.q), jnp.where(end.reset, qd, end.qd)),
        )


class ImpactJump(AbstractJumpLaw):
    """Releases, contacts with their impacts, and resets projected onto the acting rows."""

    def __call__(self, system, args, end, *, active, modes, unilateral, resets, zeno, tolerance):
        t = end.t
        m_h = active.shape[0]
        jumped = end.released | end.contacted | end.reset
        # Which constraint switched: the one whose multiplier / gap is at its minimum.
        lam_e = solve_with_modes(system, end.q, end.qd, t, args, active=active, modes=modes)[1]
        f_e = holonomic_residual(system, end.q, t, args)
        release_index = jnp.argmin(jnp.where(active & unilateral, lam_e, jnp.inf))
        contact_index = jnp.argmin(jnp.where(~active & unilateral, f_e, jnp.inf))
        rows = jnp.arange(m_h)
        released_row = end.released & (rows == release_index)
        forced = end.contacted & (rows == contact_index)
        leaving = resets.released(
            system, end.q_reset, end.qd_reset, t, args, end.reset, unilateral & active, tolerance
        )
        before = active & ~released_row & ~leaving
        qd_i, impulses, after_impact, rebound = impact(
            system,
            end.q_reset,
            end.qd_reset,
            t,
            args,
            before,
            unilateral,
            forced,
            released_row,
            zeno,
            tolerance,
        )
        q_p = project_state(system, end.q_reset, qd_i, t, args, resets.newton_steps, after_impact | rebound)[
            0
        ]
        qd_p = project_state(system, q_p, qd_i, t, args, 0, after_impact, refresh_mass=True)[1]
        # A constraint that would have to pull right after engaging separates again.
        lam_p = solve_with_modes(system, q_p, qd_p, t, args, active=after_impact, modes=modes)[1]
        pulls = after_impact & ~before & unilateral & (lam_p < 0)
        return Jump(
            q=jnp.where(jumped, q_p, end.q),
            qd=jnp.where(jumped, qd_p, end.qd),
            active=jnp.where(jumped, after_impact & ~pulls, active),
            impulses=jnp.where(jumped, impulses, 0.0),
            release_index=release_index,
            contact_index=contact_index,
            rebounded=end.contacted & rebound[contact_index],
        )


def jump_law_for(system, m_h: int, resets: AbstractResets) -> AbstractJumpLaw:
    """The jump law of a run: `ImpactJump` with holonomic rows, else
    `VelocityReprojection` for resets under velocity constraints, else `NoJump`."""
    if m_h:
        return ImpactJump()
    if system.velocity_constraints is not None and not isinstance(resets, NoResets):
        return VelocityReprojection()
    return NoJump()
