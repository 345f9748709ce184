r"""The conditions that end a segment of the segment loop (`jaxlag._segment_loop`).

``SegmentConditions.switches`` lists the quantities whose zero from above ends a segment, in
this order: ``min λ`` over the acting unilateral rows (a release), ``min f`` over the inactive
ones (a contact), the friction switch (`jaxlag._mechanics.friction_modes`), then ``σ_k c_k``
of each user condition (``σ_k = ±1`` the side ``c_k`` starts the segment on). diffrax locates
their minimum as one condition (releases and contacts alone: two).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from . import _compile as compilation
from ._events import Event
from ._mechanics.constraints import holonomic_residual
from ._mechanics.friction import solve_with_modes
from ._mechanics.friction_modes import AbstractFrictionModes
from ._system import System
from ._vector_field import EquationsOfMotion


def condition_dtype():
    """The dtype of condition values: JAX's default float. (diffrax pads untriggered conditions
    with a Python ``0.0`` inside a ``lax.cond``, which must match the condition's dtype: float32
    states under ``jax_enable_x64`` would otherwise fail to trace.)"""
    return jax.dtypes.canonicalize_dtype(float)


def _masked_min(values, mask):
    return jnp.min(jnp.where(mask, values, jnp.inf), initial=jnp.inf)


@compilation.filter_jit
def _release_value(system, y, t, args, active, unilateral, modes=None):
    """``min λ`` over the acting unilateral constraints (``inf`` if none). Jitted on its own:
    diffrax traces event conditions a dozen times per solve and each trace is a KKT solve;
    JAX's tracing cache serves the repeats."""
    q, qd = y
    lam = solve_with_modes(system, q, qd, t, args, active=active, modes=modes)[1]
    return _masked_min(lam, active & unilateral)


