"""jaxlag.robots against MuJoCo: M(q), the bias forces and q̈ of imported MJCF and URDF models.

Every model is compiled by MuJoCo (the test extra installs it); at random states the tree's
mass matrix, bias forces and accelerations agree with ``mj_fullM``, ``qfrc_bias`` and ``qacc``
of ``mj_forward`` to 1e-10 relative. jaxlag's coordinates are MuJoCo's ``qpos``/``qvel``: a ball
joint's velocity is the angular velocity in the child's frame, a free joint's the world velocity
of the body's origin then the angular velocity in the body's frame (checked below against
``mj_integratePos`` and ``mj_objectVelocity``), so the comparison maps each entry to itself.
"""

import sys

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag.robots as jlr

mujoco = pytest.importorskip("mujoco")

_NO_CONTACT = '<option><flag contact="disable"/></option>'

DOUBLE_PENDULUM = f"""<mujoco>{_NO_CONTACT}<worldbody>
  <body name="upper"><joint name="shoulder" type="hinge" axis="0 1 0" damping="0.3" armature="0.02"/>
    <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1"/>
    <body name="lower" pos="0 0 -1"><joint name="elbow" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.8" size="0.04" mass="0.7"/></body></body>
</worldbody></mujoco>"""

ARM = f"""<mujoco>{_NO_CONTACT}<default><joint damping="0.5" armature="0.1"/></default><worldbody>
  <body name="base" pos="0 0 0.3" euler="0 0 20"><geom type="cylinder" size="0.1 0.05"/>
  <body name="l1" pos="0 0 0.1"><joint name="j1" axis="0 0 1"/>
    <geom type="capsule" fromto="0 0 0 0 0 0.3" size="0.05"/>
  <body name="l2" pos="0 0 0.3" quat="0.9 0.1 0.3 -0.2"><joint name="j2" axis="0 1 0" pos="0 0 0.02"/>
    <geom type="box" size="0.04 0.05 0.2" pos="0.01 0.02 0.2"/>
  <body name="l3" pos="0 0 0.4"><joint name="j3" axis="0 0 1" armature="0.3"/>
    <geom type="capsule" fromto="0 0 0 0.05 0 0.3" size="0.04"/>
  <body name="l4" pos="0 0 0.3" euler="10 -20 5"><joint name="j4" axis="0.3 1 0.1" damping="1.2"/>
    <geom type="ellipsoid" size="0.05 0.08 0.15" pos="0 0 0.15" euler="5 10 15"/>
  <body name="l5" pos="0.02 0 0.3"><joint name="j5" axis="0 0 1"/>
    <geom type="capsule" fromto="0 0 0 0 0 0.2" size="0.03"/>
  <body name="l6" pos="0 0 0.2"><joint name="j6" axis="0 1 0" pos="0.01 0.01 0"/>
    <geom type="box" size="0.03 0.03 0.06" pos="0 0 0.06"/>
  <body name="l7" pos="0 0 0.12"><joint name="j7" axis="1 0 0"/>
    <geom type="cylinder" size="0.05 0.01" pos="0 0.02 0.01"/>
  </body></body></body></body></body></body></body></body>
</worldbody>
<actuator><motor joint="j1" gear="2"/><motor joint="j4"/><motor joint="j7" gear="0.5"/></actuator>
</mujoco>"""

FLOATING_BASE = f"""<mujoco>{_NO_CONTACT}<option gravity="0.5 -1 -9.81"/><worldbody>
  <body name="torso" pos="0.1 0.2 1.0" quat="0.8 0.2 0.1 0.4"><freejoint/>
    <geom type="box" size="0.2 0.1 0.05" pos="0.03 -0.02 0.01"/>
    <geom type="sphere" size="0.05" pos="0.2 0.1 0"/>
    <body name="leg1" pos="0.2 0.1 -0.05"><joint type="hinge" axis="0 1 0" damping="0.2" armature="0.01"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03"/>
      <body name="shin1" pos="0 0 -0.3"><joint type="hinge" axis="1 0 0"/>
        <geom type="capsule" fromto="0 0 0 0.1 0 -0.3" size="0.03"/></body></body>
    <body name="leg2" pos="-0.2 -0.1 -0.05"><joint type="ball" pos="0 0 0.02" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0 0.1 -0.3" size="0.03"/></body>
  </body>
</worldbody></mujoco>"""

BALLS = f"""<mujoco>{_NO_CONTACT}<worldbody>
  <body name="a" pos="0 0 2"><joint type="ball" damping="0.2" armature="0.05"/>
    <geom type="capsule" fromto="0 0 0 0.1 0 -0.5" size="0.05"/>
    <body name="b" pos="0.1 0 -0.5" euler="0 30 0"><joint type="ball" pos="0.01 0.02 0.03"/>
      <geom type="box" size="0.05 0.1 0.2" pos="0 0.02 -0.2"/>
      <body name="c" pos="0 0 -0.4"><joint type="hinge" axis="1 1 0"/>
        <geom type="ellipsoid" size="0.1 0.05 0.2" pos="0 0 -0.2" euler="10 0 40"/></body></body></body>
</worldbody></mujoco>"""

