r"""The robots of ``jaxlag.systems`` (``robot_arm``, ``space_robot``): read from their MJCF by
``jaxlag.robots``, checked against MuJoCo's own ``mj_fullM`` and ``qfrc_bias`` and against the
invariants of a free motion (energy without damping or motors; the linear momentum of the
free-flying robot, on which no external force acts)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
import jaxlag.robots as jlr
import jaxlag.systems as systems

mujoco = pytest.importorskip("mujoco")

jax.config.update("jax_enable_x64", True)

MODELS = [systems.robot_arm, systems.space_robot]


def _full_mass_matrix(model, data) -> np.ndarray:
    out = np.zeros((model.nv, model.nv))
    try:  # MuJoCo 4: mj_fullM(m, d, dst)
        mujoco.mj_fullM(model, data, out)
    except TypeError:  # MuJoCo 3: mj_fullM(m, dst, qM)
        mujoco.mj_fullM(model, out, data.qM)
    return out


def _state(model, tree, rng):
    q = model.qpos0.copy()
    hinges = [i for i, kind in enumerate(tree.joint_types) if kind == "hinge"]
    q[[tree.q_addresses[i] for i in hinges]] += rng.uniform(-1.5, 1.5, len(hinges))
    if tree.joint_types[0] == "free":
        q[:3] = rng.normal(size=3)
        q[3:7] = rng.normal(size=4)
        q[3:7] /= np.linalg.norm(q[3:7])
    return q, rng.normal(size=model.nv)


@pytest.mark.parametrize("factory", MODELS, ids=lambda f: f.__name__)
def test_robot_model_agrees_with_mujoco(factory):
    tree = systems.default_args(factory)
    assert isinstance(tree, jlr.KinematicTree)
    assert factory() is factory()  # memoized: compiled simulations are reused
    model = mujoco.MjModel.from_xml_string(factory.mjcf)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    for k in range(4):
        q, v = _state(model, tree, rng) if k else (model.qpos0.copy(), np.zeros(model.nv))
        data.qpos[:], data.qvel[:] = q, v
        mujoco.mj_forward(model, data)
        expected = _full_mass_matrix(model, data)
        mass = np.asarray(jlr.mass_matrix(tree, q))
        np.testing.assert_allclose(mass, expected, rtol=0, atol=1e-10 * np.abs(expected).max())
        np.testing.assert_allclose(mass, mass.T, rtol=0, atol=1e-14 * np.abs(mass).max())
        assert np.linalg.eigvalsh(mass).min() > 0  # symmetric positive definite
        bias = np.asarray(jlr.bias_forces(tree, q, v))
        scale = max(np.abs(data.qfrc_bias).max(), 1.0)
        np.testing.assert_allclose(bias, data.qfrc_bias, rtol=0, atol=1e-10 * scale)


def test_robot_arm_conserves_energy_without_damping():
    # No damping, no motor torque: h = ½ q̇ᵀ M q̇ + V is constant along the motion.
    tree = systems.default_args(systems.robot_arm)
    undamped = eqx.tree_at(lambda t: t.damping, tree, jnp.zeros_like(tree.damping))
    arm = systems.robot_arm().with_control(lambda q, qd: jnp.zeros(6))
    q0 = jnp.array([0.3, 0.8, -0.6, 0.5, 0.9, -0.4])
    qd0 = jnp.array([1.0, -0.5, 0.8, 2.0, -1.0, 3.0])
    traj = jl.simulate(arm, q0, qd0, jnp.linspace(0.0, 0.5, 6), args=undamped, projection=None)
    energy = np.asarray(traj.energy)
    assert np.max(np.abs(energy - energy[0])) <= 1e-9 * max(np.abs(energy).max(), 1.0), energy - energy[0]
    assert not np.allclose(traj.q[-1], q0)  # it moved


def test_space_robot_conserves_momentum_and_energy():
    # Zero gravity and no motor torque: nothing acts from outside, so the total linear momentum
    # Σ m_i ċ_i (ċ_i the velocity of link i's centre of mass) and the energy stay constant.
    tree = systems.default_args(systems.space_robot)
    robot = systems.space_robot().with_control(lambda q, qd: jnp.zeros(4))
    quaternion = jnp.array([0.9, 0.1, -0.2, 0.3])
    quaternion = quaternion / jnp.linalg.norm(quaternion)
    q0 = jnp.concatenate([jnp.array([0.1, -0.2, 0.3]), quaternion, jnp.array([0.4, -0.3, -0.5, 0.6])])
    qd0 = jnp.concatenate([jnp.array([0.2, 0.1, -0.1]), jnp.zeros(4), jnp.array([1.0, -2.0, 1.5, 0.5])])
    traj = jl.simulate(robot, q0, qd0, jnp.linspace(0.0, 0.5, 6), projection=None)

    def centres(q):
        poses = jlr.forward_kinematics(tree, q)
        return poses.translation + jnp.einsum("lij,lj->li", poses.rotation, tree.com)

    def momentum(q, qd):
        return tree.mass @ jax.jvp(centres, (q,), (qd,))[1]

    p = np.asarray(jax.vmap(momentum)(traj.q, traj.qd))
    assert np.abs(p[0]).max() > 1.0  # the test means something
    np.testing.assert_allclose(p, np.broadcast_to(p[0], p.shape), rtol=0, atol=1e-9 * np.abs(p).max())
    energy = np.asarray(traj.energy)
    assert np.max(np.abs(energy - energy[0])) <= 1e-9 * max(np.abs(energy).max(), 1.0), energy - energy[0]
