r"""Conservation laws: momenta, ignorable coordinates, Noether charges, the energy function.

Sign convention of the library: ``d/dt ∂L/∂q̇ − ∂L/∂q = Qᶜ + Qⁿᶜ`` with ``Qᶜ = Jᵀλ + Aᵀμ`` and
``Qⁿᶜ = −∂R/∂q̇ + Q``. Hence along any motion

* ``ṗ_i = ∂L/∂q_i + Qᶜ_i + Qⁿᶜ_i``: the momentum ``p_i = ∂L/∂q̇_i`` of an **ignorable (cyclic)**
  coordinate is conserved when ``L`` does not depend on ``q_i`` and neither the constraints
  (column ``i`` of ``J`` and ``A``) nor the non-conservative forces act on it;
* for a vector field ``ξ(q, t)`` on configuration space (an infinitesimal transformation
  ``q → q + ε ξ``) the **Noether charge** ``Q_ξ = p·ξ`` changes at the rate

      dQ_ξ/dt = δ_ξL + (Qᶜ + Qⁿᶜ)·ξ,     δ_ξL = ∂L/∂q·ξ + ∂L/∂q̇·ξ̇,   ξ̇ = (∂ξ/∂q) q̇ + ∂ξ/∂t,

  so ``Q_ξ`` is conserved when ``ξ`` is a symmetry of ``L`` (``δ_ξL = 0``) compatible with the
  constraints and forces (`noether_rate` evaluates the right-hand side exactly);
* the **energy function** ``h = q̇·p − L`` has ``dh/dt = −∂L/∂t + q̇·(Qᶜ + Qⁿᶜ)``.

`conservation_report` measures how well each of these is conserved along a
[`Trajectory`][jaxlag.Trajectory].
"""

from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .. import _compile as compilation
from .._conventions import as_array_leaves, wrap_configuration_function
from .._custom_types import Args, Coordinates, RealScalarLike, Scalar, Vector, Velocities
from .._mechanics import kkt as _kkt
from .._mechanics import lagrangian as _mechanics
from .._mechanics.constraints import constraint_rows
from .._mechanics.lagrangian import as_time
from .._system import System
from .._trajectory import Trajectory

__all__ = [
    "ConservedQuantity",
    "conservation_report",
    "energy",
    "format_report",
    "ignorable_coordinates",
    "momenta",
    "noether_charge",
    "noether_rate",
    "rotation_generator",
    "translation_generator",
]


def momenta(
    system: System, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
) -> Vector:
    """Generalized momenta ``p = ∂L/∂q̇`` (n,)."""
    return _momenta(system, *_state(q, qd, t, args))


def energy(
    system: System, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
) -> Scalar:
    """Energy function ``h = q̇·∂L/∂q̇ − L`` (the Jacobi integral)."""
    return _energy(system, *_state(q, qd, t, args))


_momenta = compilation.filter_jit(_mechanics.momenta)
_energy = compilation.filter_jit(_mechanics.energy)


# ----------------------------------------------------------------------------- generators
#: A small vector (a direction, an axis, a point) of the spatial dimension ``d``.
SpatialVector = Float[ArrayLike, " d"] | Sequence[float]