SLIDES = f"""<mujoco>{_NO_CONTACT}<option gravity="0 0 -9.81"/><worldbody>
  <body name="cart" pos="0 0 0.5"><joint name="rail" type="slide" axis="1 0 0" damping="0.4" armature="0.2"/>
    <geom type="box" size="0.2 0.1 0.05"/>
    <body name="pole"><joint type="hinge" axis="0 1 0" pos="0 0 0.05"/>
      <joint type="slide" axis="0 0 1" ref="0.1" damping="0.3"/>
      <geom type="capsule" fromto="0 0 0 0 0.05 0.6" size="0.03"/>
      <body name="tip" pos="0 0 0.6"><joint type="slide" axis="0.3 0.4 1"/>
        <joint type="hinge" axis="1 0 0" ref="0.2" armature="0.01"/>
        <geom type="sphere" size="0.06" pos="0.05 0 0"/></body></body></body>
</worldbody><actuator><motor joint="rail" gear="3"/></actuator></mujoco>"""

URDF = """<robot name="urdf_arm">
  <link name="base"><inertial><mass value="2"/>
    <inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="upper"><inertial><origin xyz="0.02 0 0.2" rpy="0.1 0.2 0.3"/><mass value="1.2"/>
    <inertia ixx="0.02" ixy="0.001" ixz="0.002" iyy="0.025" iyz="-0.001" izz="0.012"/></inertial></link>
  <link name="fore"><inertial><origin xyz="0 0.01 0.15"/><mass value="0.8"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.012" iyz="0" izz="0.005"/></inertial></link>
  <link name="hand"><inertial><origin xyz="0 0 0.05"/><mass value="0.3"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.0012" iyz="0" izz="0.0005"/></inertial></link>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
    <origin xyz="0 0 0.1" rpy="0 0 0.3"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="10" velocity="5"/><dynamics damping="0.2"/></joint>
  <joint name="elbow" type="continuous"><parent link="upper"/><child link="fore"/>
    <origin xyz="0 0 0.4" rpy="0.2 0 0"/><axis xyz="1 0 0"/></joint>
  <joint name="wrist" type="prismatic"><parent link="fore"/><child link="hand"/>
    <origin xyz="0 0 0.3"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="10" velocity="5"/></joint>
</robot>"""

MODELS = {
    "double_pendulum": DOUBLE_PENDULUM,
    "arm_7dof": ARM,
    "floating_base": FLOATING_BASE,
    "ball_joints": BALLS,
    "slide_joints": SLIDES,
    "urdf_arm": URDF,
}


def _full_mass_matrix(model, data) -> np.ndarray:
    out = np.zeros((model.nv, model.nv))
    try:  # MuJoCo 4: mj_fullM(m, d, dst)
        mujoco.mj_fullM(model, data, out)
    except TypeError:  # MuJoCo 3: mj_fullM(m, dst, qM)
        mujoco.mj_fullM(model, out, data.qM)
    return out


def _random_states(model, rng, count):
    """``(q, v)`` inside every joint's range; quaternions of unit length."""
    qs, vs = [], []
    for _ in range(count):
        q = np.array(model.qpos0) + rng.uniform(-0.8, 0.8, model.nq)
        for joint in range(model.njnt):
            adr = model.jnt_qposadr[joint]
            kind = model.jnt_type[joint]
            if kind == mujoco.mjtJoint.mjJNT_FREE:
                q[adr + 3 : adr + 7] /= np.linalg.norm(q[adr + 3 : adr + 7])
            elif kind == mujoco.mjtJoint.mjJNT_BALL:
                q[adr : adr + 4] = rng.normal(size=4)
                q[adr : adr + 4] /= np.linalg.norm(q[adr : adr + 4])
        qs.append(q)
        vs.append(rng.normal(size=model.nv) * 1.5)
    return np.array(qs), np.array(vs)


def _mujoco_reference(model, qs, vs, controls):
    data = mujoco.MjData(model)
    out = {"M": [], "bias": [], "qacc": []}
    for q, v, u in zip(qs, vs, controls):
        data.qpos[:] = q
        data.qvel[:] = v
        data.ctrl[:] = u
        mujoco.mj_forward(model, data)
        assert data.nefc == 0  # no contact, no limit: qacc is M⁻¹(τ + qfrc_passive − qfrc_bias)
        out["M"].append(_full_mass_matrix(model, data))
        out["bias"].append(np.array(data.qfrc_bias))
        out["qacc"].append(np.array(data.qacc))
    return {key: np.array(value) for key, value in out.items()}


