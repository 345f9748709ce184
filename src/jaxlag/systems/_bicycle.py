r"""The Whipple bicycle: four rigid bodies, two rolling wheels, built from jaxlag's pieces.

A genuine nonlinear model (not the published linear equations): the rear wheel ``R``, the rear
frame with rider ``B``, the front frame (fork and handlebar) ``H`` and the front wheel ``F`` are
[`RigidBody3D`][jaxlag.coordinates.RigidBody3D] bodies; the front wheel touches the ground by a holonomic
constraint and both wheels roll without slipping by velocity constraints
(`jaxlag.contact`). Its linearization about upright straight-ahead motion at speed ``v`` by
[`jaxlag.analysis.linearize`][jaxlag.analysis.linearize] is compared in the tests with the benchmark of
Meijaard,
Papadopoulos, Ruina and Schwab, *Linearized dynamics equations for the balance and steer of a
bicycle: a benchmark and review*, Proc. R. Soc. A 463 (2007) 1955–1982.

Parameters (``args``) are the benchmark's names and values, in its axes (x forward, y right,
z **down**, so heights are negative): ``w`` wheelbase, ``c`` trail, ``lam`` steer-axis tilt
from the vertical, ``g``; rear wheel ``rR``, ``mR``, ``IRxx`` (= ``IRzz``), ``IRyy``; rear body
centre of mass ``(xB, zB)``, ``mB``, ``IBxx``, ``IByy``, ``IBzz``, ``IBxz``; front frame
``(xH, zH)``, ``mH``, ``IHxx``, ``IHyy``, ``IHzz``, ``IHxz``; front wheel ``rF``, ``mF``,
``IFxx`` (= ``IFzz``), ``IFyy``. Internally the axes are x forward, y left, z up (``(x, y, z) ↦
(x, −y, −z)``, which flips the sign of the ``xz`` products of inertia).
"""

import math

import jax.numpy as jnp
from jaxtyping import Array, Complex, Float

from .. import contact
from .._custom_types import Args, RealScalarLike, Scalar
from .._system import System
from ..analysis._linearize import linearize
from ..coordinates import RigidBody3D, lagrangian_from_positions
from ..rotations import axis_angle_matrix, axis_rotation
from ._common import model, parameters

BENCHMARK = {
    "w": 1.02,
    "c": 0.08,
    "lam": math.pi / 10,
    "g": 9.81,
    "rR": 0.3,
    "mR": 2.0,
    "IRxx": 0.0603,
    "IRyy": 0.12,
    "xB": 0.3,
    "zB": -0.9,
    "mB": 85.0,
    "IBxx": 9.2,
    "IByy": 11.0,
    "IBzz": 2.8,
    "IBxz": 2.4,
    "xH": 0.9,
    "zH": -0.7,
    "mH": 4.0,
    "IHxx": 0.05892,
    "IHyy": 0.06,
    "IHzz": 0.00708,
    "IHxz": -0.00756,
    "rF": 0.35,
    "mF": 3.0,
    "IFxx": 0.1405,
    "IFyy": 0.28,
}

# Lean, steer and their rates among the state (q, q̇) of whipple_bicycle.
_LATERAL = (3, 5, 11, 13)


def _tensor(xx, yy, zz, xz):
    """Inertia tensor in z-up axes from the benchmark's z-down values (the xz product flips)."""
    zero = jnp.zeros_like(jnp.asarray(xx, float))
    return jnp.array([[xx, zero, -xz], [zero, yy, zero], [-xz, zero, zz]])


