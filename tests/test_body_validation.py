r"""Rigid-body input is refused where no body can be, and coordinate singularities are named.

Each case was reproduced on the unchecked library first (what it did then is in the comment);
the tests check the message names the actual problem and its fix, eagerly (with the numbers)
and inside ``jit``/``vmap`` (static message). Runs that are refused stop before anything is
integrated, so the eager tests compile at most the small check program. Valid edge cases (a
massless gimbal, a thin rod, a flat lamina, a quaternion within the constraint tolerance, a
gimbal chain whose M stays regular at gimbal lock) must still pass.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
import jaxlag.systems as systems
from jaxlag import coordinates, loads, rotations

jax.config.update("jax_enable_x64", True)

TS = jnp.array([0.0, 0.1])
EULER_Q, EULER_QD = jnp.array([0.1, 0.5, 0.2]), jnp.array([0.3, 0.2, 1.0])


def free_body(pose, inertia=(1.0, 2.0, 2.5), mass=1.0, holonomic=None):
    body = coordinates.RigidBody3D(pose, mass=mass, inertia=inertia)
    return jl.System(coordinates.lagrangian_from_positions(None, bodies=[body]), holonomic=holonomic)


def euler_pose(q):
    return jnp.zeros(3), rotations.euler_matrix(q, "zxz")


def unit_quaternion():
    return rotations.quaternion_from_matrix(rotations.euler_matrix(EULER_Q, "zxz"))


# ----------------------------------------------------------------------------- mass
def test_negative_mass_is_refused_when_built_and_at_the_initial_state():
    # Before: a heavy top with m = −1 (I1 = 0.1, so M stays positive definite) started at θ = 0.3
    # and rose to θ = 0.23 after 1 s, with no error.
    with pytest.raises(ValueError, match=r"mass m = -1: a mass must be finite and ≥ 0"):
        coordinates.RigidBody3D(euler_pose, mass=-1.0, inertia=jnp.ones(3))
    with pytest.raises(ValueError, match=r"bodies\[0\] \(RigidBody3D\) mass .* m = -1.*rises"):
        jl.simulate(
            systems.heavy_top("euler"), [0.0, 0.3, 0.0], [0.0, 0.0, 50.0], TS, args={"m": -1.0, "I1": 0.1}
        )
    with pytest.raises(ValueError, match="mass m = -0.5"):
        coordinates.RigidBody2D(lambda q: q, mass=-0.5, inertia=1.0)
    with pytest.raises(ValueError, match=r"point masses must be finite and ≥ 0; got masses\[1\] = -2"):
        coordinates.lagrangian_from_positions(lambda q: q.reshape(2, 2), masses=jnp.array([1.0, -2.0]))
    # m = 0 is a body that only turns about its fixed centre (the gyroscope's gimbals): accepted
    coordinates.RigidBody3D(euler_pose, mass=0.0, inertia=jnp.ones(3))


@pytest.mark.parametrize("mode", ("jit", "vmap"))
def test_negative_mass_under_jit_and_vmap(mode):
    top = systems.heavy_top("euler")
    q, qd = jnp.array([0.0, 0.3, 0.0]), jnp.array([0.0, 0.0, 50.0])

    def accelerations(m):
        return top.accelerations(q, qd, args={"m": m, "I1": 0.1})

    run = jax.jit(accelerations) if mode == "jit" else jax.vmap(accelerations)
    m = jnp.array(-1.0) if mode == "jit" else jnp.array([1.0, -1.0])
    with pytest.raises(Exception, match=r"bodies\[0\] \(RigidBody3D\) mass must be finite and ≥ 0"):
        jax.block_until_ready(run(m))
    if mode == "jit":  # the initial-state check of simulate, compiled in
        simulate = jax.jit(lambda m: jl.simulate(top, q, qd, TS, args={"m": m, "I1": 0.1}).q)
        with pytest.raises(Exception, match=r"bodies\[0\] \(RigidBody3D\) mass must be finite"):
            jax.block_until_ready(simulate(jnp.array(-1.0)))
    # a body built inside jit from a traced constant carries the check with it
    build = jax.jit(lambda m: coordinates.RigidBody3D(euler_pose, mass=m, inertia=jnp.ones(3)).mass)
    with pytest.raises(Exception, match="RigidBody3D mass must be finite and ≥ 0"):
        jax.block_until_ready(build(jnp.array(-1.0)))
    assert float(build(jnp.array(2.0))) == 2.0


# ----------------------------------------------------------------------------- inertia
@pytest.mark.parametrize("form", ("euler", "quaternion", "matrix"))
def test_triangle_inequality_is_refused_in_every_form(form):
    # Before: (1, 1, 3) ran silently in Euler and quaternion form and was refused as "Lagrangian
    # degenerate" in matrix form. Now every form gives the same message.
    body = systems.torque_free_body(form)
    q0 = {"euler": EULER_Q, "quaternion": unit_quaternion(), "matrix": jnp.eye(3).ravel()}[form]
    with pytest.raises(
        ValueError, match=r"principal moments \[1.0, 1.0, 3.0\] violate the triangle inequality"
    ):
        jl.simulate(body, q0, jnp.zeros_like(q0), TS, args={"I1": 1.0, "I2": 1.0, "I3": 3.0})


def test_inertia_tensor_checks_and_accepted_limits():
    # Before: a non-symmetric tensor was accepted and only its symmetric part acted.
    asymmetric = jnp.array([[1.0, 0.5, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 2.5]])
    with pytest.raises(ValueError, match=r"not symmetric: I\[0, 1\] = 0.5 but I\[1, 0\] = 0"):
        coordinates.RigidBody3D(euler_pose, 1.0, asymmetric)
    with pytest.raises(ValueError, match="include a negative one"):
        coordinates.RigidBody3D(euler_pose, 1.0, jnp.array([-1.0, 2.0, 2.5]))
    with pytest.raises(ValueError, match="triangle inequality"):
        coordinates.RigidBody3D(euler_pose, 1.0, jnp.diag(jnp.array([1.0, 1.0, 3.0])))
    with pytest.raises(ValueError, match="moment of inertia I = -1"):
        coordinates.RigidBody2D(lambda q: q, mass=1.0, inertia=-1.0)
    # a function of args is checked at the initial state
    system = free_body(euler_pose, inertia=lambda a: a["I"])
    with pytest.raises(ValueError, match=r"bodies\[0\] \(RigidBody3D\) inertia .*not symmetric"):
        jl.simulate(system, EULER_Q, EULER_QD, TS, args={"I": asymmetric})
    # limits a real body reaches: a thin rod (I3 = 0), a lamina (I3 = I1 + I2 exactly, also when
    # rotated into a full tensor: round-off stays within the √ε tolerance)
    coordinates.RigidBody3D(euler_pose, 1.0, jnp.array([1.0, 1.0, 0.0]))
    rotation = rotations.euler_matrix(jnp.array([0.3, 1.1, -0.4]))
    coordinates.RigidBody3D(euler_pose, 1.0, rotation @ jnp.diag(jnp.array([0.1, 0.2, 0.3])) @ rotation.T)


# ----------------------------------------------------------------------------- pose
@pytest.mark.parametrize(
    "matrix, text",
    [
        (lambda r: 1.2 * r, r"not orthonormal: max \|RᵀR − I\| = 0.44 .*det R = 1.728"),
        (lambda r: r @ jnp.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "not orthonormal"),
        (lambda r: r @ jnp.diag(jnp.array([1.0, 1.0, -1.0])), r"a reflection \(det R < 0\)"),
    ],
    ids=("scaled", "sheared", "reflected"),
)
def test_pose_must_be_a_rotation_at_the_initial_state(matrix, text):
    # Before: a pose returning 1.2 R ran silently and ended 2.2 rad off the true motion.
    system = free_body(lambda q: (jnp.zeros(3), matrix(rotations.euler_matrix(q, "zxz"))))
    with pytest.raises(ValueError, match=text + ".*Build it with jaxlag.rotations"):
        jl.simulate(system, EULER_Q, EULER_QD, TS)


def test_quaternion_body_needs_its_constraint():
    # Before: without |q|² = 1 the body drifted to |q| = 4.3 in 10 s (1.63 in the run).
    def pose(q):
        return jnp.zeros(3), rotations.quaternion_matrix(q)

    q0, qd0 = unit_quaternion(), jnp.array([0.3, 0.2, 1.0, 0.1])
    with pytest.raises(ValueError, match=r"leaves the rotation group.*\|q\|² − 1 = 0.*holonomic="):
        jl.simulate(free_body(pose), q0, qd0, TS)
    with pytest.raises(Exception, match="leaves the rotation group"):
        jax.block_until_ready(jax.jit(free_body(pose).accelerations)(q0, qd0))
    # with the constraint, and a state within its tolerance of the unit sphere, it runs
    unit = free_body(pose, holonomic=lambda q: jnp.reshape(q @ q - 1.0, (1,)))
    qd0 = qd0 - (qd0 @ q0) * q0  # tangent to the sphere
    off = q0 * (1.0 + 2e-9)
    acc = unit.accelerations(off, qd0)
    assert np.all(np.isfinite(acc))


# ----------------------------------------------------------------------------- points and loads
def test_body_offsets_of_the_wrong_shape_name_the_expected_shape():
    # Before: TypeError "dot_general requires contracting dimensions to have the same shape".
    body = coordinates.RigidBody3D(euler_pose, 1.0, jnp.ones(3))
    with pytest.raises(ValueError, match=r"body coordinates r, shape \(3,\); got shape \(2,\)"):
        body.point_position(EULER_Q, jnp.ones(2))
    with pytest.raises(ValueError, match=r"shape \(3,\); got shape \(2,\)"):
        body.point_velocity(EULER_Q, EULER_QD, jnp.ones(2))
    with pytest.raises(ValueError, match=r"\(RigidBody3D, r\) takes r in body coordinates, shape \(3,\)"):
        loads.Force((body, jnp.ones(2)), jnp.ones(3))
    planar = coordinates.RigidBody2D(lambda q: q, 1.0, 1.0)
    with pytest.raises(ValueError, match=r"shape \(2,\); got shape \(3,\)"):
        loads.Force((planar, jnp.ones(3)), jnp.ones(2))


def test_force_at_a_point_that_does_not_move_with_q_is_refused():
    # Before: exactly 0, silently. δx = 0 for a point fixed in space (or on a path x(t)).
    fixed = loads.generalized_forces(loads.Force(lambda q: jnp.array([1.0, 0.0, 0.0]), jnp.ones(3)))
    with pytest.raises(ValueError, match="does not depend on q.*exactly 0.*Force\\(\\(body, r\\), F\\)"):
        fixed(EULER_Q, EULER_QD)
    moving = loads.generalized_forces(loads.Force(lambda q, t: jnp.array([t, 0.0, 0.0]), jnp.ones(3)))
    with pytest.raises(ValueError, match="does not depend on q"):
        jax.jit(moving)(EULER_Q, EULER_QD, 1.0)
    # a point that moves with q is fine: Q = (∂x/∂q)ᵀ F
    attached = loads.generalized_forces(loads.Force(lambda q: q, jnp.array([1.0, 2.0, 3.0])))
    assert np.allclose(attached(EULER_Q, EULER_QD), [1.0, 2.0, 3.0], rtol=0, atol=0)


# ----------------------------------------------------------------------------- singularities
def test_gimbal_lock_is_named_with_the_fix():
    # Before: "M singular ... The Lagrangian is degenerate: every coordinate needs a kinetic term".
    top = systems.heavy_top("euler")
    with pytest.raises(ValueError) as info:
        jl.simulate(top, [0.0, 0.0, 0.0], [0.0, 0.0, 50.0], TS)
    text = str(info.value)
    assert "not because the Lagrangian lacks a kinetic term" in text
    assert "q̇ ∝ [0.707107, 0.0, -0.707107]" in text  # φ̇ = −ψ̇: both spin about the vertical
    assert "euler_matrix(angles, 'zxz')" in text and "a₂ = 0 or π" in text and "(gimbal lock)" in text
    assert "quaternion" in text and "gimbal_lock_margin" in text
    yaw_pitch_roll = free_body(lambda q: (jnp.zeros(3), rotations.euler_matrix(q, "zyx")))
    with pytest.raises(ValueError, match=r"'zyx'.*a₂ = ±π/2.*middle angle is 1.5708.*gimbal lock"):
        jl.simulate(yaw_pitch_roll, [0.1, np.pi / 2, 0.2], EULER_QD, TS)
    # compiled: the static message names coordinate singularities next to a degenerate L
    with pytest.raises(Exception, match="Euler angles at gimbal lock.*quaternion body"):
        jax.block_until_ready(jax.jit(top.accelerations)(jnp.zeros(3), jnp.array([0.0, 0.0, 50.0])))


def test_gimbal_lock_with_a_regular_mass_matrix_is_not_refused():
    # The gyroscope's gimbals carry inertia: at β = 0 the rotor's angles α, γ turn about one
    # axis, but the outer gimbal gives α its own kinetic term, so M is regular and the motion
    # is well defined.
    gyro = systems.gyroscope()
    qd = jnp.array([0.5, 0.0, 30.0])
    acc = gyro.accelerations(jnp.zeros(3), qd)
    assert np.all(np.isfinite(acc))
    margin = rotations.gimbal_lock_margin(jnp.array([0.1, 0.0, 0.2]), "zxz")
    assert float(margin) == 0.0
    assert np.isclose(float(rotations.gimbal_lock_margin(jnp.array([0.1, 0.3, 0.2]), "zyx")), np.cos(0.3))


def test_batch_members_are_checked_with_their_own_parameters():
    # simulate_batch returns every member's checks to the host (no callback in the program):
    # the member with m = −1 is named, with its number. Before: it ran (the top rose).
    pendulum = systems.simple_pendulum()
    with pytest.raises(ValueError, match=r"1 of 2 batch members failed .*member \[1\].*masses\[0\] = -1"):
        jl.simulate_batch(
            pendulum,
            jnp.array([[0.3], [0.3]]),
            jnp.zeros((2, 1)),
            TS,
            args={"m": jnp.array([1.0, -1.0])},
            args_axes=0,
        )