@eqx.filter_jit
def _quantities(tree, qs, vs, controls):
    def one(q, v, u):
        tau = tree.actuation @ u
        mass = jlr.mass_matrix(tree, q)
        bias = jlr.bias_forces(tree, q, v)
        return {
            "M": mass,
            "bias": bias,
            "qacc": jlr.forward_dynamics(tree, q, v, tau),
            "qacc_dense": jnp.linalg.solve(mass, tau - tree.damping * v - bias),
            "inverse": jlr.inverse_dynamics(tree, q, v, jlr.forward_dynamics(tree, q, v, tau)) - tau,
        }

    return jax.vmap(one)(qs, vs, controls)


def _relative(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - b)) / max(np.max(np.abs(b)), 1e-300))


AGREEMENT: dict[tuple[str, str], float] = {}


@pytest.mark.parametrize("name", list(MODELS))
def test_agrees_with_mujoco(name):
    model = mujoco.MjModel.from_xml_string(MODELS[name])
    tree = jlr.load(MODELS[name])
    assert (tree.nq, tree.nv) == (model.nq, model.nv)
    rng = np.random.default_rng(len(name))
    qs, vs = _random_states(model, rng, 4)
    controls = rng.normal(size=(4, model.nu))
    reference = _mujoco_reference(model, qs, vs, controls)
    ours = _quantities(tree, jnp.asarray(qs), jnp.asarray(vs), jnp.asarray(controls))
    for key, reference_key in (("M", "M"), ("bias", "bias"), ("qacc", "qacc"), ("qacc_dense", "qacc")):
        error = _relative(ours[key], reference[reference_key])
        AGREEMENT[(name, key)] = error
        assert error < 1e-10, (name, key, error)
    # inverse_dynamics undoes forward_dynamics (armature and damping included)
    assert np.max(np.abs(np.asarray(ours["inverse"]))) < 1e-10 * np.max(np.abs(reference["bias"]))


def test_forward_kinematics_matches_mujoco():
    model = mujoco.MjModel.from_xml_string(FLOATING_BASE)
    tree = jlr.load(FLOATING_BASE)
    data = mujoco.MjData(model)
    qs, _ = _random_states(model, np.random.default_rng(3), 1)
    data.qpos[:] = qs[0]
    mujoco.mj_kinematics(model, data)
    poses = jlr.forward_kinematics(tree, qs[0])
    # each body is the last of its links
    last = [
        tree.names.index(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}")
        for b in range(1, model.nbody)
    ]
    np.testing.assert_allclose(np.asarray(poses.translation)[last], data.xpos[1:], atol=1e-12)
    np.testing.assert_allclose(np.asarray(poses.rotation)[last], data.xmat[1:].reshape(-1, 3, 3), atol=1e-12)


def test_velocity_conventions_are_mujocos():
    """Ball and free joints: ``q̇`` from ``v`` as MuJoCo integrates it, and the free joint's
    velocity is (world velocity of the origin, angular velocity in the body's frame)."""
    model = mujoco.MjModel.from_xml_string(FLOATING_BASE)
    tree = jlr.load(FLOATING_BASE)
    q, v = (x[0] for x in _random_states(model, np.random.default_rng(5), 1))
    rate = np.asarray(jlr.configuration_rate(tree, q, v))
    for dt in (1e-4, 5e-5):
        stepped = q.copy()
        mujoco.mj_integratePos(model, stepped, v, dt)
        np.testing.assert_allclose((stepped - q) / dt, rate, atol=20 * dt)
    data = mujoco.MjData(model)
    data.qpos[:] = q
    data.qvel[:] = v
    mujoco.mj_forward(model, data)
    torso = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "torso")
    local = np.zeros(6)  # (ω, v) at the body's origin, in the body's frame
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, torso, local, 1)
    rotation = data.xmat[torso].reshape(3, 3)
    np.testing.assert_allclose(v[3:6], local[:3], atol=1e-12)
    np.testing.assert_allclose(v[:3], rotation @ local[3:], atol=1e-12)


