r"""Rolling contact of a disk or a sphere on the ground plane ``z = 0`` (z up).

The body is a [`RigidBody3D`][jaxlag.coordinates.RigidBody3D] whose centre of mass is the centre of the
disk or sphere. The contact point ``P`` is the lowest point of the body:

* sphere of radius ``r``: ``P = x_c − r e_z``;
* disk of radius ``r`` with unit axis ``n = R a`` (``a`` its axis in body coordinates):
  ``P = x_c − r u``, ``u = (e_z − (n·e_z) n)/|e_z − (n·e_z) n|`` (the in-plane direction that
  points most upward; undefined for a disk lying flat).

**Contact** (holonomic, `contact_height`): ``f(q) = P_z = 0``. Its multiplier is the
normal force: ``ḟ`` is the vertical velocity of the material point at ``P`` (the contact point
slides along the rim horizontally), so ``Jᵀλ`` is the generalized force of the world force
``λ e_z`` applied at ``P``: ``λ = N``, positive when the ground pushes up.

**Rolling without slipping** (`rolling_without_slipping`): the velocity of the material
point at ``P``, ``v_P = ẋ_c + ω × (P − x_c)`` (world axes), equals that of the ground (zero, or
``surface_velocity`` for a turntable or a conveyor). The constraint returns the two horizontal
components of ``v_P − v_surface`` (the vertical one is ``ḟ``, already imposed by the contact
constraint or by coordinates that keep the body on the ground). It is affine in ``q̇``, a
Pfaffian constraint ``A q̇ + b = 0`` with ``A = ∂v_P,xy/∂q̇``, so ``Aᵀμ`` is the generalized
force of the world force ``(μ₀, μ₁, 0)`` at ``P``: **the velocity multipliers are the friction
force on the body in world axes**, ``traj.velocity_multipliers == (F_x, F_y)``.
"""

from collections.abc import Callable

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._conventions import wrap_configuration_function
from ._custom_types import Args, Coordinates, Parameter, RealScalarLike, Validated, Velocities
from .coordinates import RigidBody3D, parameter_value
from .rotations import unskew

__all__ = ["contact_height", "contact_point", "contact_velocity", "rolling_without_slipping"]

_SHAPES = ("disk", "sphere")

#: The symmetry axis of a disk, in body coordinates.
Axis = Float[ArrayLike, "3"] | tuple[float, float, float]


def _check(body, shape):
    if not isinstance(body, RigidBody3D):
        raise TypeError(f"Rolling contact needs a RigidBody3D; got {type(body).__name__}.")
    if shape not in _SHAPES:
        raise ValueError(f"shape must be one of {_SHAPES}; got {shape!r}.")


def _offset(centre, rotation, radius, shape, axis):
    """``P − x_c``: from the centre to the lowest point of the disk or sphere."""
    up = jnp.zeros(3, centre.dtype).at[2].set(1.0)
    if shape == "sphere":
        return -radius * up
    n = rotation @ jnp.asarray(axis, centre.dtype)
    n = n / jnp.linalg.norm(n)
    in_plane = up - n[2] * n
    return -radius * in_plane / jnp.linalg.norm(in_plane)


def contact_point(
    body: Validated[RigidBody3D],
    q: Coordinates,
    radius: Parameter,
    *,
    shape: str = "disk",
    axis: Axis = (0.0, 0.0, 1.0),
    t: RealScalarLike = 0.0,
    args: Args = None,
) -> Float[Array, "3"]:
    """World position of the lowest point ``P`` of a disk (axis ``axis`` in body coordinates)
    or sphere of radius ``radius`` (a number or a function of ``args``)."""
    _check(body, shape)
    centre, rotation = body.position(q, t, args)
    return centre + _offset(centre, rotation, parameter_value(radius, args, "radius"), shape, axis)


def contact_velocity(
    body: Validated[RigidBody3D],
    q: Coordinates,
    qd: Velocities,
    radius: Parameter,
    *,
    shape: str = "disk",
    axis: Axis = (0.0, 0.0, 1.0),
    t: RealScalarLike = 0.0,
    args: Args = None,
) -> Float[Array, "3"]:
    """``v_P = ẋ_c + ω × (P − x_c)``: velocity (world axes) of the material point at ``P``."""
    _check(body, shape)
    (centre, rotation), (velocity, rate) = body.pose_and_rates(q, qd, t, args)
    offset = _offset(centre, rotation, parameter_value(radius, args, "radius"), shape, axis)
    return velocity + jnp.cross(unskew(rate @ rotation.T), offset)


def contact_height(
    body: Validated[RigidBody3D], radius: Parameter, *, shape: str = "disk", axis: Axis = (0.0, 0.0, 1.0)
) -> Callable:
    """Holonomic contact ``f(q, t, args) = (P_z,)``: the body touches the plane ``z = 0``.
    Its multiplier is the normal force ``N`` (see the module docstring)."""
    _check(body, shape)

    def height(q, t=0.0, args=None):
        return contact_point(body, q, radius, shape=shape, axis=axis, t=t, args=args)[2:]

    return height


def rolling_without_slipping(
    body: Validated[RigidBody3D],
    radius: Parameter,
    *,
    shape: str = "disk",
    axis: Axis = (0.0, 0.0, 1.0),
    surface_velocity: Callable | None = None,
) -> Callable:
    r"""Velocity constraint ``g(q, qd, t, args) = (v_P − v_s)_{x,y} = 0`` (shape (2,)).

    - ``body``: a `RigidBody3D` whose centre of mass is the disk's or sphere's centre.
    - ``radius``: a number or a function of ``args``.
    - ``shape``: ``"disk"`` (a thin wheel with symmetry axis ``axis`` in body coordinates) or
      ``"sphere"``.
    - ``surface_velocity``: optional ``v_s(P, [t], [args]) -> (3,)``, the velocity of the ground
      at the contact point (e.g. ``Ω e_z × P`` for a turntable); zero by default.

    Pass it as ``System(velocity_constraints=...)`` (stack several with ``jnp.concatenate``).
    The multipliers ``μ`` of these two rows are the friction force ``(F_x, F_y)`` that the
    ground exerts on the body at ``P`` (world axes).
    """
    _check(body, shape)
    surface = None
    if surface_velocity is not None:
        surface = wrap_configuration_function(surface_velocity, "surface velocity")

    def rolling(q, qd, t=0.0, args=None):
        v = contact_velocity(body, q, qd, radius, shape=shape, axis=axis, t=t, args=args)
        if surface is not None:
            point = contact_point(body, q, radius, shape=shape, axis=axis, t=t, args=args)
            v = v - jnp.asarray(surface(point, t=t, args=args), v.dtype)
        return v[:2]

    return rolling
