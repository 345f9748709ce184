r"""Lagrangians from particle positions: ``q ↦ x(q, t)`` in, ``L(q, q̇, t, args)`` out.

Instead of deriving the kinetic energy by hand, describe where the mass is:

    T = ½ Σ_k m_k |ẋ_k|² + Σ_b (½ m_b |ẋ_b|² + ½ I_b φ̇_b²),     ẋ = (∂x/∂q) q̇ + ∂x/∂t,

with ``ẋ`` computed by one forward-mode ``jax.jvp`` of the position map along ``(q̇, 1)`` in
``(q, t)`` (no Jacobian is formed). Point masses are given by a map ``positions(q, [t], [args])
-> (N, d)``; rigid planar bodies by :class:`RigidBody2D` (centre of mass and orientation angle,
mass and moment of inertia about the centre of mass); rigid bodies in space by
:class:`RigidBody3D` (centre of mass and rotation matrix, mass and inertia tensor, kinetic energy
``½ m |ẋ_c|² + ½ ωᵀIω``). The potential is ``V(q, [t], [args])``
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

from typing import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._conventions import UserFunction, wrap_configuration_function
from ._custom_types import Args, Coordinates, Parameter, RealScalarLike, Scalar, Vector, Velocities
from .rotations import unskew

__all__ = [
    "RigidBody2D",
    "RigidBody3D",
    "cylindrical",
    "kinetic_energy_from_positions",
    "lagrangian_from_positions",
    "planar_chain",
    "polar",
    "spherical",
]


# ----------------------------------------------------------------------------- coordinate maps
def polar(r: Float[ArrayLike, "*#shape"], theta: Float[ArrayLike, "*#shape"]) -> Float[Array, "*shape 2"]:
    """Plane polar coordinates: ``(r cos θ, r sin θ)``, θ from the +x axis. Shape ``(..., 2)``."""
    r, theta = jnp.broadcast_arrays(jnp.asarray(r), jnp.asarray(theta))
    return jnp.stack([r * jnp.cos(theta), r * jnp.sin(theta)], axis=-1)


def cylindrical(
    rho: Float[ArrayLike, "*#shape"], phi: Float[ArrayLike, "*#shape"], z: Float[ArrayLike, "*#shape"]
) -> Float[Array, "*shape 3"]:
    """Cylindrical coordinates: ``(ρ cos φ, ρ sin φ, z)``. Shape ``(..., 3)``."""
    rho, phi, z = jnp.broadcast_arrays(jnp.asarray(rho), jnp.asarray(phi), jnp.asarray(z))
    return jnp.stack([rho * jnp.cos(phi), rho * jnp.sin(phi), z], axis=-1)


def spherical(
    r: Float[ArrayLike, "*#shape"], theta: Float[ArrayLike, "*#shape"], phi: Float[ArrayLike, "*#shape"]
) -> Float[Array, "*shape 3"]:
    """Spherical coordinates, θ the polar angle from +z, φ the azimuth from +x:
    ``(r sin θ cos φ, r sin θ sin φ, r cos θ)``. Shape ``(..., 3)``."""
    r, theta, phi = jnp.broadcast_arrays(jnp.asarray(r), jnp.asarray(theta), jnp.asarray(phi))
    s = jnp.sin(theta)
    return jnp.stack([r * s * jnp.cos(phi), r * s * jnp.sin(phi), r * jnp.cos(theta)], axis=-1)


def planar_chain(
    angles: Float[ArrayLike, " N"],
    lengths: Float[ArrayLike, "#N"] | RealScalarLike,
    origin: Float[ArrayLike, "2"] | tuple[float, float] = (0.0, 0.0),
) -> Float[Array, "N 2"]:
    """Joint positions of a planar chain of rods hanging from ``origin``, shape ``(N, 2)``.

    ``angles`` (N,) are absolute angles from the downward vertical (y up), ``lengths`` (N,) or a
    scalar: ``x_k = Σ_{i≤k} l_i sin θ_i``, ``y_k = −Σ_{i≤k} l_i cos θ_i``.
    """
    angles = jnp.asarray(angles)
    lengths = jnp.broadcast_to(jnp.asarray(lengths, angles.dtype), angles.shape)
    steps = jnp.stack([lengths * jnp.sin(angles), -lengths * jnp.cos(angles)], axis=-1)
    joints = jnp.cumsum(steps, axis=0)
    return jnp.broadcast_to(jnp.asarray(origin, angles.dtype), joints.shape) + joints


# ----------------------------------------------------------------------------- helpers
def parameter_value(value, args, name):
    """A mass, inertia or ``g``: a number/array, or a function of ``args``."""
    if callable(value):
        value = value(args)
    value = jnp.asarray(value)
    if not jnp.issubdtype(value.dtype, jnp.inexact):
        value = value.astype(jnp.result_type(float))
    return value


def _velocity(fn: UserFunction | Callable, q, qd, t, args):
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
    mass: Parameter
    inertia: Parameter

    def __init__(self, pose: Callable, mass: Parameter, inertia: Parameter):
        self.pose = wrap_configuration_function(pose, "rigid body pose function")
        self.mass = mass
        self.inertia = inertia

    def kinetic_energy(self, q: Vector, qd: Vector, t: RealScalarLike, args: Args) -> Scalar:
        x, v = _velocity(self.pose, q, qd, t, args)
        if x.shape != (3,):
            raise ValueError(
                "A RigidBody2D pose function must return (x_c, y_c, angle), shape (3,); it "
                f"returned shape {x.shape}."
            )
        m = parameter_value(self.mass, args, "mass")
        inertia = parameter_value(self.inertia, args, "inertia")
        return 0.5 * m * (v[0] ** 2 + v[1] ** 2) + 0.5 * inertia * v[2] ** 2

    def height(self, q: Coordinates, t: RealScalarLike, args: Args) -> Scalar:
        """``m y_c``: the body's mass times the height of its centre of mass."""
        x = jnp.asarray(self.pose(q, t=t, args=args))
        return parameter_value(self.mass, args, "mass") * x[1]

    def angular_velocity(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Scalar:
        """``φ̇`` (a scalar: the angular velocity about the out-of-plane axis)."""
        return _velocity(self.pose, jnp.asarray(q), jnp.asarray(qd), t, args)[1][2]

    def point_position(
        self, q: Coordinates, point: Float[ArrayLike, "2"], t: RealScalarLike = 0.0, args: Args = None
    ) -> Float[Array, "2"]:
        """World position ``x_c + R(φ) r`` of the body point with body coordinates ``r`` (2,)."""
        x = jnp.asarray(self.pose(q, t=t, args=args))
        r = jnp.asarray(point, x.dtype)
        c, s = jnp.cos(x[2]), jnp.sin(x[2])
        return x[:2] + jnp.stack([c * r[0] - s * r[1], s * r[0] + c * r[1]])

    def point_velocity(
        self,
        q: Coordinates,
        qd: Velocities,
        point: Float[ArrayLike, "2"],
        t: RealScalarLike = 0.0,
        args: Args = None,
    ) -> Float[Array, "2"]:
        """``ẋ_c + φ̇ ẑ × (R r)``: velocity of the body point with body coordinates ``r``."""
        q, qd = jnp.asarray(q), jnp.asarray(qd)
        return _velocity(lambda x, t, args: self.point_position(x, point, t, args), q, qd, t, args)[1]


def _inertia_tensor(inertia):
    """Principal moments (3,) or a symmetric tensor (3, 3), as a (3, 3) tensor."""
    if inertia.shape == (3,):
        return jnp.diag(inertia)
    if inertia.shape == (3, 3):
        return inertia
    raise ValueError(
        "A RigidBody3D inertia must be the principal moments, shape (3,), or the inertia tensor "
        f"in body axes about the centre of mass, shape (3, 3); got shape {inertia.shape}."
    )


class RigidBody3D(eqx.Module):
    r"""A rigid body moving in space (z up for gravity).

    - ``pose``: ``pose(q, [t], [args]) -> (x_c, R)``: the centre of mass (3,) and the rotation
      matrix (3, 3) taking body components to world components. Any parameterization of ``R``
      works: Euler angles (:func:`jaxlag.rotations.euler_matrix`), a quaternion
      (:func:`jaxlag.rotations.quaternion_matrix`, with ``|q|² = 1`` as a holonomic constraint),
      the nine entries of ``R`` themselves (with ``RᵀR = I`` as constraints), or a product of
      joint rotations along a chain of bodies.
    - ``mass``: ``m``; ``inertia``: principal moments ``(I₁, I₂, I₃)`` or the inertia tensor
      ``I`` (3, 3), in body axes about the centre of mass (numbers, arrays or functions of
      ``args``).

    Kinetic energy (König): ``T = ½ m |ẋ_c|² + ½ ωᵀ I ω`` with ``[ω]ₓ = RᵀṘ`` (body axes), ``ẋ_c``
    and ``Ṙ`` from one ``jax.jvp`` of the pose along ``(q̇, 1)``. It is evaluated as
    ``½ tr(Ṙ E Ṙᵀ)`` with the body's second-moment tensor ``E = ∫ r rᵀ dm = ½ tr(I) 𝟙 − I``:
    identical to ``½ ωᵀIω`` whenever ``R`` is a rotation, and, when ``R`` is off the rotation
    group (a quaternion off the unit sphere, nine free matrix entries), the kinetic energy of the
    body's mass points at ``x_c + R r``, so the mass matrix stays positive definite in every
    direction and the constraints keep the motion on the group. Gravity acts on ``x_c[2]``.
    """

    pose: UserFunction
    mass: Parameter
    inertia: Parameter  # principal moments (3,) or the tensor (3, 3), or a function of args

    def __init__(self, pose: Callable, mass: Parameter, inertia: Parameter):
        self.pose = wrap_configuration_function(pose, "rigid body pose function")
        self.mass = mass
        self.inertia = inertia

    # ----------------------------------------------------------------- kinematics
    def _pose(self, q, t, args):
        out = self.pose(q, t=t, args=args)
        if not isinstance(out, (tuple, list)) or len(out) != 2:
            raise ValueError(
                "A RigidBody3D pose function must return a pair (x_c, R): the centre of mass, "
                f"shape (3,), and the rotation matrix body → world, shape (3, 3); it returned {out!r}."
            )
        x, rotation = jnp.asarray(out[0]), jnp.asarray(out[1])
        if x.shape != (3,) or rotation.shape != (3, 3):
            raise ValueError(
                "A RigidBody3D pose function must return (x_c, R) with shapes (3,) and (3, 3); it "
                f"returned shapes {x.shape} and {rotation.shape}."
            )
        dtype = jnp.result_type(x.dtype, rotation.dtype, float)
        return x.astype(dtype), rotation.astype(dtype)

    def pose_and_rates(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> tuple[tuple[Float[Array, "3"], Float[Array, "3 3"]], tuple[Float[Array, "3"], Float[Array, "3 3"]]]:
        """``((x_c, R), (ẋ_c, Ṙ))``: one ``jax.jvp`` of the pose along ``(q̇, 1)``."""
        q, qd = jnp.asarray(q), jnp.asarray(qd)
        t = jnp.asarray(t, dtype=q.dtype)
        return jax.jvp(lambda x, s: self._pose(x, s, args), (q, t), (qd, jnp.ones_like(t)))

    def position(
        self, q: Coordinates, t: RealScalarLike = 0.0, args: Args = None
    ) -> tuple[Float[Array, "3"], Float[Array, "3 3"]]:
        """``(x_c, R)``: centre of mass and rotation matrix."""
        return self._pose(jnp.asarray(q), t, args)

    def angular_velocity(
        self,
        q: Coordinates,
        qd: Velocities,
        t: RealScalarLike = 0.0,
        args: Args = None,
        *,
        frame: str = "body",
    ) -> Float[Array, "3"]:
        """``ω`` with ``[ω]ₓ = RᵀṘ`` (``frame="body"``) or ``Ṙ Rᵀ`` (``frame="world"``)."""
        if frame not in ("body", "world"):
            raise ValueError(f"frame must be 'body' or 'world'; got {frame!r}.")
        (_, rotation), (_, rate) = self.pose_and_rates(q, qd, t, args)
        return unskew(rotation.T @ rate) if frame == "body" else unskew(rate @ rotation.T)

    def point_position(
        self, q: Coordinates, point: Float[ArrayLike, "3"], t: RealScalarLike = 0.0, args: Args = None
    ) -> Float[Array, "3"]:
        """World position ``x_c + R r`` of the body point with body coordinates ``r`` (3,)."""
        x, rotation = self._pose(jnp.asarray(q), t, args)
        return x + rotation @ jnp.asarray(point, x.dtype)

    def point_velocity(
        self,
        q: Coordinates,
        qd: Velocities,
        point: Float[ArrayLike, "3"],
        t: RealScalarLike = 0.0,
        args: Args = None,
    ) -> Float[Array, "3"]:
        """``ẋ_c + Ṙ r = v + ω × (R r)`` (world axes): velocity of the body point ``r``."""
        (_, _), (v, rate) = self.pose_and_rates(q, qd, t, args)
        return v + rate @ jnp.asarray(point, v.dtype)

    # ----------------------------------------------------------------- dynamics
    def inertia_tensor(self, args: Args = None) -> Float[Array, "3 3"]:
        """The inertia tensor ``I`` (3, 3) in body axes about the centre of mass."""
        return _inertia_tensor(parameter_value(self.inertia, args, "inertia"))

    def kinetic_energy(self, q: Coordinates, qd: Velocities, t: RealScalarLike, args: Args) -> Scalar:
        (_, _), (v, rate) = self.pose_and_rates(q, qd, t, args)
        m = parameter_value(self.mass, args, "mass")
        inertia = self.inertia_tensor(args)
        second_moment = 0.5 * jnp.trace(inertia) * jnp.eye(3, dtype=inertia.dtype) - inertia
        return 0.5 * m * (v @ v) + 0.5 * jnp.sum((rate @ second_moment) * rate)

    def height(self, q: Coordinates, t: RealScalarLike, args: Args) -> Scalar:
        """``m z_c``: the body's mass times the height of its centre of mass."""
        x, _ = self._pose(q, t, args)
        return parameter_value(self.mass, args, "mass") * x[2]

    def momentum(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Float[Array, "3"]:
        """Linear momentum ``m ẋ_c`` (world axes)."""
        (_, _), (v, _) = self.pose_and_rates(q, qd, t, args)
        return parameter_value(self.mass, args, "mass") * v

    def angular_momentum(
        self,
        q: Coordinates,
        qd: Velocities,
        t: RealScalarLike = 0.0,
        args: Args = None,
        *,
        about: Float[ArrayLike, "3"] | None = None,
    ) -> Float[Array, "3"]:
        """Angular momentum in world axes, ``R I ω_body`` about the centre of mass, plus
        ``(x_c − a) × m ẋ_c`` about a fixed point ``a`` if ``about`` is given."""
        (x, rotation), (v, rate) = self.pose_and_rates(q, qd, t, args)
        spin = rotation @ (self.inertia_tensor(args) @ unskew(rotation.T @ rate))
        if about is None:
            return spin
        m = parameter_value(self.mass, args, "mass")
        return spin + jnp.cross(x - jnp.asarray(about, x.dtype), m * v)


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
    positions: Callable | None,
    masses: Parameter = 1.0,
    *,
    bodies: Sequence[RigidBody2D | RigidBody3D] = (),
) -> Callable:
    r"""``T(q, q̇, t, args) = ½ Σ_k m_k |ẋ_k|² + Σ_b T_b`` for point masses and rigid bodies.

    ``positions(q, [t], [args]) -> (N, d)`` (or ``(d,)``); ``masses`` a scalar, an ``(N,)``
    array, or a function of ``args``. ``ẋ`` comes from one ``jax.jvp`` along ``(q̇, 1)``, so
    time-dependent maps (a rotating wire, a driven support) give the full ``∂x/∂t`` terms.
    """
    fn = wrap_configuration_function(positions, "position map") if positions is not None else None
    bodies = tuple(bodies)
    for b in bodies:
        if not isinstance(b, (RigidBody2D, RigidBody3D)):
            raise TypeError(f"bodies must be RigidBody2D or RigidBody3D instances; got {type(b).__name__}.")
    if fn is None and not bodies:
        raise ValueError("Give a position map, rigid bodies, or both.")

    def kinetic(q, qd, t=0.0, args=None):
        total = jnp.zeros((), q.dtype)
        if fn is not None:
            _, v = _velocity(fn, q, qd, t, args)
            v = _as_points(v, "position map")
            m = _check_masses(parameter_value(masses, args, "masses"), v.shape[0])
            total = total + 0.5 * jnp.sum(m * jnp.sum(v**2, axis=-1))
        for b in bodies:
            total = total + b.kinetic_energy(q, qd, t, args)
        return total

    return kinetic


def lagrangian_from_positions(
    positions: Callable | None,
    masses: Parameter = 1.0,
    potential: Callable | None = None,
    *,
    gravity: Parameter | None = None,
    bodies: Sequence[RigidBody2D | RigidBody3D] = (),
) -> Callable:
    r"""Build ``L(q, q̇, t, args) = T − V`` from where the mass is.

    **Arguments:**

    - ``positions``: ``x(q, [t], [args]) -> (N, d)`` Cartesian positions of N point masses
      (``(d,)`` for one), or ``None`` if only ``bodies`` carry mass.
    - ``masses``: scalar, ``(N,)`` array, or a function ``masses(args)``.
    - ``potential``: optional ``V(q, [t], [args]) -> scalar`` (springs, fields, ...).
    - ``gravity``: optional ``g`` (number or function of ``args``): uniform gravity along the
      last Cartesian axis, which points up, ``V_g = g (Σ_k m_k x_k[-1] + Σ_b m_b h_b)`` with
      ``h_b`` the height of a body's centre of mass (``y_c`` in the plane, ``z_c`` in space).
    - ``bodies``: :class:`RigidBody2D` (planar, y up) and :class:`RigidBody3D` (in space, z up)
      instances.

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
            m = _check_masses(parameter_value(masses, args, "masses"), x.shape[0])
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
            value = value - parameter_value(gravity, args, "gravity") * height
        return value

    return lagrangian