def test_jit_vmap_grad():
    """Derivatives through the recursions agree with central differences: with respect to the
    configuration and to the inertial parameters (masses, centres of mass, inertias)."""
    tree = jlr.load(FLOATING_BASE)
    model = mujoco.MjModel.from_xml_string(FLOATING_BASE)
    q, v = (jnp.asarray(x[0]) for x in _random_states(model, np.random.default_rng(7), 1))
    tau = jnp.linspace(-1.0, 1.0, tree.nv)

    def loss(params, q):
        mass, com, inertia = params
        t = eqx.tree_at(lambda t: (t.mass, t.com, t.inertia), tree, (mass, com, inertia))
        return jnp.sum(jnp.sin(jlr.forward_dynamics(t, q, v, tau))) + jnp.sum(jlr.mass_matrix(t, q) ** 2)

    params = (tree.mass, tree.com, tree.inertia)
    grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(params, q)
    rng = np.random.default_rng(0)
    flat, unravel = jax.flatten_util.ravel_pytree((params, q))
    gflat, _ = jax.flatten_util.ravel_pytree(grads)
    value = jax.jit(lambda x: loss(*unravel(x)))
    for _ in range(3):
        # relative steps: the links' inertias (~1e-4) set the scale of the acceleration's curvature
        direction = jnp.asarray(rng.normal(size=flat.shape)) * (jnp.abs(flat) + 1e-3)
        h = 1e-7
        fd = (value(flat + h * direction) - value(flat - h * direction)) / (2 * h)
        np.testing.assert_allclose(float(gflat @ direction), float(fd), rtol=1e-5)
    # vmap over parameters: a batch of masses
    masses = tree.mass[None, :] * jnp.array([[1.0], [1.5]])
    batched = jax.vmap(lambda m: jlr.forward_dynamics(eqx.tree_at(lambda t: t.mass, tree, m), q, v, tau))(
        masses
    )
    assert batched.shape == (2, tree.nv)
    np.testing.assert_allclose(batched[0], jlr.forward_dynamics(tree, q, v, tau), rtol=1e-12)


def test_chain_compiles_once_per_structure():
    """A 60-link chain: the sweeps are scans, so the program does not grow with the links."""
    links = 60
    body = (
        '<body pos="0 0 -0.1"><joint type="hinge" axis="0 1 0" damping="0.1"/>'
        '<geom size="0.02" pos="0 0 -0.05"/>'
    )
    xml = f"<mujoco><worldbody>{body * links}{'</body>' * links}</worldbody></mujoco>"
    tree = jlr.load(xml)
    q = jnp.linspace(0.0, 1.0, links)
    v = jnp.linspace(1.0, -1.0, links)
    acceleration = jax.jit(jlr.forward_dynamics)(tree, q, v)
    mass = jax.jit(jlr.mass_matrix)(tree, q)
    bias = jax.jit(jlr.bias_forces)(tree, q, v)
    np.testing.assert_allclose(mass @ acceleration, -bias - tree.damping * v, rtol=1e-9, atol=1e-9)
    hlo = jax.jit(jlr.forward_dynamics).lower(tree, q, v).as_text()
    assert len(hlo.splitlines()) < 1500


def test_loading_needs_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco", None)
    with pytest.raises(ImportError, match=r"jaxlag\[robots\]"):
        jlr.load(DOUBLE_PENDULUM)


def test_refuses_what_it_does_not_model():
    friction = DOUBLE_PENDULUM.replace('damping="0.1"', 'frictionloss="0.2"')
    with pytest.raises(ValueError, match="frictionloss"):
        jlr.load(friction)
    servo = ARM.replace('<motor joint="j4"/>', '<position joint="j4" kp="10"/>')
    with pytest.raises(ValueError, match="motors"):
        jlr.load(servo)


HANGING = f"""<mujoco>{_NO_CONTACT}<worldbody>
  <body name="upper"><joint type="hinge" axis="0 1 0"/>
    <inertial pos="0 0 -0.5" mass="1.0" diaginertia="0.02 0.03 0.01"/>
    <body name="lower" pos="0 0 -1"><joint type="hinge" axis="0 1 0"/>
      <inertial pos="0 0 -0.4" mass="0.6" diaginertia="0.01 0.015 0.005"/></body></body>
</worldbody></mujoco>"""


def test_imported_and_hand_written_double_pendulum_move_alike():
    """``jlr.system``: an imported tree simulates with ``jl.simulate`` as its hand-written ``L``."""
    import jaxlag as jl

    g, m1, m2, c1, c2, l1, i1, i2 = 9.81, 1.0, 0.6, 0.5, 0.4, 1.0, 0.03, 0.015

    def lagrangian(q, qd):
        # hinges about y: a point (0, 0, −c) of a link at angle θ sits at (−c sin θ, −c cos θ) in (x, z)
        t1, t2 = q
        w1, w2 = qd
        x1d, z1d = -c1 * jnp.cos(t1) * w1, c1 * jnp.sin(t1) * w1
        x2d = -l1 * jnp.cos(t1) * w1 - c2 * jnp.cos(t1 + t2) * (w1 + w2)
        z2d = l1 * jnp.sin(t1) * w1 + c2 * jnp.sin(t1 + t2) * (w1 + w2)
        kinetic = 0.5 * m1 * (x1d**2 + z1d**2) + 0.5 * i1 * w1**2
        kinetic += 0.5 * m2 * (x2d**2 + z2d**2) + 0.5 * i2 * (w1 + w2) ** 2
        potential = -m1 * g * c1 * jnp.cos(t1) - m2 * g * (l1 * jnp.cos(t1) + c2 * jnp.cos(t1 + t2))
        return kinetic - potential

    tree = jlr.load(HANGING)
    q0, qd0 = jnp.array([0.7, -0.4]), jnp.array([0.3, 1.1])
    ts = jnp.linspace(0.0, 1.0, 11)
    imported = jl.simulate(jlr.system(tree), q0, qd0, ts)
    by_hand = jl.simulate(jl.System(lagrangian), q0, qd0, ts)
    np.testing.assert_allclose(imported.q, by_hand.q, atol=1e-7)
    # and the system's accelerations are the recursive algorithm's
    np.testing.assert_allclose(
        jlr.system(tree).accelerations(q0, qd0), jlr.forward_dynamics(tree, q0, qd0), rtol=1e-12
    )


