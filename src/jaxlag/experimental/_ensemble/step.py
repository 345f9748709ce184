r"""One explicit Runge–Kutta step of every member of the batch, and the field it evaluates.

    k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),   y₁ = y + h Σ b_i k_i,   e = h Σ b̂_i k_i

with ``f(t, (q, q̇)) = (q̇, q̈)`` the library's equations of motion vmapped over the members
(`BatchedField`) and ``(c, a, b, b̂)`` a `Tableau`. Shared by the XLA loops and the Pallas kernels.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from ..._custom_types import Args
from ..._mechanics.constant_mass import ConstantMass
from ..._stabilization import Baumgarte, Projection
from ..._system import System
from ..._vector_field import EquationsOfMotion
from .settings import Tableau

__all__ = ["BatchedField", "rk_step", "select", "constant_step"]


class BatchedField(eqx.Module):
    """``(t (B,), (q, q̇) (B, n)) ↦ ((q̇, q̈), ...)``: the equations of motion vmapped over members.

    ``member_args`` have a leading batch axis on every leaf, ``shared_args`` none;
    ``constant_mass`` is the per-member `ConstantMass` (or ``None``).
    """

    system: System
    baumgarte: Baumgarte | None
    projection: Projection | None
    member_args: Args
    shared_args: Args
    constant_mass: ConstantMass | None

    def _system(self, constant_mass):
        if constant_mass is None:
            return self.system
        return eqx.tree_at(lambda s: s.constant_mass, self.system, constant_mass, is_leaf=lambda x: x is None)

    def _args(self, member):
        return eqx.combine(member, self.shared_args)

    def __call__(self, t, y):
        def one(ti, qi, qdi, member, constant_mass):
            field = EquationsOfMotion(self._system(constant_mass), self.baumgarte)
            return field(ti, (qi, qdi), self._args(member))

        return jax.vmap(one)(t, y[0], y[1], self.member_args, self.constant_mass)

    def project(self, t, y):
        projection = self.projection
        if projection is None:
            return y

        def one(ti, qi, qdi, member, constant_mass):
            return projection(self._system(constant_mass), qi, qdi, ti, self._args(member))

        return jax.vmap(one)(t, y[0], y[1], self.member_args, self.constant_mass)


def _combine(y, h, coefficients, ks):
    """``y + h Σ c_j k_j`` (zero coefficients skipped; ``h`` per member, shape (B,))."""
    total = None
    for c, k in zip(coefficients, ks):
        if c == 0:
            continue
        term = jax.tree.map(lambda x: float(c) * x, k)
        total = term if total is None else jax.tree.map(jnp.add, total, term)
    if total is None:
        return y
    return jax.tree.map(lambda a, s: a + h[:, None] * s, y, total)


def rk_step(field, tableau: Tableau, t, h, y, f0):
    """One explicit Runge–Kutta step of every member: ``(y₁, e, f(t + c_last h, ·))``.

    ``f0 = f(t, y)``; for first-same-as-last tableaus the returned last stage is ``f(t + h, y₁)``.
    """
    ks = [f0]
    for c, a in zip(tableau.c, tableau.a_lower):
        ks.append(field(t + float(c) * h, _combine(y, h, a, ks)))
    y1 = _combine(y, h, tableau.b_sol, ks)
    error = _combine(jax.tree.map(jnp.zeros_like, y), h, tableau.b_error, ks)
    return y1, error, ks[-1]


def select(mask, new, old):
    """``new`` where the per-member ``mask`` (B,) holds, else ``old``, leaf by leaf."""
    return jax.tree.map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old
    )


def constant_step(field, tableau: Tableau, t, h, t1, carry, active=None):
    """One constant step from ``t`` to ``t1`` (``= t + h``, or the save time it lands on) of the
    carry ``(y, f)``, the state projected onto the constraints at ``t1``: the new carry.

    ``f`` is the last stage ``f(t, y)`` of the step before for first-same-as-last tableaus (else
    ``None``); ``active`` (B,) masks members whose interval has fewer steps (``None``: all step).
    """
    y, f = carry
    fsal = tableau.fsal
    f0 = f if fsal else field(t, y)
    y1, _, f_last = rk_step(field, tableau, t, h, y, f0)
    y1 = field.project(t1, y1)
    # First-same-as-last: the last stage is f at the unprojected end state, reused as the next
    # first stage exactly as diffrax's ProjectedSolver does (it differs from f at the projected
    # state by one step's drift).
    f_next = f_last if fsal else f
    if active is not None:
        y1 = select(active, y1, y)
        f_next = select(active, f_next, f) if fsal else f_next
    return y1, f_next
