r"""Rigid bodies in space: the heavy symmetric top, the torque-free body, a gimballed gyroscope,
a disk rolling on a plane and a ball on a turntable.

All are built from [`RigidBody3D`][jaxlag.coordinates.RigidBody3D] (kinetic energy ``½ m|ẋ_c|² +
½ ωᵀIω`` by autodiff) and, for rolling, `jaxlag.contact`. World axes: z up. Euler angles are
the classical intrinsic ``"zxz"`` sequence ``(φ, θ, ψ)`` (precession, nutation, spin), singular
at ``θ = 0, π``; quaternions ``(w, x, y, z)`` carry ``|q|² − 1 = 0`` as a holonomic constraint
(its multiplier does no work) and pass through every orientation.

Parameters are checked at the initial state of a run (by the Lagrangian of
[`jaxlag.coordinates.lagrangian_from_positions`][jaxlag.coordinates.lagrangian_from_positions]): masses ``≥
0`` and principal moments
``≥ 0`` obeying the triangle inequality (for a symmetric top ``I3 ≤ 2 I1``; for
``torque_free_body`` each moment at most the sum of the other two). An
Euler-angle model started at gimbal lock (``θ = 0`` or ``π``) is refused with a message that
names it; the ``"quaternion"`` form has no such point.
"""

import jax.numpy as jnp

from .. import contact
from .._system import System
from ..coordinates import RigidBody3D, lagrangian_from_positions
from ..rotations import axis_rotation, euler_matrix, quaternion_matrix
from ._common import check_form, model, parameters

_ORIENTATION_FORMS = ("euler", "quaternion", "matrix")


def _orientation(form):
    """``q ↦ R`` for the orientation block of ``q`` and the holonomic constraints it needs."""
    if form == "euler":
        return (lambda q: euler_matrix(q[:3], "zxz")), None
    if form == "quaternion":
        return (lambda q: quaternion_matrix(q[:4])), (lambda q: jnp.reshape(q[:4] @ q[:4] - 1.0, (1,)))

    def orthonormal(q):
        r = q[:9].reshape(3, 3)
        gram = r.T @ r - jnp.eye(3, dtype=q.dtype)
        rows, cols = jnp.triu_indices(3)
        return gram[rows, cols]

    return (lambda q: q[:9].reshape(3, 3)), orthonormal


@model({"m": 1.0, "l": 0.25, "g": 9.81, "I1": 0.02, "I3": 0.01})
def heavy_top(form: str = "euler") -> System:
    r"""A heavy symmetric top with its tip fixed at the origin.

    Mass ``m``, centre of mass at distance ``l`` from the tip along the symmetry axis (body z),
    moments about the centre of mass ``I1`` (transverse) and ``I3`` (axial); gravity ``g``.

    Forms: ``"euler"``: ``q = (φ, θ, ψ)`` (``"zxz"``, θ the tilt of the axis from the vertical);
    ``"quaternion"``: ``q = (w, x, y, z)`` with ``|q|² = 1``; ``"matrix"``: the nine entries of
    ``R`` (row-major) with the six constraints ``RᵀR = I``.

    ``L = ½ I₁' (θ̇² + φ̇² sin²θ) + ½ I₃ (ψ̇ + φ̇ cos θ)² − m g l cos θ`` with ``I₁' = I1 + m l²``.
    Conserved: ``p_ψ = I₃ ω₃``, ``p_φ = I₁' φ̇ sin²θ + I₃ ω₃ cos θ`` (``ω₃ = ψ̇ + φ̇ cos θ``) and
    the energy. Steady precession at fixed θ: ``m g l = φ̇ (I₃ ω₃ − I₁' φ̇ cos θ)``.
    Parameters: ``m``, ``l``, ``g``, ``I1``, ``I3``.
    """
    check_form("heavy_top", form, _ORIENTATION_FORMS)
    orientation, holonomic = _orientation(form)

    def pose(q, args):
        rotation = orientation(q)
        return rotation @ jnp.array([0.0, 0.0, 1.0]) * parameters(heavy_top, args)["l"], rotation

    def inertia(args):
        p = parameters(heavy_top, args)
        return jnp.stack([jnp.asarray(p["I1"]), jnp.asarray(p["I1"]), jnp.asarray(p["I3"])])

    top = RigidBody3D(pose, mass=lambda a: parameters(heavy_top, a)["m"], inertia=inertia)
    lagrangian = lagrangian_from_positions(
        None, gravity=lambda a: parameters(heavy_top, a)["g"], bodies=[top]
    )
    return System(lagrangian, holonomic=holonomic)