@pytest.mark.parametrize("name", ["floating_base", "ball_joints"])
def test_system_with_free_and_ball_joints_follows_the_recursive_dynamics(name):
    """Quaternion coordinates with ``|Q|² = 1`` (jaxlag's convention): the KKT solve gives
    ``q̈ = d/dt configuration_rate(q, v)`` with ``v̇`` from ABA, with the recursive dynamics
    (``M = Gᵀ M_v G + Q Qᵀ``, ``F_L`` by Newton–Euler) and with autodiff of ``L`` alike; ``M``, ``F``
    and the multipliers of the ``|Q|² − 1`` rows agree between the two to rounding."""
    import jaxlag as jl

    tree = jlr.load(MODELS[name])
    model = mujoco.MjModel.from_xml_string(MODELS[name])
    recursive, autodiff = _both_dynamics(tree)
    assert isinstance(recursive.dynamics, jlr.TreeDynamics)
    assert isinstance(autodiff.dynamics, jl.AutodiffDynamics)
    for q, v in zip(*_random_states(model, np.random.default_rng(11), 3)):
        q, v = jnp.asarray(q), jnp.asarray(v)
        qd = jlr.configuration_rate(tree, q, v)
        acceleration = jlr.forward_dynamics(tree, q, v)
        _, expected = jax.jvp(lambda q, v: jlr.configuration_rate(tree, q, v), (q, v), (qd, acceleration))
        scale = np.abs(expected).max()
        for system in (recursive, autodiff):
            np.testing.assert_allclose(system.accelerations(q, qd), expected, rtol=0, atol=1e-11 * scale)
        mass = autodiff.mass_matrix(q, qd)
        np.testing.assert_allclose(
            recursive.mass_matrix(q, qd), mass, rtol=0, atol=1e-13 * np.abs(mass).max()
        )
        force = autodiff.generalized_forces(q, qd)
        np.testing.assert_allclose(
            recursive.generalized_forces(q, qd), force, rtol=0, atol=1e-13 * np.abs(force).max()
        )
        multipliers = autodiff.multipliers(q, qd)
        np.testing.assert_allclose(
            recursive.multipliers(q, qd), multipliers, rtol=0, atol=1e-11 * np.abs(multipliers).max()
        )


def test_floating_base_moves_alike_with_both_dynamics():
    """A free-flying base with a ball-jointed leg over 0.3 s: the recursive and the autodiff
    systems give the same trajectory and energy; the recursive one's gradient with respect to the
    link masses matches a central difference (whose error is O(h²) ≈ 1e-10 relative plus the
    solver's tolerance over h, about 1e-7)."""
    import jaxlag as jl

    tree = jlr.load(FLOATING_BASE)
    model = mujoco.MjModel.from_xml_string(FLOATING_BASE)
    q, v = (jnp.asarray(x[0]) for x in _random_states(model, np.random.default_rng(5), 1))
    qd = jlr.configuration_rate(tree, q, v)
    recursive, autodiff = _both_dynamics(tree)
    ts = jnp.linspace(0.0, 0.3, 4)
    fast, slow = jl.simulate(recursive, q, qd, ts), jl.simulate(autodiff, q, qd, ts)
    np.testing.assert_allclose(fast.q, slow.q, rtol=0, atol=1e-10)
    np.testing.assert_allclose(fast.qd, slow.qd, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.energy, slow.energy, rtol=0, atol=1e-9)

    # grad with respect to the link masses (the tree as args) against a central difference (the
    # autodiff path's gradient is tested in test_recursive_dynamics_under_jit_vmap_grad)
    def final_height(system, masses):
        heavier = eqx.tree_at(lambda t: t.mass, tree, masses)
        return jl.simulate(system, q, qd, ts, args=heavier).q[-1, 2]

    grad_fast = jax.grad(lambda m: final_height(recursive, m))(tree.mass)
    h = 1e-5 * tree.mass[0]
    step = jnp.zeros_like(tree.mass).at[0].set(h)
    central = (final_height(recursive, tree.mass + step) - final_height(recursive, tree.mass - step)) / (
        2 * h
    )
    np.testing.assert_allclose(grad_fast[0], central, rtol=1e-6, atol=1e-9)