class SegmentConditions(eqx.Module):
    """The conditions of one segment (a Module, so that diffrax's compile cache is reused)."""

    system: System
    events: tuple[Event, ...]
    friction: AbstractFrictionModes
    unilateral: Bool[Array, " m_h"]
    active: Bool[Array, " m_h"]
    t_start: Float[Array, ""]
    sides: Float[Array, " e"] | None  # the side (±1; 0 unknown) of each user condition
    # Inactive unilateral rows that touch (f ≈ 0) at t_start: just rebounded, released or reset.
    departing: Bool[Array, " m_h"] | None
    modes: Float[Array, " k"]

    def release(self, t, y, args, **kwargs):
        """``min λ`` over the acting unilateral rows; 1 if there is none (a constant)."""
        value = self.release_raw(t, y, args)
        return jnp.where(jnp.isfinite(value), value, 1.0).astype(condition_dtype())

    def release_raw(self, t, y, args):
        value = _release_value(self.system, y, t, args, self.active, self.unilateral, self.modes)
        return value.astype(condition_dtype())

    def contact(self, t, y, args, **kwargs):
        """`contact_raw`, 1 where it is ``inf`` (a diffrax condition of its own)."""
        value = self.contact_raw(t, y, args)
        return jnp.where(jnp.isfinite(value), value, 1.0).astype(condition_dtype())

    def contact_raw(self, t, y, args):
        """``min_i f_i`` over the inactive unilateral rows (``inf`` at ``t_start`` and where
        there is none), ``f_i / (t − t_start)`` for the `departing` ones.

        The division keeps the roots of ``f_i`` after ``t_start`` but not the one at ``t_start``
        of a body that has just rebounded from ``f_i = 0``: there ``f_i ≈ ḟ⁺ δ − ½|f̈| δ²``
        (``δ = t − t_start``), ``f_i ≤ 0`` at both ends of a solver step longer than the flight
        (the landing would be missed), while the quotient starts at ``ḟ⁺ > 0`` and is close to
        linear. The other rows keep ``f_i``: concave and decreasing at a landing, where Newton
        from the right converges monotonically."""
        q, _ = y
        f = holonomic_residual(self.system, q, t, args)
        later = t > self.t_start
        if self.departing is not None:
            elapsed = jnp.where(later, t - self.t_start, 1.0).astype(f.dtype)
            f = jnp.where(self.departing, f / elapsed, f)
        value = _masked_min(f, ~self.active & self.unilateral)
        return jnp.where(later, value, jnp.inf).astype(condition_dtype())

    def raw(self, j, t, y, args):
        """The user's condition ``c_j`` at ``(t, q, q̇)``."""
        q, qd = y
        event = self.events[j]
        available = {"t": t, "args": args}
        if "multipliers" in event.condition.keywords:
            available["multipliers"] = solve_with_modes(
                self.system, q, qd, t, args, active=self.active, modes=self.modes
            )[1]
        return jnp.asarray(event.condition(q, qd, **available), condition_dtype())

    def signed(self, t, y, args):
        """``σ_k c_k``: positive on the side each condition starts the segment on (``+inf``
        where that side is unknown, ``σ_k = 0``); it turns ≤ 0 when ``c_k`` crosses."""
        values = jnp.stack([self.raw(j, t, y, args) for j in range(len(self.events))])
        sides = jnp.zeros_like(values) if self.sides is None else self.sides
        return jnp.where(sides != 0, sides * values, jnp.inf)

    def switches(self, t, y, args, release: bool = True):
        """The quantities that end the segment when they reach 0 from above, in this order:
        ``min λ`` and ``min f`` (with unilateral rows), the friction switch (with Coulomb
        contacts), then ``σ_k c_k``. ``release=False``: without the two that need the KKT
        solve (``min λ`` and the friction switch)."""
        values = []
        if self.system.unilateral:
            values = [self.release_raw(t, y, args)] if release else []
            values.append(self.contact_raw(t, y, args))
        if release:
            q, qd = y
            values.append(self.friction.switch_values(self.system, q, qd, t, args, self.active, self.modes))
        if self.events:
            values.append(self.signed(t, y, args))
        values = [jnp.reshape(v, (-1,)).astype(condition_dtype()) for v in values]
        return jnp.concatenate(values) if values else jnp.zeros((0,), condition_dtype())

    def crossing(self, t, y, args, **kwargs):
        """The one diffrax condition of the segment, ``φ = min`` of `switches`: ``φ > 0``
        until the first switch and 0 there. At ``t_start`` each term is put above 0 (its
        quantity may be ~0 after an event, with a residual of either sign, and diffrax counts a
        change of sign to 0 as a crossing)."""
        values = self.switches(t, y, args)
        tiny = jnp.finfo(values.dtype).tiny
        values = jnp.where(t == self.t_start, jnp.maximum(jnp.abs(values), tiny), values)
        # The minimum over the finite terms; 1 if there is none (a constant among them would cap
        # the minimum and stall the root find where the real terms are above it).
        smallest = jnp.min(jnp.where(jnp.isfinite(values), values, jnp.inf))
        return jnp.where(jnp.isfinite(smallest), smallest, 1.0)

    @property
    def paired(self) -> bool:
        """Releases and contacts only: two diffrax conditions, ``min λ`` and ``min f``."""
        return not self.events and not self.system.friction

    def diffrax_event(self, root_finder):
        if self.paired:
            return diffrax.Event([self.release, self.contact], root_finder=root_finder, direction=[False] * 2)
        return diffrax.Event(self.crossing, root_finder=root_finder, direction=False)


def sides_from(values):
    """The side of each condition from ``(c, ċ, c̈)``: the sign of the first non-zero."""
    c0, c1, c2 = values
    side = jnp.where(c0 != 0, jnp.sign(c0), jnp.where(c1 != 0, jnp.sign(c1), jnp.sign(c2)))
    return jnp.where(jnp.isfinite(side), side, 0.0).astype(condition_dtype())


def condition_values(segment: SegmentConditions, baumgarte, q, qd, t, args):
    r"""``(c, ċ, c̈)`` of each user condition at ``(q, q̇, t)``: the derivatives along the motion
    (Lie derivatives along ``ẏ = (q̇, q̈)``, by nested ``jax.jvp``).

    The side each condition starts on is the sign of the first non-zero of them (0 if all
    three vanish), so a condition that is exactly 0 at ``t0`` is on the side it leaves to and
    its first event is its next sign change; the same rule gives the sides after a jump."""
    num_events = len(segment.events)
    field = EquationsOfMotion(segment.system, baumgarte, segment.active, segment.modes)
    t = jnp.asarray(t, q.dtype)

    def values(s, y):
        return jnp.stack([segment.raw(j, s, y, args) for j in range(num_events)])

    def rate(fn):
        def along_motion(s, y):
            return jax.jvp(fn, (s, y), (jnp.ones_like(s), field(s, y, args)))[1]

        return along_motion

    y = (q, qd)
    return values(t, y), rate(values)(t, y), rate(rate(values))(t, y)