@model({"I1": 2.0, "I2": 3.0, "I3": 4.0})
def torque_free_body(form: str = "euler") -> System:
    r"""A rigid body with principal moments ``(I1, I2, I3)`` (body x, y, z) turning freely about
    its fixed centre of mass.

    Forms as `heavy_top` (``"euler"``, ``"quaternion"``, ``"matrix"``). Conserved: the
    energy ``½ ωᵀIω`` and the angular momentum ``L = R I ω`` (world axes). Rotation about the
    axes of largest and smallest moment is stable, about the intermediate one unstable; a
    perturbed rotation at rate ``Ω`` about axis ``k`` (moments ``I_i``, ``I_j`` about the other two)
    wobbles at ``Ω √((I_k − I_i)(I_k − I_j)/(I_i I_j))`` in the body frame, or grows at the rate
    ``Ω √((I_k − I_i)(I_j − I_k)/(I_i I_j))`` for the intermediate axis.
    Parameters: ``I1``, ``I2``, ``I3``.
    """
    check_form("torque_free_body", form, _ORIENTATION_FORMS)
    orientation, holonomic = _orientation(form)

    def pose(q):
        return jnp.zeros(3, q.dtype), orientation(q)

    def inertia(args):
        p = parameters(torque_free_body, args)
        return jnp.stack([jnp.asarray(p[k]) for k in ("I1", "I2", "I3")])

    body = RigidBody3D(pose, mass=1.0, inertia=inertia)
    return System(lagrangian_from_positions(None, bodies=[body]), holonomic=holonomic)


@model(
    {
        "m": 1.0,
        "l": 0.25,
        "g": 9.81,
        "I1": 0.02,
        "I3": 0.01,
        "inner": (0.004, 0.002, 0.004),
        "outer": (0.006, 0.006, 0.004),
    }
)
def gyroscope() -> System:
    r"""A gyroscope in a Cardan suspension: a chain of three bodies turning about one point.

    ``q = (α, β, γ)``: the outer gimbal turns about the vertical (``R_o = R_z(α)``), the inner
    gimbal about the outer gimbal's x axis (``R_i = R_o R_x(β)``), the rotor about the inner
    gimbal's z axis (``R_r = R_i R_z(γ)``). The rotor (mass ``m``, moments ``I1``, ``I3`` about
    its centre of mass) has its centre of mass at distance ``l`` along its axis from the common
    centre; the gimbals (principal moments ``inner``, ``outer``, in their own axes) are centred.
    With massless gimbals it is `heavy_top` with ``(φ, θ, ψ) = (α, β, γ)``. Conserved:
    the energy, ``p_α`` and ``p_γ = I3 (γ̇ + α̇ cos β)``. Parameters: ``m``, ``l``, ``g``, ``I1``,
    ``I3``, ``inner``, ``outer``.
    """

    def p_of(args):
        return parameters(gyroscope, args)

    def outer_pose(q):
        return jnp.zeros(3, q.dtype), axis_rotation("z", q[0])

    def inner_pose(q):
        return jnp.zeros(3, q.dtype), axis_rotation("z", q[0]) @ axis_rotation("x", q[1])

    def rotor_pose(q, args):
        rotation = axis_rotation("z", q[0]) @ axis_rotation("x", q[1]) @ axis_rotation("z", q[2])
        return rotation[:, 2] * p_of(args)["l"], rotation

    def rotor_inertia(args):
        p = p_of(args)
        return jnp.stack([jnp.asarray(p["I1"]), jnp.asarray(p["I1"]), jnp.asarray(p["I3"])])

    bodies = [
        RigidBody3D(outer_pose, mass=0.0, inertia=lambda a: jnp.asarray(p_of(a)["outer"])),
        RigidBody3D(inner_pose, mass=0.0, inertia=lambda a: jnp.asarray(p_of(a)["inner"])),
        RigidBody3D(rotor_pose, mass=lambda a: p_of(a)["m"], inertia=rotor_inertia),
    ]
    return System(lagrangian_from_positions(None, gravity=lambda a: p_of(a)["g"], bodies=bodies))