def test_joint_limits_are_one_sided_constraints():
    """A limited hinge stops at its range (plastic), and the stop's multiplier holds gravity's
    torque ``m g x cos θ``."""
    import jaxlag as jl

    xml = """<mujoco><worldbody><body><joint type="hinge" axis="0 1 0" range="-30 30" limited="true"/>
      <inertial pos="0.5 0 0" mass="1" diaginertia="0.01 0.01 0.01"/></body></worldbody></mujoco>"""
    tree = jlr.load(xml)
    ts = jnp.linspace(0.0, 1.5, 16)
    assert isinstance(jlr.system(tree).dynamics, jlr.TreeDynamics)  # the stop acts on the recursive M
    traj = jl.simulate(jlr.system(tree), jnp.zeros(1), jnp.zeros(1), ts, events=jl.Events(max_segments=4))
    stop = np.deg2rad(30.0)
    assert traj.events is not None and traj.events.kinds()[0] == "contact"
    np.testing.assert_allclose(traj.q[-1, 0], stop, atol=1e-9)
    np.testing.assert_allclose(traj.multipliers[-1], [0.0, 9.81 * 0.5 * np.cos(stop)], atol=1e-7)
    assert jlr.system(tree, limits=False).holonomic is None


def test_ball_joint_limit_is_a_cone_on_the_rotation_angle():
    """A ball joint limited to 30° (MuJoCo's range: the rotation angle about any axis) swings
    under gravity onto its cone and stays there (plastic): ``θ = 2 arccos w = 30°`` and the
    cone's torque ``τ = −λ x/2`` holds gravity's ``m g x cos θ`` about the swing axis."""
    import jaxlag as jl

    xml = """<mujoco><worldbody><body><joint type="ball" range="0 30" limited="true"/>
      <inertial pos="0.5 0 0" mass="1" diaginertia="0.01 0.01 0.01"/></body></worldbody></mujoco>"""
    tree = jlr.load(xml)
    system = jlr.system(tree)
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])
    traj = jl.simulate(system, q0, jnp.zeros(4), jnp.linspace(0.0, 1.5, 16), events=jl.Events(max_segments=4))
    assert traj.events is not None and traj.events.kinds()[0] == "contact"
    quaternion = traj.q[-1]
    np.testing.assert_allclose(2 * np.arccos(quaternion[0]), np.deg2rad(30.0), atol=1e-9)
    np.testing.assert_allclose(traj.qd[-1], 0.0, atol=1e-9)
    torque = -traj.multipliers[-1, 1] * quaternion[1:] / 2
    np.testing.assert_allclose(torque, [0.0, -9.81 * 0.5 * np.cos(np.deg2rad(30.0)), 0.0], atol=1e-7)
    assert jlr.system(tree, limits=False).unilateral == ()


def test_files_and_wrong_lengths(tmp_path):
    path = tmp_path / "arm.urdf"
    path.write_text(URDF)
    from_file = jlr.load(path)
    assert from_file.joint_types[-3:] == ("hinge", "hinge", "slide")
    q = jnp.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(jlr.mass_matrix(from_file, q), jlr.mass_matrix(jlr.load(URDF), q), rtol=1e-15)
    with pytest.raises(ValueError, match=r"qpos\) of this tree has shape \(3,\); got shape \(2,\)"):
        jlr.mass_matrix(from_file, jnp.zeros(2))


def _both_dynamics(tree, control=None):
    """``jlr.system(tree)`` with the recursive dynamics and with automatic differentiation of L."""
    import jaxlag as jl

    recursive = jlr.system(tree)
    autodiff = jlr.system(tree, dynamics=jl.AutodiffDynamics())
    if control is not None:
        recursive, autodiff = recursive.with_control(control), autodiff.with_control(control)
    return recursive, autodiff


@pytest.mark.parametrize("name", ["HANGING", "ARM"])
def test_recursive_dynamics_move_as_the_lagrangian(name):
    """``TreeDynamics`` (CRBA + RNEA) gives the motion of ``M = ∂²L/∂q̇²``, ``F = ∂L/∂q − …`` of the
    tree's ``L``, with damping, armature and motors, to ~1e-12 over a short run."""
    import jaxlag as jl

    tree = jlr.load({"HANGING": HANGING, "ARM": ARM}[name])
    k = tree.actuation.shape[1]
    control = (lambda q, qd: 0.5 * jnp.sin(jnp.arange(1.0, k + 1.0) * q[:k])) if k else None
    recursive, autodiff = _both_dynamics(tree, control)
    assert isinstance(recursive.dynamics, jlr.TreeDynamics)
    assert isinstance(autodiff.dynamics, jl.AutodiffDynamics)
    q0 = jnp.linspace(0.4, -0.3, tree.nq)
    qd0 = jnp.linspace(0.8, -0.5, tree.nq)
    np.testing.assert_allclose(recursive.mass_matrix(q0, qd0), autodiff.mass_matrix(q0, qd0), atol=1e-13)
    np.testing.assert_allclose(
        recursive.generalized_forces(q0, qd0), autodiff.generalized_forces(q0, qd0), atol=1e-12
    )
    ts = jnp.linspace(0.0, 0.5, 6)
    fast, slow = jl.simulate(recursive, q0, qd0, ts), jl.simulate(autodiff, q0, qd0, ts)
    np.testing.assert_allclose(fast.q, slow.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.qd, slow.qd, rtol=0, atol=1e-11)
    np.testing.assert_allclose(fast.energy, slow.energy, rtol=0, atol=1e-11)


