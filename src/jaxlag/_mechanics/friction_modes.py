r"""The friction modes of the segmented integration, as an object the segment loop calls.

Each [`Coulomb`][jaxlag.Coulomb] contact is in one mode per segment: 0 (stick) or ``s = ±1`` (slip
with ``sign v_t = s``); `jaxlag._mechanics.friction` gives the dynamics in a mode and the
switch quantities. This module says how the modes start, what ends a segment and how the modes
change at the end of one. `NoFriction` is the "does nothing" law of a system without
Coulomb contacts (as diffrax's ``ConstantStepSize`` is its "no adaptivity" controller): the
loop calls the same methods and never asks whether friction is present.
"""

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .. import _compile as compilation
from .friction import (
    decide_modes,
    project_tangent_velocity,
    solve_with_modes,
    switch_values,
    tangent_terms,
)


class FrictionUpdate(eqx.Module):
    """The state of the friction modes after a segment's end."""

    qd: Float[Array, " n"]  # the velocities, v_t = 0 made exact on the contacts that stick
    modes: Float[Array, " k"]
    index: Int[Array, ""]  # the contact whose switch ended the segment (if one did)
    stuck: Bool[Array, ""]  # whether that contact sticks now


class AbstractFrictionModes(eqx.Module):
    """How the friction modes (k,) of a run start, end segments and switch."""

    @abc.abstractmethod
    def initial(self, system, q0, qd0, t0, args, active, tolerance) -> tuple[Array, Array]:
        """``(modes, q̇0)`` at the start of the run."""

    @abc.abstractmethod
    def switch_values(self, system, q, qd, t, args, active, modes) -> Float[Array, " s"]:
        """The quantities (0 or 1 of them) whose zero from above ends a segment."""

    @abc.abstractmethod
    def after_switch(
        self, system, args, *, q_e, qd_e, q, qd, t, active, new_active, modes, switched, jumped, tolerance
    ) -> FrictionUpdate:
        """The modes after a segment ending at ``(q_e, q̇_e)`` and continuing from ``(q, q̇)``:
        ``switched`` when a friction switch ended it, ``jumped`` when the state jumped there."""


class NoFriction(AbstractFrictionModes):
    """No Coulomb contact: no mode, no switch, nothing changes."""

    def initial(self, system, q0, qd0, t0, args, active, tolerance):
        return jnp.zeros((0,), q0.dtype), qd0

    def switch_values(self, system, q, qd, t, args, active, modes):
        return jnp.zeros((0,), q.dtype)

    def after_switch(
        self, system, args, *, q_e, qd_e, q, qd, t, active, new_active, modes, switched, jumped, tolerance
    ):
        return FrictionUpdate(qd=qd, modes=modes, index=jnp.asarray(0), stuck=jnp.asarray(False))


@compilation.filter_jit
def _friction_value(system, y, t, args, active, modes):
    """``min`` over the contacts of ``s v_t`` and ``μ λ_N − |λ_t|`` (``inf`` if none acts).
    Jitted on its own: diffrax traces event conditions a dozen times per solve (its checks, the
    loop body's static analysis, the root finder), and JAX's tracing cache serves the repeats."""
    q, qd = y
    return jnp.min(switch_values(system, q, qd, t, args, active, modes), initial=jnp.inf)


class CoulombModes(AbstractFrictionModes):
    """The stick–slip modes of the system's [`Coulomb`][jaxlag.Coulomb] contacts."""

    contacts: tuple[int, ...] = eqx.field(static=True)  # the normal row of each contact

    def _acting(self, active: Bool[Array, " m_h"]) -> Bool[Array, " k"]:
        return active[jnp.asarray(self.contacts, jnp.int32)]

    def initial(self, system, q0, qd0, t0, args, active, tolerance):
        """A contact at rest (``|v_t| ≤`` the constraint tolerance) sticks if it can; the
        sticking contacts' ``v_t`` is then made exactly 0 (a mass-weighted projection)."""
        acting = self._acting(active)
        t0 = jnp.asarray(t0, q0.dtype)
        v0 = tangent_terms(system, q0, qd0, t0, args)[1]
        modes = decide_modes(system, q0, qd0, t0, args, active, acting & (jnp.abs(v0) <= tolerance), v0)
        modes = jnp.where(acting, modes, 0.0)
        sticking = acting & (modes == 0)
        projected = project_tangent_velocity(system, q0, qd0, t0, args, active, sticking)
        return modes, jnp.where(jnp.any(sticking), projected, qd0)

    def switch_values(self, system, q, qd, t, args, active, modes):
        return jnp.reshape(_friction_value(system, (q, qd), t, args, active, modes), (1,))

    def after_switch(
        self, system, args, *, q_e, qd_e, q, qd, t, active, new_active, modes, switched, jumped, tolerance
    ):
        """The contact whose switch ended the segment: slip → try stick (else slip the other
        way); stick → slip where the net force drives it, ``s = −sign λ_t``. A contact that has
        just engaged sticks if at rest, else slips along ``v_t``; the others keep their mode
        (sticking ones are tested again: a jump may break them loose). ``v_t = 0`` is made
        exact where a contact sticks, or starts to slip from rest."""
        index = jnp.argmin(switch_values(system, q_e, qd_e, t, args, active, modes))
        lam_t_e = solve_with_modes(system, q_e, qd_e, t, args, active=active, modes=modes)[3]
        event_row = switched & (jnp.arange(len(self.contacts)) == index)
        was_acting, acting = self._acting(active), self._acting(new_active)
        v_next = tangent_terms(system, q, qd, t, args)[1]
        newly = acting & ~was_acting
        candidates = jnp.where(newly, jnp.abs(v_next) <= tolerance, modes == 0)
        directions = jnp.where(newly, v_next, modes)
        candidates = jnp.where(event_row, modes != 0, candidates)
        directions = jnp.where(event_row & (modes == 0), -lam_t_e, directions)
        decided = decide_modes(system, q, qd, t, args, new_active, acting & candidates, directions)
        decided = jnp.where(acting, decided, 0.0)
        zero = acting & ((decided == 0) | event_row)
        qd_f = project_tangent_velocity(system, q, qd, t, args, new_active, zero)
        changed = jumped | switched
        new_modes = jnp.where(changed, decided, modes)
        return FrictionUpdate(
            qd=jnp.where(changed & jnp.any(zero), qd_f, qd),
            modes=new_modes,
            index=index,
            stuck=new_modes[index] == 0,
        )


def friction_modes_for(system) -> AbstractFrictionModes:
    """`CoulombModes` of the system's contacts, or `NoFriction`."""
    if not system.friction:
        return NoFriction()
    return CoulombModes(contacts=tuple(e.contact for e in system.friction))