@model({"m": 1.0, "R": 0.5, "g": 9.81})
def rolling_disk_3d() -> System:
    r"""A uniform thin disk (mass ``m``, radius ``R``) rolling without slipping on the plane
    ``z = 0``, free to lean, steer and fall.

    ``q = (x, y, z, φ, θ, ψ)``: centre and ``"zxz"`` Euler angles (axis ``n = R e_z``, θ its tilt
    from the vertical, ``θ = π/2`` upright). Inertia ``(¼, ¼, ½) m R²``.
    Holonomic: the lowest rim point touches the plane, ``z − R sin θ = 0`` (written with
    [`jaxlag.contact.contact_height`][jaxlag.contact.contact_height]); its multiplier is the normal force
    ``N``.
    Velocity constraints:
    [`jaxlag.contact.rolling_without_slipping`][jaxlag.contact.rolling_without_slipping], the contact point of
    the disk is at rest; the two multipliers are the friction force ``(F_x, F_y)`` on the disk.

    Steady rolling (θ, ``Ω = φ̇`` and ``s = ψ̇`` constant): with ``A = ¼ m R²``, ``C = ½ m R²``,
    ``(C + m R²) Ω (Ω cos θ + s) sin θ − A Ω² sin θ cos θ + m g R cos θ = 0``; the contact point
    runs on a circle of radius ``R s/Ω``, the centre on one of radius ``R (Ω cos θ + s)/Ω``,
    and the friction force is the centripetal force of the centre, ``N = m g``.
    Parameters: ``m``, ``R``, ``g``.
    """

    def p_of(args):
        return parameters(rolling_disk_3d, args)

    def pose(q):
        return q[:3], euler_matrix(q[3:6], "zxz")

    def inertia(args):
        p = p_of(args)
        return p["m"] * p["R"] ** 2 * jnp.array([0.25, 0.25, 0.5])

    disk = RigidBody3D(pose, mass=lambda a: p_of(a)["m"], inertia=inertia)
    radius = lambda a: p_of(a)["R"]  # noqa: E731
    return System(
        lagrangian_from_positions(None, gravity=lambda a: p_of(a)["g"], bodies=[disk]),
        holonomic=contact.contact_height(disk, radius),
        velocity_constraints=contact.rolling_without_slipping(disk, radius),
    )


@model({"m": 1.0, "R": 0.1, "Omega": 1.0, "k": 0.4})
def ball_on_turntable() -> System:
    r"""A ball rolling without slipping on a horizontal turntable spinning at ``Omega`` about the
    vertical through the origin.

    ``q = (x, y, w, a, b, c)``: the ball's centre (at height ``R``) and its orientation
    quaternion, with ``|q_{2:6}|² = 1``. Moment of inertia ``k m R²`` about any diameter
    (``k = 2/5`` a solid ball, ``2/3`` a thin shell). Rolling: the ball's contact point moves with
    the table, ``v_P = Ω e_z × P``
    ([`jaxlag.contact.rolling_without_slipping`][jaxlag.contact.rolling_without_slipping] with a
    ``surface_velocity``); the multipliers are the friction force.

    Closed form: the centre moves on a circle at the angular rate ``k Ω/(1 + k)`` (``2Ω/7`` for a
    solid ball), whatever the initial velocity; the circle's centre is fixed.
    Parameters: ``m``, ``R``, ``Omega``, ``k``.
    """

    def p_of(args):
        return parameters(ball_on_turntable, args)

    def pose(q, args):
        centre = jnp.stack([q[0], q[1], jnp.asarray(p_of(args)["R"], q.dtype)])
        return centre, quaternion_matrix(q[2:6])

    def inertia(args):
        p = p_of(args)
        return p["k"] * p["m"] * p["R"] ** 2 * jnp.ones(3)

    def table(point, args):
        omega = p_of(args)["Omega"]
        return jnp.stack([-omega * point[1], omega * point[0], jnp.zeros_like(point[2])])

    ball = RigidBody3D(pose, mass=lambda a: p_of(a)["m"], inertia=inertia)
    return System(
        lagrangian_from_positions(None, bodies=[ball]),
        holonomic=lambda q: jnp.reshape(q[2:6] @ q[2:6] - 1.0, (1,)),
        velocity_constraints=contact.rolling_without_slipping(
            ball, lambda a: p_of(a)["R"], shape="sphere", surface_velocity=table
        ),
    )