def test_recursive_dynamics_under_jit_vmap_grad():
    """The recursive system composes with ``jit``, ``vmap`` and ``grad`` (with respect to the
    tree's masses, given as ``args``) exactly as the autodiff one."""
    import jaxlag as jl

    tree = jlr.load(HANGING)
    recursive, autodiff = _both_dynamics(tree)
    ts = jnp.linspace(0.0, 0.4, 5)
    q0, qd0 = jnp.array([0.7, -0.4]), jnp.array([0.3, 1.1])

    def final(system, masses, q0):
        heavier = eqx.tree_at(lambda t: t.mass, tree, masses)
        return jl.simulate(system, q0, qd0, ts, args=heavier).q[-1]

    fast = jax.jit(jax.jacrev(lambda m: final(recursive, m, q0)))(tree.mass * 1.2)
    slow = jax.jit(jax.jacrev(lambda m: final(autodiff, m, q0)))(tree.mass * 1.2)
    np.testing.assert_allclose(fast, slow, rtol=1e-9, atol=1e-12)
    starts = q0[None, :] * jnp.array([[1.0], [0.5], [-0.8]])
    fast = jax.jit(jax.vmap(lambda q: final(recursive, tree.mass, q)))(starts)
    slow = jax.jit(jax.vmap(lambda q: final(autodiff, tree.mass, q)))(starts)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12)


def test_recursive_dynamics_with_a_loop_closure_and_limits():
    """The KKT solve applies on top: the double pendulum's tip held on a vertical line (a loop
    closure) moves and pulls alike with both dynamics, and a joint stop still stops."""
    import jaxlag as jl

    tree = jlr.load(HANGING)
    base = jlr.system(tree, limits=False)

    def tip_x(q):
        return -(jnp.sin(q[0]) + jnp.sin(q[0] + q[1]))

    q0, qd0 = jnp.array([0.5, -0.3]), jnp.array([0.4, 0.0])
    qd0 = qd0.at[1].set(-qd0[0] * (jnp.cos(q0[0]) + jnp.cos(q0[0] + q0[1])) / jnp.cos(q0[0] + q0[1]))
    x0 = tip_x(q0)

    def closed(dynamics):
        return jl.System(
            lambda q, qd, t, args: base.lagrangian(q, qd, t=t, args=args),
            holonomic=lambda q: jnp.array([tip_x(q) - x0]),
            dynamics=dynamics,
        )

    ts = jnp.linspace(0.0, 0.5, 6)
    fast = jl.simulate(closed(jlr.TreeDynamics(tree)), q0, qd0, ts)
    slow = jl.simulate(closed(jl.AutodiffDynamics()), q0, qd0, ts)
    np.testing.assert_allclose(fast.q, slow.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.multipliers, slow.multipliers, rtol=1e-10, atol=1e-11)
    np.testing.assert_allclose(jax.vmap(tip_x)(fast.q), x0, atol=1e-8)

    with pytest.raises(TypeError, match="AbstractDynamics"):
        jl.System(lambda q, qd: 0.5 * qd @ qd, dynamics=object())  # pyright: ignore[reportArgumentType]


@pytest.mark.parametrize("name", list(MODELS))
def test_articulated_body_dynamics_solves_without_forming_M(name):
    """``ArticulatedBodyDynamics`` applies ``M⁻¹`` by the articulated-body algorithm (the
    quaternion rows through ``M = Hᵀ diag(M_v, I) H``): ``M⁻¹ M = I`` to rounding, and the
    accelerations and stop multipliers equal `TreeDynamics`'s (dense ``M``, Cholesky)."""
    import jaxlag as jl

    tree = jlr.load(MODELS[name])
    model = mujoco.MjModel.from_xml_string(MODELS[name])
    dense = jlr.system(tree)
    sweeps = jlr.system(tree, dynamics=jlr.ArticulatedBodyDynamics(tree))
    k = tree.actuation.shape[1]
    if k:
        dense = dense.with_control(lambda q, qd: jnp.linspace(0.5, -0.5, k))
        sweeps = sweeps.with_control(lambda q, qd: jnp.linspace(0.5, -0.5, k))
    for q, v in zip(*_random_states(model, np.random.default_rng(7), 2)):
        q, v = jnp.asarray(q), jnp.asarray(v)
        qd = jlr.configuration_rate(tree, q, v)
        mass = dense.mass_matrix(q, qd)
        inverse = jax.jit(
            lambda q, qd: sweeps.dynamics.mass_solver(sweeps, q, qd, jnp.zeros(()), None)(jnp.eye(tree.nq))
        )
        np.testing.assert_allclose(inverse(q, qd) @ mass, np.eye(tree.nq), rtol=0, atol=1e-12)
        expected = dense.accelerations(q, qd)
        np.testing.assert_allclose(
            sweeps.accelerations(q, qd), expected, rtol=0, atol=1e-12 * np.abs(expected).max()
        )
        if dense.holonomic is not None:
            multipliers = dense.multipliers(q, qd)
            np.testing.assert_allclose(
                sweeps.multipliers(q, qd), multipliers, rtol=0, atol=1e-11 * np.abs(multipliers).max()
            )
    assert isinstance(sweeps.dynamics, jl.AbstractDynamics)


