"""Rolling and skating: the vertical rolling disk, a disk rolling down an incline, the knife edge.

Rolling without slipping and skating are velocity constraints ``A(q) q̇ = 0`` (nonholonomic,
multipliers ``μ``) except on a straight incline, where rolling integrates to ``s = R θ``.
"""

import jax.numpy as jnp

from .._system import System
from ..coordinates import RigidBody2D, lagrangian_from_positions
from ._common import model, parameters


@model({"m": 1.0, "R": 1.0})
def rolling_disk() -> System:
    r"""A uniform vertical disk (mass ``m``, radius ``R``) rolling without slipping on a horizontal plane.

    ``q = (x, y, φ, θ)``: contact point, heading (the direction ``(cos φ, sin φ)`` it rolls in)
    and rolling angle. ``L = ½ m (ẋ² + ẏ²) + ½ I θ̇² + ½ J φ̇²`` with ``I = ½ m R²`` (about the
    axle) and ``J = ¼ m R²`` (about a diameter); rolling: ``ẋ = R θ̇ cos φ``, ``ẏ = R θ̇ sin φ``.

    ``θ̇`` and ``φ̇`` stay constant: the contact point runs on a circle of radius
    ``R θ̇/φ̇`` (a line if ``φ̇ = 0``); the energy is conserved. Parameters: ``m``, ``R``.
    """

    def lagrangian(q, qd, args):
        p = parameters(rolling_disk, args)
        m, r = p["m"], p["R"]
        return (
            0.5 * m * (qd[0] ** 2 + qd[1] ** 2) + 0.25 * m * r**2 * qd[3] ** 2 + 0.125 * m * r**2 * qd[2] ** 2
        )

    def rolling(q, qd, args):
        r = parameters(rolling_disk, args)["R"]
        return jnp.stack([qd[0] - r * qd[3] * jnp.cos(q[2]), qd[1] - r * qd[3] * jnp.sin(q[2])])

    return System(lagrangian, velocity_constraints=rolling)


@model({"m": 1.0, "R": 1.0, "g": 9.81, "alpha": 0.5})
def disk_on_incline() -> System:
    r"""A uniform disk (mass ``m``, radius ``R``) rolling without slipping down an incline of angle
    ``alpha``.

    ``q = (s, θ)``: distance travelled down the slope and rotation angle; the disk is a
    [`RigidBody2D`][jaxlag.coordinates.RigidBody2D] with ``I = ½ m R²``:
    ``L = ½ m ṡ² + ¼ m R² θ̇² + m g s sin α``, rolling ``f = s − R θ = 0``.
    Closed forms: ``s̈ = ⅔ g sin α`` and ``λ = −⅓ m g sin α`` (the friction force, up the slope).
    Parameters: ``m``, ``R``, ``g``, ``alpha``.
    """

    def p_of(args):
        return parameters(disk_on_incline, args)

    def pose(q, args):
        a = p_of(args)["alpha"]
        return jnp.stack([q[0] * jnp.cos(a), -q[0] * jnp.sin(a), -q[1]])

    disk = RigidBody2D(
        pose, mass=lambda a: p_of(a)["m"], inertia=lambda a: 0.5 * p_of(a)["m"] * p_of(a)["R"] ** 2
    )

    def rolls(q, args):
        return jnp.reshape(q[0] - p_of(args)["R"] * q[1], (1,))

    return System(
        lagrangian_from_positions(None, gravity=lambda a: p_of(a)["g"], bodies=[disk]), holonomic=rolls
    )


@model({"m": 1.0, "I": 1.0, "g": 9.81, "alpha": 0.5})
def knife_edge() -> System:
    r"""A knife edge (skate) on an inclined plane of angle ``alpha`` (Neimark–Fufaev).

    ``q = (x, y, θ)``: contact point (``x`` down the slope, ``y`` across) and the blade's
    heading from the x axis; mass ``m``, moment of inertia ``I`` about the vertical through the
    contact point. ``L = ½ m (ẋ² + ẏ²) + ½ I θ̇² + m g sin α x``; the blade cannot slide
    sideways: ``−ẋ sin θ + ẏ cos θ = 0``.

    ``θ̇ = ω`` is constant; from rest at the origin with ``θ(0) = 0``,
    ``x = (g sin α / 2ω²) sin²ωt`` and ``y = (g sin α / 2ω²)(ωt − ½ sin 2ωt)``: the skate
    drifts across the slope instead of sliding down. Parameters: ``m``, ``I``, ``g``, ``alpha``.
    """

    def lagrangian(q, qd, args):
        p = parameters(knife_edge, args)
        return (
            0.5 * p["m"] * (qd[0] ** 2 + qd[1] ** 2)
            + 0.5 * p["I"] * qd[2] ** 2
            + p["m"] * p["g"] * jnp.sin(p["alpha"]) * q[0]
        )

    def blade(q, qd):
        return jnp.reshape(-qd[0] * jnp.sin(q[2]) + qd[1] * jnp.cos(q[2]), (1,))

    return System(lagrangian, velocity_constraints=blade)