@model(BENCHMARK)
def whipple_bicycle() -> System:
    r"""The Whipple bicycle (benchmark parameters of Meijaard et al. 2007 by default).

    ``q = (x, y, ψ, φ, θ, δ, θ_R, θ_F)``: rear contact point on the ground, yaw, lean (roll),
    pitch of the rear frame, steer angle, rear and front wheel rotation angles. Axes x forward,
    y left, z up. The rear wheel's plane is ``R_z(ψ) R_x(φ)``, its centre ``r_R`` above the contact
    point along that plane; the rear frame is ``R_z(ψ) R_x(φ) R_y(θ)``; the front frame turns by
    ``δ`` about the steer axis (tilted back by ``lam``, meeting the ground ``c`` ahead of the front
    contact point in the reference configuration); each wheel spins about its axle (body y).

    Constraints: the front wheel touches the ground (holonomic, one row; multiplier = front normal
    force); both wheels roll without slipping (velocity constraints, rear then front, two rows each;
    multipliers = friction forces ``(F_x, F_y)`` in world axes). Three degrees of freedom in velocity
    (lean rate, steer rate, speed). Upright straight-ahead motion at speed ``v`` is
    `bicycle_upright_state`; its lean–steer eigenvalues are `bicycle_eigenvalues`.
    """

    def p_of(args):
        return parameters(whipple_bicycle, args)

    def lean(q):
        return axis_rotation("z", q[2]) @ axis_rotation("x", q[3])

    def rear_centre(q, args, leaning):
        ground = jnp.stack([q[0], q[1], jnp.zeros_like(q[0])])
        return ground + p_of(args)["rR"] * leaning[:, 2]

    def steer(q, args):
        lam = p_of(args)["lam"]
        axis = jnp.stack([-jnp.sin(lam), jnp.zeros_like(lam), jnp.cos(lam)])
        return axis_angle_matrix(axis, q[5])

    def rear_wheel(q, args):
        leaning = lean(q)
        return rear_centre(q, args, leaning), leaning @ axis_rotation("y", q[6])

    def rear_body(q, args):
        p = p_of(args)
        leaning = lean(q)
        frame = leaning @ axis_rotation("y", q[4])
        offset = jnp.stack([p["xB"], 0.0 * p["xB"], -p["zB"] - p["rR"]])
        return rear_centre(q, args, leaning) + frame @ offset, frame

    def front_frame(q, args, point):
        """World position of a front-frame point given in rear-frame coordinates at δ = 0
        (relative to the rear wheel centre), and the front frame's rotation."""
        p = p_of(args)
        leaning = lean(q)
        frame = leaning @ axis_rotation("y", q[4])
        turn = steer(q, args)
        pivot = jnp.stack([p["w"] + p["c"], 0.0 * p["w"], -p["rR"]])
        local = pivot + turn @ (point - pivot)
        return rear_centre(q, args, leaning) + frame @ local, frame @ turn

    def front_body(q, args):
        p = p_of(args)
        return front_frame(q, args, jnp.stack([p["xH"], 0.0 * p["xH"], -p["zH"] - p["rR"]]))

    def front_wheel(q, args):
        p = p_of(args)
        centre, rotation = front_frame(q, args, jnp.stack([p["w"], 0.0 * p["w"], p["rF"] - p["rR"]]))
        return centre, rotation @ axis_rotation("y", q[7])

    def wheel_inertia(xx, yy):
        return lambda a: jnp.stack(
            [jnp.asarray(p_of(a)[xx]), jnp.asarray(p_of(a)[yy]), jnp.asarray(p_of(a)[xx])]
        )

    def body_inertia(prefix):
        return lambda a: _tensor(*(p_of(a)[prefix + k] for k in ("xx", "yy", "zz", "xz")))

    def mass(name):
        return lambda a: p_of(a)[name]

    wheel_r = RigidBody3D(rear_wheel, mass("mR"), wheel_inertia("IRxx", "IRyy"))
    frame_b = RigidBody3D(rear_body, mass("mB"), body_inertia("IB"))
    frame_h = RigidBody3D(front_body, mass("mH"), body_inertia("IH"))
    wheel_f = RigidBody3D(front_wheel, mass("mF"), wheel_inertia("IFxx", "IFyy"))
    axle = (0.0, 1.0, 0.0)
    rear_rolls = contact.rolling_without_slipping(wheel_r, lambda a: p_of(a)["rR"], axis=axle)
    front_rolls = contact.rolling_without_slipping(wheel_f, lambda a: p_of(a)["rF"], axis=axle)

    def rolling(q, qd, args):
        return jnp.concatenate([rear_rolls(q, qd, 0.0, args), front_rolls(q, qd, 0.0, args)])

    return System(
        lagrangian_from_positions(
            None, gravity=lambda a: p_of(a)["g"], bodies=[wheel_r, frame_b, frame_h, wheel_f]
        ),
        holonomic=contact.contact_height(wheel_f, lambda a: p_of(a)["rF"], axis=axle),
        velocity_constraints=rolling,
    )


def bicycle_upright_state(
    speed: RealScalarLike, args: Args = None
) -> tuple[Float[Array, "8"], Float[Array, "8"]]:
    """``(q, q̇)`` of `whipple_bicycle` rolling upright and straight ahead at ``speed``:
    all coordinates zero (the reference configuration satisfies the front contact), ``ẋ = v``,
    wheel rates ``v/r_R`` and ``v/r_F``."""
    p = parameters(whipple_bicycle, args)
    v = jnp.asarray(speed, dtype=jnp.result_type(float))
    zero = jnp.zeros_like(v)
    q = jnp.zeros(8, v.dtype)
    qd = jnp.stack([v, zero, zero, zero, zero, zero, v / p["rR"], v / p["rF"]])
    return q, qd


def bicycle_eigenvalues(
    speed: RealScalarLike, args: Args = None, *, return_residual: bool = False
) -> Complex[Array, "4"] | tuple[Complex[Array, "4"], Scalar]:
    r"""Eigenvalues of the lean–steer motion of `whipple_bicycle` about upright
    straight-ahead motion at ``speed``, from [`jaxlag.analysis.linearize`][jaxlag.analysis.linearize] of the
    nonlinear
    model.

    The linearization's tangent-space matrix ``A_T`` (dimension 10) carries, besides the four
    lean–steer eigenvalues, six zeros from the cyclic coordinates (``x``, ``y``, ``ψ``, the wheel
    angles) and the speed. The lean–steer motion is the quotient: with ``S`` selecting
    ``(φ, δ, φ̇, δ̇)`` and ``E`` the tangent basis, ``S A E = A_lat S E`` (upright motion does not
    feel the cyclic coordinates or a change of speed at first order), so
    ``A_lat = (S A E)(S E)⁺``, whose eigenvalues (weave pair, capsize, castering) are returned,
    sorted by real part. With ``return_residual`` also ``‖S A E − A_lat S E‖``, which vanishes
    when the quotient exists. Works under ``jit``, ``vmap`` (over speeds) and ``grad``.
    """
    system = whipple_bicycle()
    q, qd = bicycle_upright_state(speed, args)
    lin = linearize(system, q, qd, args=args)
    select = jnp.asarray(_LATERAL)
    projected = lin.basis[select]  # S E (4 × 10)
    image = (lin.state_matrix @ lin.basis)[select]  # S A E
    lateral = image @ jnp.linalg.pinv(projected)
    values = jnp.linalg.eigvals(lateral)
    values = values[jnp.argsort(jnp.real(values))]
    if return_residual:
        return values, jnp.linalg.norm(image - lateral @ projected)
    return values


__all__ = ["BENCHMARK", "bicycle_eigenvalues", "bicycle_upright_state", "whipple_bicycle"]