def test_articulated_body_dynamics_moves_alike_under_grad():
    """A short run of the hanging double pendulum with a joint stop: the same trajectory, stop
    impact included, and the same gradient with respect to the link masses as `TreeDynamics`."""
    import jaxlag as jl

    tree = jlr.load(HANGING)
    dense, sweeps = jlr.system(tree), jlr.system(tree, dynamics=jlr.ArticulatedBodyDynamics(tree))
    ts = jnp.linspace(0.0, 0.4, 5)
    q0, qd0 = jnp.array([0.7, -0.4]), jnp.array([0.3, 1.1])

    def final(system, masses):
        heavier = eqx.tree_at(lambda t: t.mass, tree, masses)
        return jl.simulate(system, q0, qd0, ts, args=heavier).q[-1]

    np.testing.assert_allclose(final(sweeps, tree.mass), final(dense, tree.mass), rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        jax.jacrev(lambda m: final(sweeps, m))(tree.mass),
        jax.jacrev(lambda m: final(dense, m))(tree.mass),
        rtol=1e-9,
        atol=1e-12,
    )


PENDULUM_BOB = f"""<mujoco>{_NO_CONTACT}<worldbody>
  <body name="bob"><joint type="hinge" axis="0 1 0"/>
    <inertial pos="0 0 -0.8" mass="1.5" diaginertia="0.01 0.02 0.03"/></body>
</worldbody></mujoco>"""


def test_public_functions_compile_once():
    """``mass_matrix``, ``bias_forces``, ``inverse_dynamics``, ``forward_dynamics``,
    ``forward_kinematics`` and ``configuration_rate`` called eagerly are one program each (a
    7-joint arm's mass matrix was 117 programs), reused for a new state. Against the closed form
    of a bob of mass m at l below a hinge about y: ``M = I_yy + m l²``, ``g(q) = m g l sin q``,
    so ``v̇ = −m g l sin q / M``, and the bob's frame rotated by ``q`` about y."""
    names = []

    def listen(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            names.append(kwargs.get("fun_name"))

    tree = jlr.load(PENDULUM_BOB)
    q, other, v = jnp.array([0.4]), jnp.array([-1.1]), jnp.array([0.7])
    acceleration_in, zero = jnp.array([0.3]), jnp.zeros(1)
    inertia, m, l, g = 0.02, 1.5, 0.8, 9.81
    jax.block_until_ready(jlr.mass_matrix(tree, other))  # the options probe and conversions
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        mass = jlr.mass_matrix(tree, q)
        bias = jlr.bias_forces(tree, q, v)
        tau = jlr.inverse_dynamics(tree, q, v, acceleration_in)
        acceleration = jlr.forward_dynamics(tree, q, v, zero)
        poses = jlr.forward_kinematics(tree, q)
        rate = jlr.configuration_rate(tree, q, v)
        jax.block_until_ready((mass, bias, tau, acceleration, poses, rate))
        per_function = len(names)
        jax.block_until_ready((jlr.mass_matrix(tree, other), jlr.bias_forces(tree, other, v)))
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert per_function <= 5, names  # mass_matrix's program is reused; one for each other function
    assert len(names) == per_function, names  # a new state compiles nothing
    total = inertia + m * l**2
    np.testing.assert_allclose(mass, [[total]], rtol=1e-12)
    np.testing.assert_allclose(bias, [m * g * l * np.sin(0.4)], rtol=1e-12)
    np.testing.assert_allclose(tau, [total * 0.3 + m * g * l * np.sin(0.4)], rtol=1e-12)
    np.testing.assert_allclose(acceleration, [-m * g * l * np.sin(0.4) / total], rtol=1e-12)
    c, s = np.cos(0.4), np.sin(0.4)
    np.testing.assert_allclose(poses.rotation[0], [[c, 0, s], [0, 1, 0], [-s, 0, c]], atol=1e-14)
    np.testing.assert_allclose(rate, v, rtol=0)
