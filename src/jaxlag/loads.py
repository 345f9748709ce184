r"""Loads on bodies -> generalized forces, by virtual work.

A force ``F`` (world components) applied at a point ``x_p(q, t)`` and a torque ``τ`` (world
components) on a body with angular velocity ``ω`` contribute

    Q = Σ (∂ẋ_p/∂q̇)ᵀ F_p + Σ (∂ω/∂q̇)ᵀ τ_b,

the generalized forces of ``M q̈ = F + Jᵀλ + Aᵀμ`` (they enter as the ``Q`` of
``d/dt ∂L/∂q̇ − ∂L/∂q = Q``). Both velocities are linear in ``q̇`` (the ``∂/∂t`` part of a
moving support does no virtual work), so each term is the transpose of that linear map applied
to the load (``jax.linear_transpose`` of a ``jvp``, a reverse pass): no Jacobian is formed.

Loads may depend on the state, the time and the parameters (springs, dampers, actuators):
``force(q, qd, [t], [args]) -> (d,)`` and ``torque(q, qd, [t], [args]) -> (3,)`` (a scalar for a
[`RigidBody2D`][jaxlag.coordinates.RigidBody2D]) follow the library's calling convention; a constant
array may be given instead of a function::

    tip = (arm, jnp.array([0.0, 0.0, 0.5]))              # body point, body coordinates
    spring = loads.Force(tip, lambda q, qd, args: -args["k"] * arm.point_position(q, tip[1]))
    motor = loads.Torque(arm, lambda q, qd, t: jnp.array([0.0, 0.0, jnp.sin(t)]))
    system = jl.System(L, forces=loads.generalized_forces(spring, motor))
"""

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.extend.core as jcore
import jax.numpy as jnp
import numpy as np

from ._conventions import UserFunction, wrap_configuration_function, wrap_state_function
from ._custom_types import Args, RealArrayLike, RealScalarLike, Validated, Vector
from .coordinates import RigidBody2D, RigidBody3D

__all__ = ["Force", "Torque", "generalized_forces", "point_map"]

_BODIES = (RigidBody2D, RigidBody3D)

#: A body point ``(body, r)`` (``r`` its body coordinates) or a position map ``x(q, [t], [args])``.
PointLike = tuple[RigidBody2D | RigidBody3D, RealArrayLike] | Callable


def point_map(point: Validated[PointLike]) -> UserFunction:
    """A point as a position map ``x(q, [t], [args]) -> (d,)``.

    ``point`` is a ``(body, r)`` pair (a body point with body coordinates ``r``, on a
    `RigidBody3D` or `RigidBody2D`) or a position map itself.
    """
    if isinstance(point, tuple) and len(point) == 2 and isinstance(point[0], _BODIES):
        body, offset = point
        size = 3 if isinstance(body, RigidBody3D) else 2
        if np.shape(offset) != (size,):
            raise ValueError(
                f"A body point ({type(body).__name__}, r) takes r in body coordinates, shape "
                f"({size},); got shape {np.shape(offset)}."
            )

        def position(q, t, args):
            return body.point_position(q, offset, t, args)

        return wrap_configuration_function(position, "point position map")
    if callable(point):
        return wrap_configuration_function(point, "point position map")
    raise TypeError(
        "A point must be a (body, r) pair (body a RigidBody3D or RigidBody2D, r its body "
        f"coordinates) or a position map x(q, [t], [args]); got {type(point).__name__}."
    )


def _load_function(load, role):
    if callable(load):
        return wrap_state_function(load, role)
    value = jnp.asarray(load)

    def constant(q, qd):
        return value.astype(q.dtype)

    return wrap_state_function(constant, role)


class Force(eqx.Module):
    """A force ``F`` (world components) acting at ``point``: a ``(body, r)`` pair or a position
    map ``x(q, [t], [args])``. ``force``: ``F(q, qd, [t], [args]) -> (d,)`` or a constant.

    A position map that does not depend on ``q`` is refused (``ValueError`` when the forces
    are first evaluated): such a point has no virtual displacement, so the force would
    contribute exactly 0. A body offset ``r`` must have shape (3,) (a ``RigidBody2D``: (2,))."""

    point: UserFunction
    force: UserFunction

    def __init__(self, point: Validated[PointLike], force: Callable | RealArrayLike):
        self.point = point_map(point)
        self.force = _load_function(force, "force")

    def generalized(self, q: Vector, qd: Vector, t: RealScalarLike, args: Args) -> Vector:
        """``(∂ẋ_p/∂q̇)ᵀ F``."""
        load = jnp.asarray(self.force(q, qd, t=t, args=args))

        def velocity(v):
            return jax.jvp(lambda x: jnp.asarray(self.point(x, t=t, args=args)), (q,), (v,))[1]

        shape = jax.eval_shape(velocity, qd).shape
        if load.shape != shape:
            raise ValueError(
                f"The force at a point must have the shape of the point's position, {shape}; it "
                f"has shape {load.shape}."
            )
        if not _depends_on_input(velocity, qd):
            raise ValueError(
                "loads.Force: the point's position map does not depend on q (a point fixed in "
                "space, or one moving on a prescribed path x(t)). Its virtual displacement "
                "δx = (∂x/∂q) δq is zero, so the force does no virtual work on the system and "
                "its generalized force is exactly 0: almost always a mistake. Apply the force at "
                "a point of a body, Force((body, r), F) with r in body coordinates, or write the "
                "position map as a function of q; drop the load if it truly acts on nothing that "
                "moves."
            )
        return jax.linear_transpose(velocity, qd)(load.astype(q.dtype))[0]