class _Translation(eqx.Module):
    direction: Float[Array, " d"]
    num_points: int | None = eqx.field(static=True)

    def __call__(self, q):
        d = self.direction.shape[0]
        if q.shape[0] % d or (self.num_points is not None and q.shape[0] != self.num_points * d):
            raise ValueError(
                f"translation_generator: q of length {q.shape[0]} is not a layout of "
                f"{self.num_points or 'N'} points in {d} dimensions."
            )
        return jnp.tile(self.direction.astype(q.dtype), q.shape[0] // d)


class _Rotation(eqx.Module):
    axis: Float[Array, "3"] | None  # None for planar rotation
    origin: Float[Array, " d"] | None
    num_points: int | None = eqx.field(static=True)

    def __call__(self, q):
        d = 2 if self.axis is None else 3
        if q.shape[0] % d or (self.num_points is not None and q.shape[0] != self.num_points * d):
            raise ValueError(
                f"rotation_generator: q of length {q.shape[0]} is not a layout of "
                f"{self.num_points or 'N'} points in {d} dimensions."
            )
        x = q.reshape(-1, d)
        if self.origin is not None:
            x = x - self.origin.astype(q.dtype)
        if self.axis is None:  # d == 2
            return jnp.stack([-x[:, 1], x[:, 0]], axis=-1).reshape(-1)
        return jnp.cross(jnp.broadcast_to(self.axis.astype(q.dtype), x.shape), x).reshape(-1)


def translation_generator(direction: SpatialVector, num_points: int | None = None) -> Callable:
    """``ξ(q)`` translating every point of a Cartesian layout ``q = (x₁, …, x_N)`` by ``direction``.

    ``direction`` has the spatial dimension d; ``q`` must have ``N·d`` entries (``num_points``
    optional, checked if given). Its charge is the total linear momentum along ``direction``.
    The generator is an equinox Module: its direction is data, not part of a compiled program.
    """
    direction = jnp.asarray(direction, dtype=jnp.result_type(float))
    if direction.ndim != 1:
        raise ValueError(f"direction must be a 1-D vector; got shape {direction.shape}.")
    return _Translation(direction, num_points)


def rotation_generator(
    axis: SpatialVector | None = None, num_points: int | None = None, origin: SpatialVector | None = None
) -> Callable:
    """``ξ(q)`` rotating every point of a Cartesian layout about ``axis`` through ``origin``.

    In 3-D (``axis`` a 3-vector) ``ξ_k = axis × (x_k − origin)``; in 2-D (``axis=None``) the
    in-plane rotation ``ξ_k = (−(y_k − y₀), x_k − x₀)``. Its charge is the angular momentum
    about ``axis`` (times ``|axis|``).
    """
    if axis is not None:
        axis = jnp.asarray(axis, dtype=jnp.result_type(float))
        if axis.shape != (3,):
            raise ValueError(
                f"axis must be a 3-vector (or None for planar rotation); got shape {axis.shape}."
            )
    if origin is not None:
        origin = jnp.asarray(origin, dtype=jnp.result_type(float))
    return _Rotation(axis, origin, num_points)


def _state(q, qd, t, args):
    q = jnp.asarray(q)
    if not jnp.issubdtype(q.dtype, jnp.floating):
        q = q.astype(jnp.result_type(float))
    return q, jnp.asarray(qd, q.dtype), as_time(t, q), as_array_leaves(args, q.dtype)


def _generator(generator, q, t, args):
    fn = wrap_configuration_function(generator, "symmetry generator")
    t = as_time(t, q)
    xi = jnp.asarray(fn(q, t=t, args=args), dtype=q.dtype)
    if xi.shape != q.shape:
        raise ValueError(
            f"A symmetry generator ξ(q, [t], [args]) must return a vector like q, shape "
            f"{q.shape}; it returned shape {xi.shape}."
        )
    return fn, xi


def noether_charge(
    system: System,
    generator: Callable,
    q: Coordinates,
    qd: Velocities,
    t: RealScalarLike = 0.0,
    args: Args = None,
) -> Scalar:
    r"""Noether charge ``Q_ξ = p·ξ(q, t) = Σ_i ∂L/∂q̇_i ξ_i`` for the generator ``ξ(q, [t], [args])``.

    For ``ξ = e_i`` (shifting one coordinate) it is ``p_i``; for a rotation of a Cartesian
    layout (`rotation_generator`) the angular momentum. Conserved when ``ξ`` is a symmetry
    (see `noether_rate`).
    """
    return _noether_charge(system, generator, *_state(q, qd, t, args))


@compilation.filter_jit
def _noether_charge(system, generator, q, qd, t, args):
    _, xi = _generator(generator, q, t, args)
    return jnp.dot(_mechanics.momenta(system, q, qd, t, args), xi)


def noether_rate(
    system: System,
    generator: Callable,
    q: Coordinates,
    qd: Velocities,
    t: RealScalarLike = 0.0,
    args: Args = None,
) -> Scalar:
    r"""``dQ_ξ/dt = δ_ξL + (Qᶜ + Qⁿᶜ)·ξ`` at a state: zero for a symmetry of the whole system.

    ``δ_ξL = ∂L/∂q·ξ + ∂L/∂q̇·ξ̇`` (one ``jvp`` of ``L`` along ``(ξ, ξ̇)``) is the change of the
    Lagrangian under the transformation; the second term is the power of the constraint and
    non-conservative forces along ``ξ``.
    """
    return _noether_rate(system, generator, *_state(q, qd, t, args))


@compilation.filter_jit
def _noether_rate(system, generator, q, qd, t, args):
    fn, xi = _generator(generator, q, t, args)
    _, xi_dot = jax.jvp(
        lambda x, s: jnp.asarray(fn(x, t=s, args=args), q.dtype), (q, t), (qd, jnp.ones_like(t))
    )
    _, delta_l = jax.jvp(lambda x, v: system.lagrangian(x, v, t=t, args=args), (q, qd), (xi, xi_dot))
    forces = _mechanics.nonconservative_forces(system, q, qd, t, args)
    if system.is_constrained:
        _, lam, mu = _kkt.accelerations_and_multipliers(system, q, qd, t, args)
        rows, _ = constraint_rows(system, q, qd, t, args)
        forces = forces + rows.T @ jnp.concatenate([lam, mu])
    return delta_l + jnp.dot(forces, xi)


# ----------------------------------------------------------------------------- ignorable
def ignorable_coordinates(
    system: System,
    q: Coordinates,
    qd: Velocities,
    t: RealScalarLike = 0.0,
    args: Args = None,
    *,
    num_samples: int = 8,
    spread: float = 0.5,
    key: PRNGKeyArray | None = None,
    tolerance: float = 1e-10,
) -> tuple[int, ...]:
    r"""Indices of the ignorable (cyclic) coordinates whose momenta are conserved.

    Coordinate ``i`` is reported when, at the given state and at ``num_samples`` random states
    around it (Gaussian, standard deviation ``spread`` in every entry of ``q`` and ``q̇``):
    ``∂L/∂q_i = 0``, column ``i`` of the constraint rows ``[J; A]`` is zero, and the
    non-conservative force ``Qⁿᶜ_i = −∂R/∂q̇_i + Q_i`` is zero, each to ``tolerance`` relative to
    the size of the corresponding quantity over all coordinates. A numerical test (it samples,
    it does not prove), run eagerly: returns a tuple of Python ints.
    """
    q = jnp.asarray(q, dtype=jnp.result_type(float))
    qd = jnp.asarray(qd, dtype=q.dtype)
    system.check(q, qd, t, args)
    key = jax.random.PRNGKey(0) if key is None else key
    kq, kv = jax.random.split(key)
    dq = spread * jax.random.normal(kq, (num_samples,) + q.shape, q.dtype)
    dv = spread * jax.random.normal(kv, (num_samples,) + q.shape, q.dtype)
    qs = jnp.concatenate([q[None], q[None] + dq])
    qds = jnp.concatenate([qd[None], qd[None] + dv])

    @compilation.jit
    def measures(x, v):
        tt = as_time(t, x)
        dl = jax.grad(lambda y: system.lagrangian(y, v, t=tt, args=args))(x)
        rows, _ = constraint_rows(system, x, v, tt, args)
        qnc = _mechanics.nonconservative_forces(system, x, v, tt, args)
        return jnp.abs(dl), jnp.max(jnp.abs(rows), axis=0, initial=0.0), jnp.abs(qnc)

    dl, cols, qnc = (np.asarray(a) for a in jax.vmap(measures)(qs, qds))
    cyclic = np.ones(q.shape[0], bool)
    for values in (dl, cols, qnc):
        scale = np.max(values) if values.size else 0.0
        cyclic &= np.all(values <= tolerance * max(scale, 1.0), axis=0)
    return tuple(int(i) for i in np.flatnonzero(cyclic))


# ----------------------------------------------------------------------------- report
class ConservedQuantity(NamedTuple):
    """One line of a `conservation_report`.

    ``values`` (T,) along the trajectory; ``initial`` its value at the first saved time;
    ``max_deviation = max_t |Q(t) − Q(t₀)|``; ``relative_deviation`` the same divided by
    ``max_t |Q(t)|`` (``inf`` if the quantity is identically zero and still deviates, 0 if both
    vanish).
    """

    values: Float[Array, " times"]
    initial: Scalar
    max_deviation: Scalar
    relative_deviation: Scalar


def _summarize(values):
    values = jnp.asarray(values)
    initial = values[0]
    deviation = jnp.max(jnp.abs(values - initial))
    size = jnp.max(jnp.abs(values))
    relative = jnp.where(
        size > 0, deviation / jnp.where(size > 0, size, 1.0), jnp.where(deviation > 0, jnp.inf, 0.0)
    )
    return ConservedQuantity(values, initial, deviation, relative)


@compilation.filter_jit
def _charges(system, generator, q, qd, t, args):
    return jax.vmap(lambda x, v, s: _noether_charge(system, generator, x, v, s, args))(q, qd, t)


def conservation_report(
    trajectory: Trajectory,
    generators: Mapping[str, Callable] | None = None,
    *,
    ignorable: Sequence[int] | None = None,
) -> dict[str, ConservedQuantity]:
    r"""How well the conserved quantities are conserved along ``trajectory``.

    Reports ``"energy"`` (the energy function ``h``), the momentum ``"p[i]"`` of each ignorable
    coordinate (detected with `ignorable_coordinates` at the first saved state unless
    ``ignorable`` gives the indices), and one Noether charge per entry of ``generators``
    (``{name: ξ}``). Every entry is a `ConservedQuantity`; `format_report` prints a
    table. Whether a quantity *should* be conserved is the physics' business: energy is not
    when ``L`` or the constraints depend on time or forces act.
    """
    if trajectory.q.ndim != 2:
        raise ValueError(
            "conservation_report takes one trajectory (q of shape (T, n)); for a batch from "
            "jax.vmap, index it first."
        )
    system, args = trajectory.system, trajectory.args
    report: dict[str, ConservedQuantity] = {"energy": _summarize(trajectory.energy)}
    if ignorable is None:
        ignorable = ignorable_coordinates(system, trajectory.q[0], trajectory.qd[0], trajectory.t[0], args)
    p = trajectory.momenta
    for i in ignorable:
        report[f"p[{int(i)}]"] = _summarize(p[:, int(i)])
    for name, generator in (generators or {}).items():
        values = _charges(system, generator, trajectory.q, trajectory.qd, trajectory.t, args)
        report[str(name)] = _summarize(values)
    return report


def format_report(report: Mapping[str, ConservedQuantity]) -> str:
    """A plain-text table of a `conservation_report`."""
    lines = [f"{'quantity':<16} {'initial':>16} {'max |Δ|':>12} {'relative':>12}"]
    for name, entry in report.items():
        lines.append(
            f"{name:<16} {float(entry.initial):>16.9g} {float(entry.max_deviation):>12.3e} "
            f"{float(entry.relative_deviation):>12.3e}"
        )
    return "\n".join(lines)
