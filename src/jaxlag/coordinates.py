r"""Lagrangians from particle positions: ``q ↦ x(q, t)`` in, ``L(q, q̇, t, args)`` out.

Instead of deriving the kinetic energy by hand, describe where the mass is:

    T = ½ Σ_k m_k |ẋ_k|² + Σ_b (½ m_b |ẋ_b|² + ½ I_b φ̇_b²),     ẋ = (∂x/∂q) q̇ + ∂x/∂t,

with ``ẋ`` computed by one forward-mode ``jax.jvp`` of the position map along ``(q̇, 1)`` in
``(q, t)`` (no Jacobian is formed). Point masses are given by a map ``positions(q, [t], [args])
-> (N, d)``; rigid planar bodies by `RigidBody2D` (centre of mass and orientation angle,
mass and moment of inertia about the centre of mass); rigid bodies in space by
`RigidBody3D` (centre of mass and rotation matrix, mass and inertia tensor, kinetic energy
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

from collections.abc import Callable, Sequence
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import _compile as compilation
from ._checks import AbstractLagrangianChecks
from ._conventions import UserFunction, host_to_jax, wrap_configuration_function
from ._custom_types import (
    Args,
    Coordinates,
    Parameter,
    RealScalarLike,
    Scalar,
    Validated,
    Vector,
    Velocities,
)
from ._errors import compiled_check
from ._misc import is_concrete
from ._tolerances import MASS_RCOND, rcond
from .rotations import euler_singularity, record_euler_calls, unskew

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
    value = host_to_jax(value)
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
    ``m ≥ 0`` and a scalar ``I ≥ 0`` are checked (constants when built, functions of ``args``
    at the initial state of a run); a body point ``r`` must have shape (2,).
    """

    pose: UserFunction
    mass: Parameter
    inertia: Parameter

    def __init__(self, pose: Callable, mass: Parameter, inertia: Parameter):
        self.pose = wrap_configuration_function(pose, "rigid body pose function")
        self.mass = _validated(mass, "RigidBody2D", "mass", _mass_problem)
        self.inertia = _validated(inertia, "RigidBody2D", "inertia", _planar_inertia_problem)

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
        self,
        q: Coordinates,
        point: Validated[Float[ArrayLike, "2"] | Sequence[RealScalarLike]],
        t: RealScalarLike = 0.0,
        args: Args = None,
    ) -> Float[Array, "2"]:
        """World position ``x_c + R(φ) r`` of the body point with body coordinates ``r`` (2,)."""
        x = jnp.asarray(self.pose(q, t=t, args=args))
        r = _offset(point, 2, "RigidBody2D", x.dtype)
        c, s = jnp.cos(x[2]), jnp.sin(x[2])
        return x[:2] + jnp.stack([c * r[0] - s * r[1], s * r[0] + c * r[1]])

    def point_velocity(
        self,
        q: Coordinates,
        qd: Velocities,
        point: Validated[Float[ArrayLike, "2"] | Sequence[RealScalarLike]],
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
      works: Euler angles ([`jaxlag.rotations.euler_matrix`][jaxlag.rotations.euler_matrix]), a quaternion
      ([`jaxlag.rotations.quaternion_matrix`][jaxlag.rotations.quaternion_matrix], with ``|q|² = 1`` as a
      holonomic constraint),
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

    Checked (``ValueError`` with the numbers; ``eqx.error_if`` when traced): ``m ≥ 0`` (0 for a
    body turning about its fixed centre, like a gimbal; ``m < 0`` would reverse gravity and
    inertia); ``I`` symmetric and positive semidefinite with principal moments obeying the
    triangle inequality ``I_a + I_b ≥ I_c`` (equality: a lamina), within ``√ε`` relative
    (`inertia_tolerance`) -- constants when the body is built, functions of ``args`` at
    the initial state of a run. At the initial state ``R(q0)`` must be a rotation,
    ``max |RᵀR − I| ≤ 100 √ε`` (`pose_tolerance`) and ``det R > 0``, and a
    parametrization that can leave the rotations (a quaternion, nine free entries) must be
    held on them by holonomic constraints. A body point ``r`` must have shape (3,).
    """

    pose: UserFunction
    mass: Parameter
    inertia: Parameter  # principal moments (3,) or the tensor (3, 3), or a function of args

    def __init__(self, pose: Callable, mass: Parameter, inertia: Parameter):
        self.pose = wrap_configuration_function(pose, "rigid body pose function")
        self.mass = _validated(mass, "RigidBody3D", "mass", _mass_problem)
        self.inertia = _validated(inertia, "RigidBody3D", "inertia", _inertia_problem)

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
        self,
        q: Coordinates,
        point: Validated[Float[ArrayLike, "3"] | Sequence[RealScalarLike]],
        t: RealScalarLike = 0.0,
        args: Args = None,
    ) -> Float[Array, "3"]:
        """World position ``x_c + R r`` of the body point with body coordinates ``r`` (3,)."""
        x, rotation = self._pose(jnp.asarray(q), t, args)
        return x + rotation @ _offset(point, 3, "RigidBody3D", x.dtype)

    def point_velocity(
        self,
        q: Coordinates,
        qd: Velocities,
        point: Validated[Float[ArrayLike, "3"] | Sequence[RealScalarLike]],
        t: RealScalarLike = 0.0,
        args: Args = None,
    ) -> Float[Array, "3"]:
        """``ẋ_c + Ṙ r = v + ω × (R r)`` (world axes): velocity of the body point ``r``."""
        (_, _), (v, rate) = self.pose_and_rates(q, qd, t, args)
        return v + rate @ _offset(point, 3, "RigidBody3D", v.dtype)

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
    bodies: Validated[Sequence[RigidBody2D | RigidBody3D]] = (),
) -> Callable:
    r"""``T(q, q̇, t, args) = ½ Σ_k m_k |ẋ_k|² + Σ_b T_b`` for point masses and rigid bodies.

    ``positions(q, [t], [args]) -> (N, d)`` (or ``(d,)``); ``masses`` a scalar, an ``(N,)``
    array, or a function of ``args``. ``ẋ`` comes from one ``jax.jvp`` along ``(q̇, 1)``, so
    time-dependent maps (a rotating wire, a driven support) give the full ``∂x/∂t`` terms.
    """
    fn = wrap_configuration_function(positions, "position map") if positions is not None else None
    masses = _validated(masses, "kinetic_energy_from_positions", "masses", _point_masses_problem)
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
    bodies: Validated[Sequence[RigidBody2D | RigidBody3D]] = (),
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
    - ``bodies``: `RigidBody2D` (planar, y up) and `RigidBody3D` (in space, z up)
      instances.

    ``T = ½ Σ m |ẋ|² (+ bodies)``, ``ẋ = (∂x/∂q) q̇ + ∂x/∂t`` by forward-mode autodiff. The
    returned function declares ``t`` and ``args``; pass it to [`jaxlag.System`][jaxlag.System].

    Checks: constant masses and inertias when the bodies are built; masses and inertias that
    are functions of ``args``, and each body's rotation ``R(q0)``, at the initial state of a run
    (masses ``≥ 0``; inertias symmetric, positive semidefinite, principal moments obeying
    ``I_a + I_b ≥ I_c``; ``R`` orthonormal with ``det R = +1`` within `pose_tolerance`; a
    parametrization that can leave the rotations, such as a quaternion, held by a holonomic
    constraint). A singular mass matrix caused by gimbal lock of a body's
    Euler angles is reported as such.
    """
    masses = _validated(masses, "lagrangian_from_positions", "masses", _point_masses_problem)
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

    # Callable like the function, carrying the bodies for the initial-state check.
    return _PositionLagrangian(lagrangian, fn, masses, bodies)


# ----------------------------------------------------------------------------- validation
# A body's mass, inertia and pose are checked where they are known: constants when the body is
# built (eagerly with the numbers; a traced constant carries an eqx.error_if), functions of
# `args` and the pose at the initial state of a run (_check_bodies, called by the initial-state
# check of every entry point). Nothing is checked per step.


def inertia_tolerance(dtype) -> float:
    """Relative tolerance of the inertia checks (symmetry, ``λ ≥ 0``, triangle inequality):
    ``√ε`` of the dtype (1.5e-8 in float64, 3.5e-4 in float32), relative to the largest moment."""
    return float(np.sqrt(np.finfo(dtype).eps))


def pose_tolerance(dtype) -> float:
    """Tolerance of the rotation check at the initial state, ``max |RᵀR − I| ≤ 100 √ε`` (1.5e-6
    in float64, 3.5e-2 in float32): loose enough for a quaternion within the default constraint
    tolerance of the unit sphere (``|q|² − 1`` up to 1e-8 moves ``RᵀR`` by 2e-8)."""
    return 100.0 * float(np.sqrt(np.finfo(dtype).eps))


def _float_dtype(x):
    dtype = np.dtype(jnp.result_type(x))
    return dtype if np.issubdtype(dtype, np.inexact) else np.dtype(jnp.result_type(float))


def _mass_problem(value, traced: bool = False):
    """Host: why ``value`` is not a mass (``str``) or ``None``; traced: ``(flag, text)``."""
    shape = jnp.shape(value)
    if shape != ():
        raise ValueError(f"A body's mass must be a scalar; got shape {shape}.")
    text = (
        "must be finite and ≥ 0 (a negative mass reverses gravity and inertia: a heavy top with m < 0 rises)"
    )
    if traced:
        return ~(jnp.asarray(value) >= 0), text
    if not (np.isfinite(value) and value >= 0):
        return (
            f"mass m = {float(value):g}: a mass must be finite and ≥ 0 (0 for a body that only "
            "turns about its fixed centre of mass, like a gimbal). A negative mass reverses both "
            "gravity and inertia: a heavy top with m = −1 rises through upright."
        )
    return None


def _point_masses_problem(value, traced: bool = False):
    text = "must be finite and ≥ 0"
    if traced:
        return ~jnp.all(jnp.asarray(value) >= 0), text
    value = np.asarray(value)
    bad = np.flatnonzero(~(np.isfinite(value) & (value >= 0)).ravel())
    if bad.size:
        shown = ", ".join(f"masses[{int(i)}] = {value.ravel()[i]:g}" for i in bad[:4])
        return f"point masses must be finite and ≥ 0; got {shown}."
    return None


def _planar_inertia_problem(value, traced: bool = False):
    shape = jnp.shape(value)
    if shape != ():
        raise ValueError(
            "A RigidBody2D inertia is the moment of inertia about the centre of mass, a scalar; got "
            f"shape {shape}."
        )
    text = "must be finite and ≥ 0"
    if traced:
        return ~(jnp.asarray(value) >= 0), text
    if not (np.isfinite(value) and value >= 0):
        return f"moment of inertia I = {float(value):g}: it must be finite and ≥ 0 (I = ∫ |r|² dm)."
    return None


def _inertia_problem(value, traced: bool = False):
    """Principal moments (3,) or a tensor (3, 3): finite, symmetric, ``λ ≥ 0``, ``λ_a + λ_b ≥ λ_c``."""
    shape = jnp.shape(value)
    if shape not in ((3,), (3, 3)):
        _inertia_tensor(jnp.zeros(shape))  # raises the shape message
    dtype = _float_dtype(value)
    tol = inertia_tolerance(dtype)
    xp = jnp if traced else np
    value = xp.asarray(value, dtype)
    tensor = xp.diag(value) if shape == (3,) else value
    finite = xp.all(xp.isfinite(tensor))
    safe = xp.where(finite, tensor, 0.0)
    scale = xp.maximum(xp.max(xp.abs(safe)), np.finfo(dtype).tiny)
    asymmetry = xp.max(xp.abs(safe - safe.T))
    moments = value if shape == (3,) else xp.linalg.eigvalsh(0.5 * (safe + safe.T))
    moments = xp.sort(xp.where(finite, moments, 0.0))
    negative = moments[0] < -tol * scale
    triangle = moments[0] + moments[1] < moments[2] - tol * scale
    if traced:
        bad = ~finite | (asymmetry > tol * scale) | negative | triangle
        return bad, (
            "must be finite, symmetric and positive semidefinite, its principal moments obeying the "
            "triangle inequality I_a + I_b ≥ I_c"
        )
    if not finite:
        return f"inertia {value.tolist()} is not finite."
    if asymmetry > tol * scale:
        i, j = np.unravel_index(np.argmax(np.abs(tensor - tensor.T)), (3, 3))
        return (
            f"the inertia tensor is not symmetric: I[{i}, {j}] = {tensor[i, j]:g} but I[{j}, {i}] = "
            f"{tensor[j, i]:g} (tolerance {tol:.2g} relative). An inertia tensor is symmetric "
            "(I_ij = −∫ r_i r_j dm for i ≠ j), and only its symmetric part would act; give the "
            "symmetric tensor."
        )
    if negative:
        return (
            f"principal moments {moments.tolist()} include a negative one: moments of inertia "
            "∫ (|r|² − r_i²) dm are ≥ 0 (the tensor must be positive semidefinite)."
        )
    if triangle:
        return (
            f"principal moments {moments.tolist()} violate the triangle inequality "
            f"I_a + I_b ≥ I_c ({moments[0]:g} + {moments[1]:g} < {moments[2]:g}): no distribution "
            "of mass has them (I_a + I_b − I_c = 2 ∫ r_c² dm ≥ 0). Equality is a flat body (a "
            "lamina), I_c = 0 a thin rod along c."
        )
    return None


def _validated(value, owner: str, name: str, problem):
    """A constant mass or inertia checked when the body is built (a function of ``args`` is
    checked at the initial state of a run, by `_check_bodies`)."""
    if callable(value):
        return value
    if is_concrete(value):
        text = problem(np.asarray(value))
        if text is not None:
            raise ValueError(f"{owner} {name}: {text}")
        return value
    bad, text = cast(tuple, problem(value, traced=True))
    return compiled_check(jnp.asarray(value), bad, 0, (f"jaxlag: {owner} {name} {text}.",))


def _offset(point, size: int, owner: str, dtype):
    r = jnp.asarray(point, dtype)
    if r.shape != (size,):
        raise ValueError(
            f"A body point of a {owner} is given by its body coordinates r, shape ({size},); got "
            f"shape {r.shape}."
        )
    return r


class _PositionLagrangian(AbstractLagrangianChecks):
    """The Lagrangian built by `lagrangian_from_positions`: a plain callable (static under
    ``jit``, like the function it replaces) that also knows its bodies and point masses, and
    implements the core's hook `AbstractLagrangianChecks` so that the
    initial-state check validates them (`_check_bodies`)."""

    def __init__(self, fn, positions, masses, bodies):
        self._fn = fn
        self.positions = positions
        self.masses = masses
        self.bodies = bodies

    def __call__(self, q, qd, t=0.0, args=None):
        return self._fn(q, qd, t, args)

    def check_initial_state(self, system, q, qd, t, args):
        return _check_bodies(self, system, q, qd, t, args)

    def initial_state_diagnostics(self, system, q, qd, t, args):
        del qd  # the checks depend on the configuration only
        return _body_diagnostics(self, system, q, t, args)

    def raise_for_diagnostics(self, system, diagnostics, q):
        _raise_for_bodies(self, diagnostics, q)


_GRAM = np.triu_indices(3)


def _nearby(q):
    """A point near ``q`` that is generic (not itself on a coordinate singularity)."""
    pattern = jnp.sin(1.0 + 2.3 * jnp.arange(q.shape[0], dtype=q.dtype))
    return q + 1e-2 * (1.0 + jnp.abs(q)) * pattern


def _parameter_values(lagrangian, args) -> dict:
    """Masses and inertias at ``args`` (plain calls: a function of ``args`` is cheap, and a
    constant was checked when the body was built)."""
    out: dict = dict(
        masses=[parameter_value(b.mass, args, "mass") for b in lagrangian.bodies],
        inertias=[parameter_value(b.inertia, args, "inertia") for b in lagrangian.bodies],
    )
    if lagrangian.positions is not None:
        out["point_masses"] = parameter_value(lagrangian.masses, args, "masses")
    return out


@compilation.filter_jit
def _pose_values(system, lagrangian, q, t, args):
    """For each RigidBody3D, ``R(q0)``, ``∂(RᵀR)/∂q`` and ``∂R/∂q`` at ``q0`` and nearby; the
    holonomic Jacobian ``J(q0)``. One small program, compiled once per system."""
    t = jnp.asarray(t, q.dtype)
    out: dict = dict(rotations=[], gram=[], jacobian=[], nearby=[])
    for b in lagrangian.bodies:
        if isinstance(b, RigidBody3D):

            def rotation(x, b=b):
                return b._pose(x, t, args)[1]

            def gram(x, rotation=rotation):
                r = rotation(x)
                return (r.T @ r)[_GRAM]

            # ∂R/∂q v = Ṙ = R [ω(v)]ₓ: on rotations ∂R/∂q has the rank of q̇ ↦ ω, so the
            # Jacobian at q0 and nearby also tells where the parametrization loses rank.
            out["rotations"].append(rotation(q))
            out["gram"].append(jax.jacfwd(gram)(q))
            out["jacobian"].append(jax.jacfwd(rotation)(q).reshape(9, q.shape[0]))
            out["nearby"].append(jax.jacfwd(rotation)(_nearby(q)).reshape(9, q.shape[0]))
    if system.holonomic is not None:
        out["constraints"] = jax.jacfwd(lambda x: jnp.asarray(system.holonomic(x, t=t, args=args)))(q)
    else:
        out["constraints"] = jnp.zeros((0, q.shape[0]), q.dtype)
    return out


def _drift(gram, jacobian, constraints, xp):
    """``(∂(RᵀR)/∂q) P`` with ``P`` the projector on the directions the holonomic constraints
    allow, and the scale ``max |∂R/∂q|`` to compare it with."""
    n = gram.shape[1]
    projector = xp.eye(n, dtype=gram.dtype)
    if constraints.shape[0] > 0:
        projector = projector - xp.linalg.pinv(constraints) @ constraints
    return gram @ projector, xp.maximum(xp.max(xp.abs(jacobian)), np.finfo(gram.dtype).tiny)


def _rotation_error(rotation, xp):
    gram = rotation.T @ rotation - xp.eye(3, dtype=rotation.dtype)
    return xp.max(xp.abs(gram)), xp.linalg.det(rotation)


def _signed(direction):
    """A direction whose first sizeable component is positive (an SVD's sign is arbitrary;
    "sizeable", within a factor 2 of the largest, so that round-off does not flip it)."""
    magnitude = np.abs(direction)
    first = int(np.flatnonzero(magnitude > 0.5 * np.max(magnitude))[0])
    return direction * np.sign(direction[first])


def _body_name(k, body) -> str:
    return f"bodies[{k}] ({type(body).__name__})"


def _host_problem(lagrangian, v, q) -> str | None:
    """The first problem with the bodies at the initial state, with its numbers, or ``None``."""
    dtype = np.asarray(q).dtype
    problems = {RigidBody3D: _inertia_problem, RigidBody2D: _planar_inertia_problem}
    for k, b in enumerate(lagrangian.bodies):
        for name, value, problem in (
            ("mass", v["masses"][k], _mass_problem),
            ("inertia", v["inertias"][k], problems[type(b)]),
        ):
            text = problem(np.asarray(value))
            if text is not None:
                return f"{_body_name(k, b)} {name} at the initial state's args: {text}"
    if "point_masses" in v:
        text = _point_masses_problem(np.asarray(v["point_masses"]))
        if text is not None:
            return f"lagrangian_from_positions: {text}"
    tol = pose_tolerance(dtype)
    bodies3 = [(k, b) for k, b in enumerate(lagrangian.bodies) if isinstance(b, RigidBody3D)]
    for i, (k, b) in enumerate(bodies3):
        rotation = np.asarray(v["rotations"][i])
        error, det = _rotation_error(rotation, np)
        if not (error <= tol and det > 0):
            kind = "a reflection (det R < 0)" if det < 0 else "not orthonormal"
            return (
                f"The pose of {_body_name(k, b)} returns at the initial state a matrix R that is "
                f"{kind}: max |RᵀR − I| = {error:.3g} (tolerance {tol:.2g}), det R = {det:.6g}, "
                f"R = {rotation.tolist()}. R must be a rotation (orthonormal, det +1): a scaled "
                "or sheared R gives a wrong kinetic energy ½ωᵀIω and a wrong motion. Build it with "
                "jaxlag.rotations (euler_matrix, axis_rotation, axis_angle_matrix, or "
                "quaternion_matrix of a unit quaternion)."
            )
    for i, (k, b) in enumerate(bodies3):
        constraints = np.asarray(v["constraints"])
        drift, scale = _drift(np.asarray(v["gram"][i]), np.asarray(v["jacobian"][i]), constraints, np)
        if np.max(np.abs(drift)) > inertia_tolerance(dtype) * scale:
            direction = _signed(np.linalg.svd(drift)[2][0])
            used = np.flatnonzero(np.abs(direction) > 0.1 * np.max(np.abs(direction)))
            entries = ", ".join(f"q[{int(j)}]" for j in used)
            return (
                f"The pose of {_body_name(k, b)} leaves the rotation group: RᵀR changes along "
                f"q̇ ∝ {np.round(direction, 6).tolist()} (coordinates {entries}), and no holonomic "
                "constraint of the System holds it there, so R drifts off the rotations during "
                "the run (a quaternion's |q| grows, the body shrinks or swells). A quaternion body "
                "needs the constraint |q|² − 1 = 0, e.g. System(L, holonomic=lambda q: "
                "jnp.reshape(q[i:i+4] @ q[i:i+4] - 1.0, (1,))) for q[i:i+4] the quaternion "
                "(jaxlag.systems.heavy_top('quaternion') does this); the nine entries of R need "
                "the six constraints RᵀR − I = 0."
            )
    return None


def _singularity_message(system, lagrangian, v, q, qd, t, args) -> str | None:
    """If ``M`` is singular at ``q0`` because a body's orientation coordinates lose rank there
    (gimbal lock), say so and name the Euler sequence; else ``None`` (M is regular, or singular
    for another reason: left to the generic check)."""
    bodies3 = [(k, b) for k, b in enumerate(lagrangian.bodies) if isinstance(b, RigidBody3D)]
    for i, (k, b) in enumerate(bodies3):
        here, nearby = np.asarray(v["jacobian"][i]), np.asarray(v["nearby"][i])
        s_nearby = np.linalg.svd(nearby, compute_uv=False)
        if s_nearby[0] == 0:
            continue
        _, s_here, vt = np.linalg.svd(here)
        cut = 1e-8 * s_nearby[0]
        rank_here, rank_nearby = int(np.sum(s_here > cut)), int(np.sum(s_nearby > cut))
        if rank_here >= rank_nearby:
            continue
        null = vt[rank_here:]  # directions that do not turn the body at q0
        lost = _signed(null.T @ np.linalg.svd(nearby @ null.T)[2][0])  # ... but turn it nearby
        qa = jnp.asarray(q)
        qda = jnp.asarray(qd)
        ta = jnp.asarray(t, qa.dtype)
        mass = np.asarray(system.mass_matrix(qa, qda, ta, args))  # compiled; M is not checked there
        eig = np.linalg.eigvalsh(mass)
        largest = max(float(np.max(np.abs(eig))), np.finfo(eig.dtype).tiny)
        if eig[0] > rcond(MASS_RCOND, eig.dtype) * largest or np.linalg.norm(mass @ lost) > 1e-6 * largest:
            continue
        with record_euler_calls() as calls:
            b._pose(qa, ta, args)
        euler = ""
        for sequence, extrinsic, angles in calls:
            angles = np.asarray(angles)
            middle = angles[1]
            margin = abs(np.sin(middle)) if sequence[0] == sequence[2] else abs(np.cos(middle))
            if margin < 1e-6:
                order = "extrinsic" if extrinsic else "intrinsic"
                euler = (
                    f" Its pose uses rotations.euler_matrix(angles, {sequence!r}) ({order}) with "
                    f"angles {angles.tolist()}: Euler angles {sequence!r} are singular at "
                    f"{euler_singularity(sequence)}, and the middle angle is {middle:.6g} here "
                    "(gimbal lock)."
                )
                break
        return (
            f"The mass matrix M = ∂²L/∂q̇² is singular at the initial state (eigenvalues {eig}) "
            f"because the coordinates of the orientation of {_body_name(k, b)} are singular there, "
            f"not because the Lagrangian lacks a kinetic term: along q̇ ∝ "
            f"{np.round(lost, 6).tolist()} the body does not turn at q0 (its map q̇ ↦ ω has rank "
            f"{rank_here} here and {rank_nearby} nearby).{euler} Use a quaternion body, which has no "
            "singularity (rotations.quaternion_matrix(q[i:i+4]) with the holonomic constraint "
            "|q|² − 1 = 0, as jaxlag.systems.heavy_top('quaternion')), or start away from it "
            "(rotations.gimbal_lock_margin(angles, sequence) > 0)."
        )
    return None


def _traced_checks(lagrangian, v, q):
    """``(flags, messages)`` of the same checks as `_host_problem`, for traced values."""
    dtype = q.dtype
    flags, messages = [], []
    problems = {RigidBody3D: _inertia_problem, RigidBody2D: _planar_inertia_problem}
    for k, b in enumerate(lagrangian.bodies):
        for name, value, problem in (
            ("mass", v["masses"][k], _mass_problem),
            ("inertia", v["inertias"][k], problems[type(b)]),
        ):
            bad, text = cast(tuple, problem(value, traced=True))
            flags.append(bad)
            messages.append(f"{_body_name(k, b)} {name} {text}.")
    if "point_masses" in v:
        bad, text = cast(tuple, _point_masses_problem(v["point_masses"], traced=True))
        flags.append(bad)
        messages.append(f"lagrangian_from_positions: point masses {text}.")
    tol = pose_tolerance(dtype)
    bodies3 = [(k, b) for k, b in enumerate(lagrangian.bodies) if isinstance(b, RigidBody3D)]
    for i, (k, b) in enumerate(bodies3):
        error, det = _rotation_error(v["rotations"][i], jnp)
        flags.append(~((error <= tol) & (det > 0)))
        messages.append(
            f"The pose of {_body_name(k, b)} returns at the initial state a matrix R that is not a "
            f"rotation (max |RᵀR − I| > {tol:.2g} or det R ≤ 0): build it with jaxlag.rotations."
        )
    for i, (k, b) in enumerate(bodies3):
        drift, scale = _drift(v["gram"][i], v["jacobian"][i], v["constraints"], jnp)
        flags.append(jnp.max(jnp.abs(drift)) > inertia_tolerance(dtype) * scale)
        messages.append(
            f"The pose of {_body_name(k, b)} leaves the rotation group along a direction that no "
            "holonomic constraint holds: a quaternion body needs |q|² − 1 = 0 as a holonomic "
            "constraint (the nine entries of R need RᵀR − I = 0)."
        )
    return flags, messages


_COMPILED = " (Checked inside a compiled program: call outside jit/vmap/grad to see the numbers.)"


def _check_bodies(lagrangian: _PositionLagrangian, system, q, qd, t, args):
    """Validate the rigid bodies and point masses of a Lagrangian built by
    `lagrangian_from_positions` at the initial state ``(q0, t0, args)``: masses ``≥ 0``,
    inertias symmetric, positive semidefinite, obeying the triangle inequality; each
    ``R(q0)`` a rotation within `pose_tolerance`; no direction that moves ``R`` off the
    rotations unless a holonomic constraint forbids it; and, when ``M`` is singular because a
    body's orientation coordinates are (gimbal lock), a message that says so. Concrete values
    raise ``ValueError`` with the numbers; traced ones return ``q`` carrying
    ``eqx.branched_error_if`` (static messages)."""
    spatial = any(isinstance(b, RigidBody3D) for b in lagrangian.bodies)
    parameters = [b.mass for b in lagrangian.bodies] + [b.inertia for b in lagrangian.bodies]
    parameters += [lagrangian.masses] if lagrangian.positions is not None else []
    if not spatial and not any(callable(p) for p in parameters):
        return q  # constants only: checked when the bodies were built
    values = _parameter_values(lagrangian, args)
    if spatial:
        values.update(_pose_values(system, lagrangian, q, t, args))
    if is_concrete((q, qd, t, args, values)):
        host = jax.device_get(values)
        text = _host_problem(lagrangian, host, q)
        if text is None:
            text = _singularity_message(system, lagrangian, host, q, qd, t, args)
        if text is not None:
            raise ValueError(text)
        return q
    flags, messages = _traced_checks(lagrangian, values, q)
    if not flags:
        return q
    stacked = jnp.stack([jnp.asarray(f) for f in flags])
    messages = tuple(f"jaxlag: {m}{_COMPILED}" for m in messages)
    return compiled_check(q, jnp.any(stacked), jnp.argmax(stacked), messages)


def _body_diagnostics(lagrangian: _PositionLagrangian, system, q, t, args):
    """The checks of `_check_bodies` as values, traceable and without a callback (for
    batch programs that return their checks to the host): ``(values, flags)``, or ``None``
    when there is nothing to check. `_raise_for_bodies` raises from them on the host."""
    spatial = any(isinstance(b, RigidBody3D) for b in lagrangian.bodies)
    parameters = [b.mass for b in lagrangian.bodies] + [b.inertia for b in lagrangian.bodies]
    parameters += [lagrangian.masses] if lagrangian.positions is not None else []
    if not spatial and not any(callable(p) for p in parameters):
        return None
    values = _parameter_values(lagrangian, args)
    if spatial:
        values.update(_pose_values(system, lagrangian, q, t, args))
    flags, _ = _traced_checks(lagrangian, values, q)
    return values, jnp.stack([jnp.asarray(f) for f in flags])


def _raise_for_bodies(lagrangian: _PositionLagrangian, diagnostics, q) -> None:
    """Raise ``ValueError`` with the numbers for the first batch member whose bodies fail the
    checks of `_body_diagnostics` (``diagnostics`` and ``q`` with or without a leading
    batch axis)."""
    if diagnostics is None:
        return
    values, flags = jax.device_get(diagnostics)
    flags, q = np.asarray(flags), np.asarray(q)
    batched = flags.ndim == 2
    failing = flags.any(axis=-1).reshape(-1)
    members = np.flatnonzero(failing)
    if members.size == 0:
        return
    first = int(members[0])
    if batched:
        values = jax.tree.map(lambda x: np.asarray(x)[first], values)
        q = q[first]
    text = _host_problem(lagrangian, values, q)
    if text is None:  # within round-off of a threshold: the compiled flag's static message
        _, messages = _traced_checks(lagrangian, values, jnp.asarray(q))
        member_flags = flags[first] if batched else flags
        text = messages[int(np.argmax(member_flags))]
    prefix = (
        f"{members.size} of {failing.size} batch members failed (first: member [{first}]). Member [{first}]: "
        if batched
        else ""
    )
    raise ValueError(prefix + text)
