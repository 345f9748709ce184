r"""Rigid bodies in space: rotations, ``RigidBody3D``, loads at points, rolling contact, closed loops.

Expected values are closed forms derived in the comments (or published values), never outputs of
the code under test. Integrations use the library default ``PIDController(rtol=1e-10,
atol=1e-10)``; over the ≤ 1.5 s horizons here the global error stays near 1e-9, so trajectories
are compared at 1e-7 and conserved quantities at 1e-8 relative. Runs whose initial state is built
exactly on the constraint manifold skip the initial-state check and, where the constraint residual
is not the point of the test, the per-step projection (fewer compiled pieces, shorter tests).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxlag as jl
import jaxlag.systems as systems
from jaxlag import analysis, contact, coordinates, loads, rotations

jax.config.update("jax_enable_x64", True)

FAST = {"checks": jl.Checks(initial_state=False), "projection": None}


def euler_to_quaternion_state(angles, rates):
    """Quaternion and its rate for the ``"zxz"`` state (angles, rates): one jvp."""

    def to_quaternion(a):
        return rotations.quaternion_from_matrix(rotations.euler_matrix(a, "zxz"))

    return jax.jvp(to_quaternion, (angles,), (rates,))


# ----------------------------------------------------------------------------- rotations
angles3 = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3)


@settings(max_examples=15, deadline=None)
@given(angles3, st.sampled_from(["zxz", "zyx", "xyz", "yzy", "xzx"]))
def test_euler_matrices_are_rotations_and_compose(angles, sequence):
    a = jnp.asarray(angles)
    r = rotations.euler_matrix(a, sequence)
    assert np.allclose(r.T @ r, np.eye(3), atol=1e-14) and np.isclose(np.linalg.det(r), 1.0)
    # intrinsic a1 a2 a3 about s1 s2 s3 = extrinsic a3 a2 a1 about s3 s2 s1
    extrinsic = rotations.euler_matrix(a[::-1], sequence[::-1], extrinsic=True)
    assert np.allclose(r, extrinsic, atol=1e-14)
    # the quaternion of R gives R back; axis-angle of that quaternion gives R too
    q = rotations.quaternion_from_matrix(r)
    assert np.isclose(float(q @ q), 1.0, atol=1e-14)
    assert np.allclose(rotations.quaternion_matrix(q), r, atol=1e-13)
    half = jnp.arccos(jnp.clip(q[0], -1.0, 1.0))
    if float(jnp.sin(half)) > 1e-3:
        assert np.allclose(rotations.axis_angle_matrix(q[1:], 2 * half), r, atol=1e-12)


def test_elementary_rotations_and_yaw_pitch_roll():
    # R_z(π/2) e_x = e_y (right-handed); yaw–pitch–roll is R_z(yaw) R_y(pitch) R_x(roll)
    assert np.allclose(
        rotations.axis_rotation("z", np.pi / 2) @ jnp.array([1.0, 0, 0]), [0, 1, 0], atol=1e-15
    )
    y, p, r = 0.3, -0.2, 0.7
    expected = (
        rotations.axis_rotation("z", y) @ rotations.axis_rotation("y", p) @ rotations.axis_rotation("x", r)
    )
    assert np.allclose(rotations.euler_matrix(jnp.array([y, p, r]), "zyx"), expected, atol=1e-15)
    # Rodrigues about z equals the elementary rotation
    assert np.allclose(
        rotations.axis_angle_matrix(jnp.array([0, 0, 2.0]), 0.4),
        rotations.axis_rotation("z", 0.4),
        atol=1e-15,
    )
    assert np.allclose(rotations.unskew(rotations.skew(jnp.array([1.0, -2.0, 3.0]))), [1, -2, 3])


def test_rotation_errors_are_clear():
    with pytest.raises(ValueError, match="sequence"):
        rotations.euler_matrix(jnp.zeros(3), "zzx")
    with pytest.raises(ValueError, match="shape \\(3,\\)"):
        rotations.euler_matrix(jnp.zeros(2), "zxz")
    with pytest.raises(ValueError, match="\\(w, x, y, z\\)"):
        rotations.quaternion_matrix(jnp.zeros(3))
    with pytest.raises(ValueError, match="frame"):
        rotations.angular_velocity(
            lambda q: rotations.euler_matrix(q), jnp.zeros(3), jnp.zeros(3), frame="inertial"
        )


def test_angular_velocity_of_euler_angles_closed_form():
    # zxz: ω_body = (φ̇ sinθ sinψ + θ̇ cosψ, φ̇ sinθ cosψ − θ̇ sinψ, φ̇ cosθ + ψ̇)  (Goldstein 4.87)
    q = jnp.array([0.3, 0.8, -1.1])
    qd = jnp.array([0.7, -0.4, 2.5])
    ph, th, ps = q
    phd, thd, psd = qd
    body = [
        phd * jnp.sin(th) * jnp.sin(ps) + thd * jnp.cos(ps),
        phd * jnp.sin(th) * jnp.cos(ps) - thd * jnp.sin(ps),
        phd * jnp.cos(th) + psd,
    ]

    def orientation(x):
        return rotations.euler_matrix(x, "zxz")

    assert np.allclose(rotations.angular_velocity(orientation, q, qd), body, atol=1e-14)
    world = rotations.angular_velocity(orientation, q, qd, frame="world")
    assert np.allclose(world, orientation(q) @ jnp.asarray(body), atol=1e-14)
    # world ω of zxz: φ̇ e_z + θ̇ (line of nodes) + ψ̇ n
    nodes = rotations.axis_rotation("z", ph) @ jnp.array([1.0, 0, 0])
    axis = orientation(q)[:, 2]
    assert np.allclose(world, phd * jnp.array([0, 0, 1.0]) + thd * nodes + psd * axis, atol=1e-14)
    # time-dependent orientation: R = R_z(Ω t) R(q) adds Ω e_z in world axes
    spin = 0.9

    def turning(x, t):
        return rotations.axis_rotation("z", spin * t) @ orientation(x)

    moving = rotations.angular_velocity(turning, q, qd, 0.0, frame="world")
    assert np.allclose(moving, world + jnp.array([0, 0, spin]), atol=1e-14)


def test_rotations_under_jit_vmap_grad():
    angles = jnp.array([[0.1, 0.2, 0.3], [1.0, -0.5, 2.0]])
    batched = jax.jit(jax.vmap(lambda a: rotations.euler_matrix(a, "zyx")))(angles)
    assert batched.shape == (2, 3, 3)
    quats = jax.vmap(rotations.quaternion_from_matrix)(batched)
    assert np.allclose(jax.vmap(rotations.quaternion_matrix)(quats), batched, atol=1e-13)
    # d/dθ of R_x(θ)[1, 1] = −sin θ
    grad = jax.grad(lambda a: rotations.euler_matrix(a, "xyz")[1, 1])(jnp.array([0.4, 0.0, 0.0]))
    assert np.isclose(grad[0], -np.sin(0.4), atol=1e-14)
    # the derivative of ω wrt a rate is the matrix's column (ω is linear in q̇): finite difference
    q, qd = jnp.array([0.3, 0.8, -1.1]), jnp.array([0.7, -0.4, 2.5])
    omega = jax.jit(lambda x, v: rotations.angular_velocity(lambda y: rotations.euler_matrix(y), x, v)[2])
    g = jax.grad(omega, argnums=0)(q, qd)
    h = 1e-6
    fd = [(omega(q + h * e, qd) - omega(q - h * e, qd)) / (2 * h) for e in jnp.eye(3)]
    assert np.allclose(g, fd, atol=1e-8)


# ----------------------------------------------------------------------------- RigidBody3D
def test_rigid_body_kinetic_energy_matches_hand_formulas():
    m, inertia = 2.0, jnp.array([[0.3, 0.02, -0.01], [0.02, 0.4, 0.03], [-0.01, 0.03, 0.5]])

    def pose(q):
        return q[:3], rotations.euler_matrix(q[3:], "zyx")

    body = coordinates.RigidBody3D(pose, mass=m, inertia=inertia)
    q = jnp.array([0.1, -0.3, 0.7, 0.4, -0.2, 1.2])
    qd = jnp.array([0.5, 0.2, -0.4, 1.1, -0.7, 0.3])
    omega = rotations.angular_velocity(lambda x: rotations.euler_matrix(x[3:], "zyx"), q, qd)
    expected = 0.5 * m * qd[:3] @ qd[:3] + 0.5 * omega @ inertia @ omega
    kinetic = coordinates.kinetic_energy_from_positions(None, bodies=[body])
    assert np.isclose(kinetic(q, qd), expected, rtol=1e-14)
    # angular momentum about the centre of mass, world axes: R I ω_body
    rotation = pose(q)[1]
    assert np.allclose(body.angular_momentum(q, qd), rotation @ inertia @ omega, atol=1e-14)
    # a body point's velocity: v + ω_world × (R r)
    r = jnp.array([0.2, -0.1, 0.3])
    expected_v = qd[:3] + jnp.cross(rotation @ omega, rotation @ r)
    assert np.allclose(body.point_velocity(q, qd, r), expected_v, atol=1e-14)
    # gravity: V = m g z_c
    lagrangian = coordinates.lagrangian_from_positions(None, gravity=9.81, bodies=[body])
    assert np.isclose(lagrangian(q, qd), expected - m * 9.81 * q[2], rtol=1e-14)


def test_rigid_body_on_a_turning_support_has_the_time_derivative_terms():
    # pose(q, t) = R_z(Ωt)·(x(q), R(q)): T uses ẋ_c and Ṙ including ∂/∂t (one jvp along (q̇, 1))
    spin, m, inertia = 0.8, 1.5, jnp.array([0.2, 0.3, 0.4])

    def pose(q, t):
        turn = rotations.axis_rotation("z", spin * t)
        return turn @ q[:3], turn @ rotations.euler_matrix(q[3:], "zyx")

    body = coordinates.RigidBody3D(pose, mass=m, inertia=inertia)
    q = jnp.array([0.1, -0.3, 0.7, 0.4, -0.2, 1.2])
    qd = jnp.array([0.5, 0.2, -0.4, 1.1, -0.7, 0.3])
    t = 0.6
    x_dot = jax.jvp(lambda x, s: pose(x, s)[0], (q, jnp.asarray(t)), (qd, jnp.asarray(1.0)))[1]
    omega = rotations.angular_velocity(lambda x, t: pose(x, t)[1], q, qd, t)
    expected = 0.5 * m * x_dot @ x_dot + 0.5 * omega @ (inertia * omega)
    assert np.isclose(body.kinetic_energy(q, qd, t, None), expected, rtol=1e-14)


@settings(max_examples=10, deadline=None)
@given(st.lists(st.floats(-2.0, 2.0), min_size=6, max_size=6))
def test_force_at_point_is_jacobian_transpose(values):
    # Q = (∂x_p/∂q)ᵀ F: against the dense Jacobian, for random states and forces
    body = coordinates.RigidBody3D(lambda q: (q[:3], rotations.euler_matrix(q[3:], "zxz")), 1.0, jnp.ones(3))
    q = jnp.asarray(values)
    point, force = jnp.array([0.3, -0.1, 0.2]), jnp.array(values[:3]) + 1.0
    jacobian = jax.jacfwd(lambda x: body.point_position(x, point))(q)
    forces = loads.generalized_forces(loads.Force((body, point), force))
    assert np.allclose(forces(q, jnp.zeros(6)), jacobian.T @ force, atol=1e-13)


def test_rigid_body_errors_are_clear():
    bad = coordinates.RigidBody3D(lambda q: (q[:3], jnp.eye(2)), mass=1.0, inertia=jnp.ones(3))
    with pytest.raises(ValueError, match="\\(3, 3\\)"):
        bad.kinetic_energy(jnp.zeros(3), jnp.zeros(3), 0.0, None)
    with pytest.raises(ValueError, match="principal moments"):  # refused when the body is built
        coordinates.RigidBody3D(lambda q: (q[:3], jnp.eye(3)), 1.0, jnp.ones(2))
    wrong_inertia = coordinates.RigidBody3D(lambda q: (q[:3], jnp.eye(3)), 1.0, lambda a: jnp.ones(2))
    with pytest.raises(ValueError, match="principal moments"):
        wrong_inertia.kinetic_energy(jnp.zeros(3), jnp.zeros(3), 0.0, None)
    with pytest.raises(TypeError, match="RigidBody2D or RigidBody3D"):
        coordinates.lagrangian_from_positions(None, bodies=[object()])


# ----------------------------------------------------------------------------- heavy top
TOP = {"m": 1.0, "l": 0.25, "g": 9.81, "I1": 0.02, "I3": 0.01}
I1P = TOP["I1"] + TOP["m"] * TOP["l"] ** 2  # transverse moment about the tip


@pytest.fixture(scope="module")
def top_euler():
    return systems.heavy_top("euler")


@pytest.fixture(scope="module")
def top_quaternion():
    return systems.heavy_top("quaternion")


def test_heavy_top_steady_precession(top_euler):
    # θ̈ = 0 at fixed θ: m g l = φ̇ (I3 ω3 − I1' φ̇ cos θ); the slow root for spin ω3
    theta, omega3 = 0.7, 150.0
    a, b, c = I1P * np.cos(theta), -TOP["I3"] * omega3, TOP["m"] * TOP["g"] * TOP["l"]
    precession = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
    q0 = jnp.array([0.0, theta, 0.0])
    qd0 = jnp.array([precession, 0.0, omega3 - precession * np.cos(theta)])
    ts = jnp.linspace(0.0, 1.0, 41)  # 41 saves in every heavy-top run: one compilation
    traj = jl.simulate(top_euler, q0, qd0, ts, args=TOP, **FAST)
    assert np.max(np.abs(traj.q[:, 1] - theta)) < 1e-8  # no nutation
    assert np.allclose(traj.q[:, 0], precession * ts, atol=1e-8)  # uniform precession


def test_heavy_top_conserved_quantities_and_forms_agree(top_euler, top_quaternion):
    q0, qd0 = jnp.array([0.2, 0.6, 0.1]), jnp.array([1.0, 0.5, 40.0])
    ts = jnp.linspace(0.0, 1.0, 41)
    euler = jl.simulate(top_euler, q0, qd0, ts, args=TOP, **FAST)
    th = euler.q[:, 1]
    omega3 = euler.qd[:, 2] + euler.qd[:, 0] * jnp.cos(th)
    p_psi = TOP["I3"] * omega3
    p_phi = I1P * euler.qd[:, 0] * jnp.sin(th) ** 2 + TOP["I3"] * omega3 * jnp.cos(th)
    assert np.allclose(euler.momenta[:, 2], p_psi, rtol=1e-12)  # the formulas are the momenta
    assert np.allclose(euler.momenta[:, 0], p_phi, rtol=1e-12)
    for series in (p_psi, p_phi, euler.energy):
        assert np.ptp(series) < 1e-8 * np.max(np.abs(series))
    assert np.ptp(th) > 0.01  # it does nutate
    # the quaternion form from the same initial state gives the same rotation matrices
    quaternion = jl.simulate(top_quaternion, *euler_to_quaternion_state(q0, qd0), ts, args=TOP, **FAST)
    r_quaternion = jax.vmap(rotations.quaternion_matrix)(quaternion.q)
    r_euler = jax.vmap(lambda a: rotations.euler_matrix(a, "zxz"))(euler.q)
    assert np.max(np.abs(r_quaternion - r_euler)) < 1e-7
    assert np.allclose(quaternion.energy, euler.energy[0], rtol=1e-8)


def test_heavy_top_quaternion_passes_through_gimbal_lock(top_quaternion):
    # With p_φ = p_ψ the axis can reach the vertical (θ = 0), where "zxz" is singular. Start at
    # θ = 0.3 falling towards the vertical with spin ω3: p_φ = p_ψ needs
    # φ̇ = I3 ω3 (1 − cos θ)/(I1' sin²θ).
    theta, omega3 = 0.3, 30.0
    phid = TOP["I3"] * omega3 * (1 - np.cos(theta)) / (I1P * np.sin(theta) ** 2)
    q0, qd0 = jnp.array([0.0, theta, 0.0]), jnp.array([phid, -3.0, omega3 - phid * np.cos(theta)])
    ts = jnp.linspace(0.0, 0.3, 41)  # same shape: no recompilation
    traj = jl.simulate(top_quaternion, *euler_to_quaternion_state(q0, qd0), ts, args=TOP, **FAST)
    axis = jax.vmap(rotations.quaternion_matrix)(traj.q)[:, :, 2]
    tilt = np.arccos(np.clip(np.asarray(axis[:, 2]), -1, 1))
    assert tilt.min() < 0.01 and tilt[-1] > 0.1  # through the vertical and beyond
    # the horizontal projection of the axis reverses: it went over the top
    assert float(axis[0, :2] @ axis[-1, :2]) < 0
    assert np.ptp(traj.energy) < 1e-8 * np.max(np.abs(traj.energy))
    # L_z (about the tip) and the spin L·n are conserved (gravity's torque is horizontal, ⟂ n)
    rotation = jax.vmap(rotations.quaternion_matrix)(traj.q)
    omega = jax.vmap(lambda q, v: rotations.angular_velocity(rotations.quaternion_matrix, q, v))(
        traj.q, traj.qd
    )
    inertia_tip = jnp.array([I1P, I1P, TOP["I3"]])
    momentum = jnp.einsum("tij,tj->ti", rotation, inertia_tip[None, :] * omega)
    assert np.ptp(momentum[:, 2]) < 1e-8 and np.ptp(TOP["I3"] * omega[:, 2]) < 1e-8
    assert np.max(np.abs(traj.constraint_residuals[0])) < 1e-9  # index-1 drift, no projection


def test_heavy_top_matrix_form_accelerations_match_euler(top_euler):
    # nine entries of R with RᵀR = I: R̈ equals d²/dt² R(φ, θ, ψ) of the Euler-angle motion
    matrix = systems.heavy_top("matrix")
    q, qd = jnp.array([0.2, 0.6, 0.1]), jnp.array([1.0, 0.5, 40.0])
    qdd = top_euler.accelerations(q, qd, args=TOP)

    def flat(a):
        return rotations.euler_matrix(a, "zxz").ravel()

    entries, rates = jax.jvp(flat, (q,), (qd,))
    second = jax.jvp(lambda x: jax.jvp(flat, (x,), (qd,))[1], (q,), (qd,))[1]
    second = second + jax.jvp(flat, (q,), (qdd,))[1]
    assert np.allclose(matrix.accelerations(entries, rates, args=TOP), second, rtol=1e-10, atol=1e-8)
    assert np.all(np.linalg.eigvalsh(matrix.mass_matrix(entries, rates, args=TOP)) > 0)


# ----------------------------------------------------------------------------- torque-free body
@pytest.fixture(scope="module")
def free_euler():
    return systems.torque_free_body("euler")


@pytest.mark.parametrize("moments", list(itertools.permutations((2.0, 3.0, 4.0))))
def test_torque_free_rotation_stability_from_linearize(free_euler, moments):
    # Steady rotation at rate Ω about world z with body y vertical: (φ, θ, ψ) = (Ωt, π/2, 0).
    # Spin moment I_s = I2, the others I_a = I1, I_b = I3. Wobble ω = Ω √((I_s−I_a)(I_s−I_b)/(I_a I_b));
    # for the intermediate axis that radicand is negative and −radicand gives the growth rate².
    a, s, b = moments
    spin = 1.3
    args = {"I1": a, "I2": s, "I3": b}
    lin = analysis.linearize(
        free_euler, jnp.array([0.0, np.pi / 2, 0.0]), jnp.array([spin, 0.0, 0.0]), args=args
    )
    radicand = (s - a) * (s - b) / (a * b)
    if s == 3.0:  # intermediate: unstable
        assert lin.stability() == "unstable"
        assert np.isclose(float(lin.growth_rate), spin * np.sqrt(-radicand), rtol=1e-10)
    else:
        assert float(lin.growth_rate) < 1e-9
        # the frequencies are the body-frame wobble and Ω itself (a world-fixed direction seen
        # from the body)
        assert np.any(np.isclose(np.asarray(lin.frequencies), spin * np.sqrt(radicand), rtol=1e-10))


def test_torque_free_body_conserves_angular_momentum_and_energy():
    system = systems.torque_free_body("quaternion")
    args = {"I1": 2.0, "I2": 3.0, "I3": 4.0}
    q0 = rotations.quaternion_from_matrix(rotations.euler_matrix(jnp.array([0.3, 1.0, -0.4])))
    omega0 = jnp.array([0.4, 2.0, 0.3])  # near the unstable axis
    # q̇ = ½ q ⊗ (0, ω_body)
    w, v = q0[0], q0[1:]
    qd0 = 0.5 * jnp.concatenate([-(v @ omega0)[None], w * omega0 + jnp.cross(v, omega0)])
    traj = jl.simulate(system, q0, qd0, jnp.linspace(0.0, 12.0, 61), args=args, **FAST)
    omega = jax.vmap(lambda q, qd: rotations.angular_velocity(rotations.quaternion_matrix, q, qd))(
        traj.q, traj.qd
    )
    assert np.allclose(omega[0], omega0, atol=1e-12)
    moments = jnp.array([2.0, 3.0, 4.0])
    world = jnp.einsum("tij,tj->ti", jax.vmap(rotations.quaternion_matrix)(traj.q), moments[None, :] * omega)
    assert np.max(np.abs(world - world[0][None, :])) < 1e-7 * np.linalg.norm(world[0])
    energy = 0.5 * jnp.sum(moments[None, :] * omega**2, axis=1)
    assert np.allclose(traj.energy, energy, rtol=1e-12)
    assert np.ptp(energy) < 1e-8 * energy[0]
    assert np.ptp(omega[:, 1]) > 1.0  # the intermediate axis flips


# ----------------------------------------------------------------------------- loads
def _top_body():
    def pose(q, args):
        rotation = rotations.euler_matrix(q, "zxz")
        return rotation @ jnp.array([0.0, 0.0, args["l"]]), rotation

    return coordinates.RigidBody3D(
        pose, mass=lambda a: a["m"], inertia=lambda a: jnp.stack([a["I1"], a["I1"], a["I3"]])
    )


def test_torque_generalized_forces_by_hand():
    # ω_world = φ̇ e_z + θ̇ (line of nodes) + ψ̇ n, so Q = (τ·e_z, τ·nodes, τ·n)
    body = _top_body()
    args = {"m": 1.0, "l": 0.25, "I1": 0.02, "I3": 0.01}
    q, qd = jnp.array([0.3, 0.8, -1.1]), jnp.array([0.7, -0.4, 2.5])
    tau = jnp.array([0.3, -0.2, 0.5])
    nodes = rotations.axis_rotation("z", q[0]) @ jnp.array([1.0, 0, 0])
    axis = rotations.euler_matrix(q, "zxz")[:, 2]
    expected = jnp.stack([tau[2], tau @ nodes, tau @ axis])
    forces = loads.generalized_forces(loads.Torque(body, tau))
    assert np.allclose(forces(q, qd, 0.0, args), expected, atol=1e-15)
    # time-dependent actuator: τ(t) = sin(t) e_z
    motor = loads.generalized_forces(loads.Torque(body, lambda q, qd, t: jnp.array([0, 0, jnp.sin(t)])))
    assert np.allclose(motor(q, qd, 0.7, args), np.sin(0.7) * np.array([1, 0, np.cos(q[1])]), atol=1e-15)


def test_force_at_point_equals_potential_and_dissipation():
    # a spring k to the anchor a and a damper c at the body point r, plus gravity as a force at the
    # centre of mass, against the same loads as V = ½k|x_p − a|² + m g z_c and R = ½c|ẋ_p|²
    body = _top_body()
    args = {"m": 1.0, "l": 0.25, "I1": 0.02, "I3": 0.01, "k": 30.0, "c": 0.4, "g": 9.81}
    point, anchor = jnp.array([0.05, 0.0, 0.3]), jnp.array([0.1, 0.2, 0.35])
    tip = (body, point)

    def spring(q, qd, args):
        return -args["k"] * (body.point_position(q, point, 0.0, args) - anchor)

    def damper(q, qd, args):
        return -args["c"] * body.point_velocity(q, qd, point, 0.0, args)

    weight = loads.Force((body, jnp.zeros(3)), lambda q, qd, args: jnp.array([0, 0, -args["m"] * args["g"]]))
    with_loads = jl.System(
        coordinates.lagrangian_from_positions(None, bodies=[body]),
        forces=loads.generalized_forces(loads.Force(tip, spring), loads.Force(tip, damper), weight),
    )

    def potential(q, args):
        stretch = body.point_position(q, point, 0.0, args) - anchor
        return 0.5 * args["k"] * stretch @ stretch

    def dissipation(q, qd, args):
        v = body.point_velocity(q, qd, point, 0.0, args)
        return 0.5 * args["c"] * v @ v

    by_potential = jl.System(
        coordinates.lagrangian_from_positions(
            None, potential=potential, gravity=lambda a: a["g"], bodies=[body]
        ),
        dissipation=dissipation,
    )
    rng = np.random.default_rng(0)
    for _ in range(4):
        q, qd = jnp.asarray(rng.uniform(0.3, 1.2, 3)), jnp.asarray(rng.normal(size=3))
        assert np.allclose(
            with_loads.accelerations(q, qd, args=args),
            by_potential.accelerations(q, qd, args=args),
            rtol=1e-12,
            atol=1e-12,
        )
    # equal accelerations at every state: the same vector field, hence the same motion (a
    # simulation of each would only re-test the integrator, at two more compilations)
    assert np.allclose(
        with_loads.input_power(q, qd, args=args),
        -by_potential.dissipated_power(q, qd, args=args)
        + qd @ jax.grad(lambda x: -potential(x, args))(q)
        - args["m"] * args["g"] * jax.jvp(lambda x: body.position(x, 0.0, args)[0][2], (q,), (qd,))[1],
        rtol=1e-12,
    )


def test_force_on_planar_body_and_position_map():
    # a pendulum rod (RigidBody2D) with a horizontal force F at its tip: Q_θ = F l cos θ;
    # the same force on the tip as a position map gives the same Q
    length = 0.8

    def pose(q):
        return jnp.stack([0.5 * length * jnp.sin(q[0]), -0.5 * length * jnp.cos(q[0]), q[0]])

    rod = coordinates.RigidBody2D(pose, mass=1.0, inertia=length**2 / 12)
    push = jnp.array([2.0, 0.0])
    on_body = loads.generalized_forces(loads.Force((rod, jnp.array([0.0, -0.5 * length])), push))
    on_map = loads.generalized_forces(
        loads.Force(lambda q: length * jnp.stack([jnp.sin(q[0]), -jnp.cos(q[0])]), push)
    )
    q, qd = jnp.array([0.4]), jnp.array([1.0])
    assert np.allclose(on_body(q, qd), 2.0 * length * np.cos(0.4), atol=1e-15)
    assert np.allclose(on_map(q, qd), on_body(q, qd), atol=1e-15)
    torque = loads.generalized_forces(loads.Torque(rod, 0.3))
    assert np.allclose(torque(q, qd), [0.3])
    with pytest.raises(ValueError, match="shape"):
        loads.generalized_forces(loads.Torque(rod, jnp.ones(3)))(q, qd)
    with pytest.raises(TypeError, match="Force or Torque"):
        loads.generalized_forces(push)


def test_loads_under_jit_vmap_grad():
    body = _top_body()
    args = {"m": 1.0, "l": 0.25, "I1": 0.02, "I3": 0.01}
    point = jnp.array([0.05, 0.0, 0.3])
    forces = loads.generalized_forces(
        loads.Force((body, point), lambda q, qd, args: args["k"] * jnp.array([1.0, 0.0, 0.0])),
        loads.Torque(body, jnp.array([0.0, 0.0, 0.2])),
    )
    qs = jnp.array([[0.1, 0.5, 0.2], [0.3, 0.9, -0.4]])
    out = jax.jit(jax.vmap(lambda q: forces(q, jnp.zeros(3), 0.0, {**args, "k": 2.0})))(qs)
    assert out.shape == (2, 3)
    # ∂Q/∂k is the force per unit k: Q(k=1)
    grad = jax.grad(lambda k: forces(qs[0], jnp.zeros(3), 0.0, {**args, "k": k})[1])(2.0)
    torque_part = forces(qs[0], jnp.zeros(3), 0.0, {**args, "k": 0.0})[1]
    assert np.isclose(grad, forces(qs[0], jnp.zeros(3), 0.0, {**args, "k": 1.0})[1] - torque_part)


# ----------------------------------------------------------------------------- rolling contact
DISK = {"m": 1.2, "R": 0.3, "g": 9.81}


def test_rolling_disk_steady_circle_no_slip_and_friction():
    # Steady rolling (derived from Newton–Euler, see rolling_disk_3d's docstring): with
    # A = ¼mR², C = ½mR², ω_n = Ω cos θ + s:
    # (C + mR²) Ω ω_n sin θ − A Ω² sin θ cos θ + m g R cos θ = 0.
    system = systems.rolling_disk_3d()
    m, radius, g = DISK["m"], DISK["R"], DISK["g"]
    big_a, big_c = 0.25 * m * radius**2, 0.5 * m * radius**2
    theta, omega = 1.2, 2.0
    omega_n = (big_a * omega**2 * np.sin(theta) * np.cos(theta) - m * g * radius * np.cos(theta)) / (
        (big_c + m * radius**2) * omega * np.sin(theta)
    )
    spin = omega_n - omega * np.cos(theta)
    # φ = ψ = 0: axis n = (0, −sin θ, cos θ), centre at height R sin θ moving with −R ω_n e_x
    q0 = jnp.array([0.0, 0.0, radius * np.sin(theta), 0.0, theta, 0.0])
    qd0 = jnp.array([-radius * omega_n, 0.0, 0.0, omega, 0.0, spin])
    ts = jnp.linspace(0.0, 1.5, 16)
    traj = jl.simulate(system, q0, qd0, ts, args=DISK, checks=jl.Checks(initial_state=False))
    assert np.max(np.abs(traj.q[:, 4] - theta)) < 1e-8  # constant lean
    assert np.allclose(traj.qd[:, 3], omega, atol=1e-8) and np.allclose(traj.qd[:, 5], spin, atol=1e-8)
    # the contact point runs on a circle of radius R s/Ω about O = P + e_z × V_P/Ω, V_P = −R s e_x
    disk = coordinates.RigidBody3D(lambda q: (q[:3], rotations.euler_matrix(q[3:6])), m, jnp.ones(3))
    points = jax.vmap(lambda q: contact.contact_point(disk, q, radius))(traj.q)
    centre = points[0] + jnp.cross(jnp.array([0, 0, 1.0]), jnp.array([-radius * spin, 0, 0])) / omega
    distance = jnp.linalg.norm(points[:, :2] - centre[None, :2], axis=1)
    assert np.allclose(distance, abs(radius * spin / omega), rtol=1e-8)
    assert np.max(np.abs(points[:, 2])) < 1e-12
    # no slip at round-off (projected each step)
    # (the saved-state quantities in one compiled function: fewer compilations than traj.<name>)
    residuals, normal, friction = jax.jit(
        jax.vmap(
            lambda x, v: (
                system.constraint_residuals(x, v, args=DISK),
                system.multipliers(x, v, args=DISK),
                system.velocity_multipliers(x, v, args=DISK),
            )
        )
    )(traj.q, traj.qd)
    f, f_dot, slip = residuals
    assert np.max(np.abs(slip)) < 1e-13 and np.max(np.abs(f)) < 1e-13
    # friction = centripetal force of the centre, m Ω e_z × v; the normal force = m g
    v = traj.qd[:, :2]
    assert np.allclose(friction, m * omega * jnp.stack([-v[:, 1], v[:, 0]], 1), atol=1e-8)
    assert np.allclose(normal[:, 0], m * g, rtol=1e-9)


def test_ball_on_turntable_circles_at_two_sevenths():
    # centre velocity turns at k Ω/(1 + k) (2Ω/7 for a solid ball): x(t) = O + Rot(ω_c t)(x0 − O)
    system = systems.ball_on_turntable()
    args = {"m": 0.5, "R": 0.1, "Omega": 3.0, "k": 0.4}
    x0, v0 = jnp.array([0.5, 0.0]), jnp.array([0.1, 0.4])
    table = args["Omega"] * jnp.array([-x0[1], x0[0]])
    # rolling at t=0: v0 + ω × (−R e_z) = Ω e_z × x0, i.e. (−R ω_y, R ω_x) = table − v0
    omega = jnp.array([(table[1] - v0[1]) / args["R"], -(table[0] - v0[0]) / args["R"], 0.7])
    q0 = jnp.array([x0[0], x0[1], 1.0, 0.0, 0.0, 0.0])
    qd0 = jnp.concatenate([v0, 0.5 * jnp.concatenate([jnp.zeros(1), omega])])  # q̇ = ½ (0, ω) at q = 1
    ts = jnp.linspace(0.0, 2.0, 11)
    traj = jl.simulate(system, q0, qd0, ts, args=args, **FAST)
    rate = args["k"] * args["Omega"] / (1 + args["k"])
    assert np.isclose(rate, 2 * args["Omega"] / 7)
    centre = x0 + jnp.array([-v0[1], v0[0]]) / rate
    c, s = jnp.cos(rate * ts), jnp.sin(rate * ts)
    rel = x0 - centre
    expected = centre[None, :] + jnp.stack([c * rel[0] - s * rel[1], s * rel[0] + c * rel[1]], axis=1)
    assert np.max(np.abs(traj.q[:, :2] - expected)) < 1e-8
    assert np.max(np.abs(traj.constraint_residuals[2])) < 1e-9  # index-1 drift, no projection
    # friction = m × acceleration of the centre (the only horizontal force): m ω_c e_z × v
    v = traj.qd[:, :2]
    assert np.allclose(
        traj.velocity_multipliers, args["m"] * rate * jnp.stack([-v[:, 1], v[:, 0]], 1), atol=1e-9
    )


def test_rolling_helpers_errors_and_transforms():
    disk = coordinates.RigidBody3D(lambda q: (q[:3], rotations.euler_matrix(q[3:6])), 1.0, jnp.ones(3))
    with pytest.raises(ValueError, match="shape"):
        contact.rolling_without_slipping(disk, 0.3, shape="cube")
    with pytest.raises(TypeError, match="RigidBody3D"):
        contact.contact_height(object(), 0.3)
    rolling = contact.rolling_without_slipping(disk, lambda a: a["R"])
    q = jnp.array([0.0, 0.0, 0.3 * np.sin(1.0), 0.2, 1.0, 0.0])
    qds = jnp.asarray(np.random.default_rng(1).normal(size=(4, 6)))
    out = jax.jit(jax.vmap(lambda v: rolling(q, v, 0.0, {"R": 0.3})))(qds)
    assert out.shape == (4, 2)
    # affine in q̇: ∂g/∂R by grad equals a finite difference
    grad = jax.grad(lambda r: rolling(q, qds[0], 0.0, {"R": r})[0])(0.3)

    def first(r):
        return rolling(q, qds[0], 0.0, {"R": r})[0]

    fd = (first(0.3 + 1e-6) - first(0.3 - 1e-6)) / 2e-6
    assert np.isclose(grad, fd, rtol=1e-7)


# ----------------------------------------------------------------------------- closed loops
BAR = {"a": 0.3, "b": 1.0, "c": 0.8, "d": 0.9}  # crank, coupler, rocker, ground (Grashof crank)


def _four_bar():
    # absolute link angles (θ1, θ2, θ3) from +x; crank A=(0,0)→B, coupler B→C, rocker D=(d,0)→C
    def link(index, start):
        def pose(q, args):
            length = args["abc"[index]]
            direction = jnp.stack([jnp.cos(q[index]), jnp.sin(q[index])])
            centre = start(q, args) + 0.5 * length * direction
            return jnp.concatenate([centre, q[index : index + 1]])

        return coordinates.RigidBody2D(
            pose, mass=lambda a: a["abc"[index]], inertia=lambda a: a["abc"[index]] ** 3 / 12
        )

    def crank_end(q, args):
        return args["a"] * jnp.stack([jnp.cos(q[0]), jnp.sin(q[0])])

    def ground(q, args):
        return jnp.stack([args["d"], 0.0 * q[0]])

    bodies = [link(0, lambda q, a: jnp.zeros(2, q.dtype)), link(1, crank_end), link(2, ground)]

    def closure(q, args):
        a, b, c, d = (args[k] for k in "abcd")
        return (
            a * jnp.stack([jnp.cos(q[0]), jnp.sin(q[0])])
            + b * jnp.stack([jnp.cos(q[1]), jnp.sin(q[1])])
            - c * jnp.stack([jnp.cos(q[2]), jnp.sin(q[2])])
            - jnp.stack([d, 0.0])
        )

    return jl.System(
        coordinates.lagrangian_from_positions(None, gravity=9.81, bodies=bodies), holonomic=closure
    )


def test_four_bar_consistent_state_holds_the_crank():
    system = _four_bar()
    crank, crank_rate = 0.6, 1.5
    guess_q, guess_qd = jnp.array([crank, 1.0, 2.0]), jnp.array([crank_rate, 0.0, 0.0])
    q, qd = jl.consistent_initial_state(
        system, guess_q, guess_qd, args=BAR, fixed_q=(0,), fixed_qd=(0,), newton_steps=8
    )
    assert float(q[0]) == crank and float(qd[0]) == crank_rate  # held exactly
    # closed form: C is the intersection of |C − B| = b and |C − D| = c (the branch above BD)
    a, b, c, d = (BAR[k] for k in "abcd")
    pb, pd = a * np.array([np.cos(crank), np.sin(crank)]), np.array([d, 0.0])
    e = np.linalg.norm(pd - pb)
    along = (b**2 - c**2 + e**2) / (2 * e)
    unit = (pd - pb) / e
    pc = pb + along * unit + np.sqrt(b**2 - along**2) * np.array([-unit[1], unit[0]])
    assert np.isclose(float(q[1]), np.arctan2(*(pc - pb)[::-1]), atol=1e-12)
    assert np.isclose(float(q[2]), np.arctan2(*(pc - pd)[::-1]), atol=1e-12)
    # rates from differentiating the loop: b θ̇2 e⊥(θ2) − c θ̇3 e⊥(θ3) = −a θ̇1 e⊥(θ1)
    perp = lambda th: np.array([-np.sin(th), np.cos(th)])  # noqa: E731
    matrix = np.stack([b * perp(float(q[1])), -c * perp(float(q[2]))], axis=1)
    rates = np.linalg.solve(matrix, -a * crank_rate * perp(crank))
    assert np.allclose(qd[1:], rates, atol=1e-12)
    # differentiable: dθ3/dθ1 from grad equals the velocity ratio
    slope = jax.grad(
        lambda th: jl.consistent_initial_state(
            system, jnp.array([th, 1.0, 2.0]), jnp.zeros(3), args=BAR, fixed_q=(0,), newton_steps=8
        )[0][2]
    )(crank)
    assert np.isclose(slope, rates[1] / crank_rate, rtol=1e-8)


def test_four_bar_holding_too_much_raises():
    system = _four_bar()
    with pytest.raises(ValueError, match="fixed_q"):
        jl.consistent_initial_state(system, jnp.zeros(3), jnp.zeros(3), args=BAR, fixed_q=(5,))
    # holding the crank and the coupler leaves one free angle for two closure equations
    with pytest.raises(Exception, match="consistent_initial_state"):
        jl.consistent_initial_state(
            system, jnp.array([0.6, 1.0, 2.0]), jnp.zeros(3), args=BAR, fixed_q=(0, 1)
        )
    # holding two rates at values the loop cannot share
    with pytest.raises(Exception, match="fixed_qd"):
        jl.consistent_initial_state(
            system,
            jnp.array([0.6, 1.0, 2.0]),
            jnp.array([1.0, 1.0, 0.0]),
            args=BAR,
            fixed_q=(0,),
            fixed_qd=(0, 1),
        )


# ----------------------------------------------------------------------------- gyroscope (a chain)
def test_gyroscope_chain_reduces_to_heavy_top_and_conserves(top_euler):
    gyro = systems.gyroscope()
    massless = {**TOP, "inner": (0.0, 0.0, 0.0), "outer": (0.0, 0.0, 0.0)}
    # equal Lagrangians at random states (hence equal equations of motion)
    rng = np.random.default_rng(2)
    for _ in range(3):
        x, v = jnp.asarray(rng.uniform(0.2, 1.2, 3)), jnp.asarray(rng.normal(size=3))
        assert np.isclose(
            gyro.lagrangian(x, v, t=0.0, args=massless),
            top_euler.lagrangian(x, v, t=0.0, args=TOP),
            rtol=1e-13,
        )
    q, qd = jnp.array([0.2, 0.6, 0.1]), jnp.array([1.0, 0.5, 40.0])
    # with massive gimbals: energy, p_α (vertical axis) and p_γ = I3 (γ̇ + α̇ cos β) are conserved
    args = {**TOP, "inner": (0.004, 0.002, 0.004), "outer": (0.006, 0.006, 0.004)}
    traj = jl.simulate(gyro, q, qd, jnp.linspace(0.0, 1.0, 41), args=args, **FAST)
    p_gamma = TOP["I3"] * (traj.qd[:, 2] + traj.qd[:, 0] * jnp.cos(traj.q[:, 1]))
    assert np.allclose(traj.momenta[:, 2], p_gamma, rtol=1e-12)
    for series in (traj.energy, traj.momenta[:, 0], p_gamma):
        assert np.ptp(series) < 1e-8 * np.max(np.abs(series))
    # the gimbals' inertia slows the precession relative to the bare top
    top = jl.simulate(top_euler, q, qd, jnp.linspace(0.0, 1.0, 41), args=TOP, **FAST)
    assert abs(float(traj.q[-1, 0] - top.q[-1, 0])) > 1e-3


def test_rigid_body_lagrangian_grad_and_vmap():
    # ∂L/∂I3 of the heavy top = ½ ω3² (L is linear in I3), by grad and against a finite difference
    lagrangian = systems.heavy_top("euler").lagrangian
    q, qd = jnp.array([0.2, 0.6, 0.1]), jnp.array([1.0, 0.5, 40.0])
    grad = jax.jit(jax.grad(lambda i3: lagrangian(q, qd, t=0.0, args={**TOP, "I3": i3})))(0.01)
    omega3 = qd[2] + qd[0] * jnp.cos(q[1])
    assert np.isclose(grad, 0.5 * omega3**2, rtol=1e-13)
    batch = jax.vmap(lambda x: lagrangian(x, qd, t=0.0, args=TOP))(jnp.stack([q, 2 * q]))
    assert batch.shape == (2,)