class Torque(eqx.Module):
    """A torque ``τ`` (world components, (3,); a scalar for a planar body) on ``body``.
    ``torque``: ``τ(q, qd, [t], [args])`` or a constant."""

    body: RigidBody2D | RigidBody3D
    torque: UserFunction

    def __init__(self, body: Validated[RigidBody2D | RigidBody3D], torque: Callable | RealArrayLike):
        if not isinstance(body, _BODIES):
            raise TypeError(f"A torque acts on a RigidBody3D or RigidBody2D; got {type(body).__name__}.")
        self.body = body
        self.torque = _load_function(torque, "torque")

    def generalized(self, q: Vector, qd: Vector, t: RealScalarLike, args: Args) -> Vector:
        """``(∂ω/∂q̇)ᵀ τ`` with ``ω`` the world-axes angular velocity of the body."""
        load = jnp.asarray(self.torque(q, qd, t=t, args=args))
        frozen = jnp.asarray(t, q.dtype)

        body = self.body
        if isinstance(body, RigidBody3D):

            def spatial_velocity(v):
                (_, rotation), (_, rate) = jax.jvp(lambda x: body.position(x, frozen, args), (q,), (v,))
                return _world_rate(rotation, rate)

            velocity = spatial_velocity
            shape = (3,)
        else:

            def planar_velocity(v):
                return jax.jvp(lambda x: jnp.asarray(self.body.pose(x, t=frozen, args=args)), (q,), (v,))[1][
                    2
                ]

            velocity = planar_velocity
            shape = ()
        if load.shape != shape:
            raise ValueError(
                f"The torque on a {type(self.body).__name__} must have shape {shape}; it has "
                f"shape {load.shape}."
            )
        return jax.linear_transpose(velocity, qd)(load.astype(q.dtype))[0]


def _depends_on_input(fn, x) -> bool:
    """Whether the output of ``fn(x)`` depends on ``x`` in its traced program (a structural
    test at trace time: no cost when the program runs). An equation with any live input makes
    all its outputs live (conservative for control flow and sub-programs)."""
    jaxpr = jax.make_jaxpr(fn)(x).jaxpr
    live = {id(v) for v in jaxpr.invars}
    for eqn in jaxpr.eqns:
        if any(not isinstance(v, jcore.Literal) and id(v) in live for v in eqn.invars):
            live.update(id(v) for v in eqn.outvars)
    return any(not isinstance(v, jcore.Literal) and id(v) in live for v in jaxpr.outvars)


def _world_rate(rotation, rate):
    w = rate @ rotation.T
    return 0.5 * jnp.stack([w[2, 1] - w[1, 2], w[0, 2] - w[2, 0], w[1, 0] - w[0, 1]])


def generalized_forces(*loads: Validated[Force | Torque | Sequence[Force | Torque]]) -> Callable:
    r"""``Q(q, qd, t, args) = Σ (∂ẋ_p/∂q̇)ᵀ F_p + Σ (∂ω/∂q̇)ᵀ τ``: pass it as ``System(forces=...)``.

    Each load is a `Force` or a `Torque` (or a sequence of them).
    """
    flat = []
    for load in loads:
        items = load if isinstance(load, (list, tuple)) else (load,)
        for item in items:
            if not isinstance(item, (Force, Torque)):
                raise TypeError(f"loads must be Force or Torque instances; got {type(item).__name__}.")
            flat.append(item)
    if not flat:
        raise ValueError("generalized_forces needs at least one Force or Torque.")
    flat = tuple(flat)

    def forces(q, qd, t=0.0, args=None):
        total = jnp.zeros_like(q)
        for item in flat:
            total = total + item.generalized(q, qd, t, args)
        return total

    return forces
