r"""Lagrangians from particle positions: ``q ↦ x(q, t)`` in, ``L(q, q̇, t, args)`` out.

Instead of deriving the kinetic energy by hand, describe where the mass is:

    T = ½ Σ_k m_k |ẋ_k|² + Σ_b (½ m_b |ẋ_b|² + ½ I_b φ̇_b²),     ẋ = (∂x/∂q) q̇ + ∂x/∂t,

with ``ẋ`` computed by one forward-mode ``jax.jvp`` of the position map along ``(q̇, 1)`` in
``(q, t)`` (no Jacobian is formed). Point masses are given by a map ``positions(q, [t], [args])
-> (N, d)``; rigid planar bodies by :class:`RigidBody2D` (centre of mass and orientation angle,
mass and moment of inertia about the centre of mass). The potential is ``V(q, [t], [args])``
and/or uniform gravity ``g`` along the last Cartesian axis (``+`` up).

Every user function follows the library's calling convention (state positionally, ``t`` and
``args`` by keyword if declared); masses, inertias and ``g`` are numbers, arrays, or functions
of ``args`` (so they can be fitted with ``jax.grad``).

Coordinate maps (``polar``, ``cylindrical``, ``spherical``, ``planar_chain``) help write the
position maps::

    def bob(q, args):                                   # spherical pendulum, θ from the top
        return coordinates.spherical(args["l"], q[0], q[1])
    L = coordinates.lagrangian_from_positions(bob, masses=lambda a: a["m"],
                                              gravity=lambda a: a["g"])
    system = jl.System(L)
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp

from .conventions import UserFunction, wrap_configuration_function

__all__ = [
    "RigidBody2D",
    "cylindrical",
    "kinetic_energy_from_positions",
    "lagrangian_from_positions",
    "planar_chain",
    "polar",
    "spherical",
]


# ----------------------------------------------------------------------------- coordinate maps
def polar(r, theta):
    """Plane polar coordinates: ``(r cos θ, r sin θ)``, θ from the +x axis. Shape ``(..., 2)``."""
    r, theta = jnp.broadcast_arrays(jnp.asarray(r), jnp.asarray(theta))
    return jnp.stack([r * jnp.cos(theta), r * jnp.sin(theta)], axis=-1)


def cylindrical(rho, phi, z):
    """Cylindrical coordinates: ``(ρ cos φ, ρ sin φ, z)``. Shape ``(..., 3)``."""
    rho, phi, z = jnp.broadcast_arrays(jnp.asarray(rho), jnp.asarray(phi), jnp.asarray(z))
    return jnp.stack([rho * jnp.cos(phi), rho * jnp.sin(phi), z], axis=-1)


def spherical(r, theta, phi):
    """Spherical coordinates, θ the polar angle from +z, φ the azimuth from +x:
    ``(r sin θ cos φ, r sin θ sin φ, r cos θ)``. Shape ``(..., 3)``."""
    r, theta, phi = jnp.broadcast_arrays(jnp.asarray(r), jnp.asarray(theta), jnp.asarray(phi))
    s = jnp.sin(theta)
    return jnp.stack([r * s * jnp.cos(phi), r * s * jnp.sin(phi), r * jnp.cos(theta)], axis=-1)


def planar_chain(angles, lengths, origin=(0.0, 0.0)):
    """Joint positions of a planar chain of rods hanging from ``origin``, shape ``(N, 2)``.

    ``angles`` (N,) are absolute angles from the downward vertical (y up), ``lengths`` (N,) or a
    scalar: ``x_k = Σ_{i≤k} l_i sin θ_i``, ``y_k = −Σ_{i≤k} l_i cos θ_i``.
    """
    angles = jnp.asarray(angles)
    lengths = jnp.broadcast_to(jnp.asarray(lengths, angles.dtype), angles.shape)
    steps = jnp.stack([lengths * jnp.sin(angles), -lengths * jnp.cos(angles)], axis=-1)
    return jnp.asarray(origin, angles.dtype) + jnp.cumsum(steps, axis=0)


# ----------------------------------------------------------------------------- helpers
def _parameter(value, args, name):
    """A mass, inertia or ``g``: a number/array, or a function of ``args``."""
    if callable(value):
        value = value(args)
    value = jnp.asarray(value)
    if not jnp.issubdtype(value.dtype, jnp.inexact):
        value = value.astype(jnp.result_type(float))
    return value


def _velocity(fn: UserFunction, q, qd, t, args):
    """``(x, ẋ)`` with ``ẋ = (∂x/∂q) q̇ + ∂x/∂t``: one jvp along ``(q̇, 1)``."""
    t = jnp.asarray(t, dtype=q.dtype)
    return jax.jvp(lambda x, s: jnp.asarray(fn(x, t=s, args=args)), (q, t), (qd, jnp.ones_like(t)))


def _as_points(x, role):
    if x.ndim == 1:
        return x[None, :]
    if x.ndim != 2:
        raise ValueError(
            f"The {role} must return an array of shape (N, d) (N points in d dimensions) or (d,) "
            f"for a single point; it returned shape {x.shape}."
        )
    return x


class RigidBody2D(eqx.Module):
    r"""A rigid body moving in a vertical plane (x horizontal, y up).

    - ``pose``: ``pose(q, [t], [args]) -> (3,)``: ``(x_c, y_c, φ)``, the centre of mass and the
      orientation angle of the body.
    - ``mass``: total mass ``m``; ``inertia``: moment of inertia ``I`` about the centre of mass
      (numbers, arrays, or functions of ``args``). Common values: a uniform rod of length ``l``
      ``I = m l²/12``, a uniform disk of radius ``R`` ``I = m R²/2``, a ring ``I = m R²``.

    Kinetic energy ``T = ½ m (ẋ_c² + ẏ_c²) + ½ I φ̇²`` (König's theorem); height ``y_c``.
    """

    pose: UserFunction
    mass: Any
    inertia: Any

    def __init__(self, pose: Callable, mass, inertia):
        self.pose = wrap_configuration_function(pose, "rigid body pose function")
        self.mass = mass
        self.inertia = inertia

    def kinetic_energy(self, q, qd, t, args):
        x, v = _velocity(self.pose, q, qd, t, args)
        if x.shape != (3,):
            raise ValueError(
                "A RigidBody2D pose function must return (x_c, y_c, angle), shape (3,); it "
                f"returned shape {x.shape}."
            )
        m = _parameter(self.mass, args, "mass")
        inertia = _parameter(self.inertia, args, "inertia")
        return 0.5 * m * (v[0] ** 2 + v[1] ** 2) + 0.5 * inertia * v[2] ** 2

    def height(self, q, t, args):
        """``m y_c``: the body's mass times the height of its centre of mass."""
        x = jnp.asarray(self.pose(q, t=t, args=args))
        return _parameter(self.mass, args, "mass") * x[1]


def _check_masses(masses, n_points):
    if masses.ndim == 0:
        return jnp.broadcast_to(masses, (n_points,))
    if masses.shape != (n_points,):
        raise ValueError(
            f"masses must be a scalar or have one entry per point, shape ({n_points},); got "
            f"shape {masses.shape}."
        )
    return masses


def kinetic_energy_from_positions(
    positions: Callable | None, masses=1.0, *, bodies: Sequence[RigidBody2D] = ()
) -> Callable:
    r"""``T(q, q̇, t, args) = ½ Σ_k m_k |ẋ_k|² + Σ_b T_b`` for point masses and planar bodies.

    ``positions(q, [t], [args]) -> (N, d)`` (or ``(d,)``); ``masses`` a scalar, an ``(N,)``
    array, or a function of ``args``. ``ẋ`` comes from one ``jax.jvp`` along ``(q̇, 1)``, so
    time-dependent maps (a rotating wire, a driven support) give the full ``∂x/∂t`` terms.
    """
    fn = wrap_configuration_function(positions, "position map") if positions is not None else None
    bodies = tuple(bodies)
    for b in bodies:
        if not isinstance(b, RigidBody2D):
            raise TypeError(f"bodies must be RigidBody2D instances; got {type(b).__name__}.")
    if fn is None and not bodies:
        raise ValueError("Give a position map, rigid bodies, or both.")

    def kinetic(q, qd, t=0.0, args=None):
        total = jnp.zeros((), q.dtype)
        if fn is not None:
            _, v = _velocity(fn, q, qd, t, args)
            v = _as_points(v, "position map")
            m = _check_masses(_parameter(masses, args, "masses"), v.shape[0])
            total = total + 0.5 * jnp.sum(m * jnp.sum(v**2, axis=-1))
        for b in bodies:
            total = total + b.kinetic_energy(q, qd, t, args)
        return total

    return kinetic


def lagrangian_from_positions(
    positions: Callable | None,
    masses=1.0,
    potential: Callable | None = None,
    *,
    gravity=None,
    bodies: Sequence[RigidBody2D] = (),
) -> Callable:
    r"""Build ``L(q, q̇, t, args) = T − V`` from where the mass is.

    **Arguments:**

    - ``positions``: ``x(q, [t], [args]) -> (N, d)`` Cartesian positions of N point masses
      (``(d,)`` for one), or ``None`` if only ``bodies`` carry mass.
    - ``masses``: scalar, ``(N,)`` array, or a function ``masses(args)``.
    - ``potential``: optional ``V(q, [t], [args]) -> scalar`` (springs, fields, ...).
    - ``gravity``: optional ``g`` (number or function of ``args``): uniform gravity along the
      last Cartesian axis, which points up, ``V_g = g (Σ_k m_k x_k[-1] + Σ_b m_b y_b)``.
    - ``bodies``: :class:`RigidBody2D` instances (planar rigid bodies, y up).

    ``T = ½ Σ m |ẋ|² (+ bodies)``, ``ẋ = (∂x/∂q) q̇ + ∂x/∂t`` by forward-mode autodiff. The
    returned function declares ``t`` and ``args``; pass it to :class:`jaxlag.System`.
    """
    kinetic_energy_from_positions(positions, masses, bodies=bodies)  # validates the pieces
    fn = wrap_configuration_function(positions, "position map") if positions is not None else None
    v_fn = wrap_configuration_function(potential, "potential") if potential is not None else None
    bodies = tuple(bodies)

    def lagrangian(q, qd, t=0.0, args=None):
        value = jnp.zeros((), q.dtype)
        height = jnp.zeros((), q.dtype)
        if fn is not None:
            x, v = _velocity(fn, q, qd, t, args)  # one jvp gives positions and velocities
            x, v = _as_points(x, "position map"), _as_points(v, "position map")
            m = _check_masses(_parameter(masses, args, "masses"), x.shape[0])
            value = value + 0.5 * jnp.sum(m * jnp.sum(v**2, axis=-1))
            height = height + jnp.sum(m * x[:, -1])
        for b in bodies:
            value = value + b.kinetic_energy(q, qd, t, args)
            if gravity is not None:
                height = height + b.height(q, t, args)
        if v_fn is not None:
            pot = jnp.asarray(v_fn(q, t=t, args=args))
            if pot.shape != ():
                raise ValueError(f"The potential must return a scalar; it returned shape {pot.shape}.")
            value = value - pot
        if gravity is not None:
            value = value - _parameter(gravity, args, "gravity") * height
        return value

    return lagrangian
