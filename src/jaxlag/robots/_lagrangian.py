r"""A kinematic tree as a [`jaxlag.System`][jaxlag.System]: its Lagrangian ``L = T − V``.

jaxlag's coordinates and velocities have one length, ``n``: here ``q`` is the tree's
configuration (MuJoCo's ``qpos``, ``n = nq``) and ``q̇`` its time derivative. A ball or free
joint's quaternion ``Q`` then has four rates ``Q̇``, from which ``ω = 2 vec(Q̄ ⊗ Q̇)`` (in the
link's frame), and a holonomic constraint ``|Q|² − 1 = 0`` keeps it of unit length (as
jaxlag's own quaternion bodies do). The kinetic energy ``½ (Q·Q̇)²``, which vanishes on
that constraint's motions, is added so that ``M = ∂²L/∂q̇²`` stays positive definite in the
direction the constraint removes; it changes the multiplier, not the motion.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._custom_types import Args
from .._mechanics.dynamics import AbstractDynamics
from .._mechanics.impacts import Unilateral
from .._mechanics.mass_solve import Factorization
from .._system import System
from ._aba import _at_rest, inverse_mass
from ._crba import mass_matrix as tree_mass_matrix
from ._kinematics import world_motion
from ._rnea import bias_forces, inverse_dynamics
from ._spatial import spatial_inertia
from ._tree import KinematicTree, joint_motion, layout


def _has_quaternions(tree: KinematicTree) -> bool:
    """Whether the tree has a ball or a free joint (``q̇ ≠ v`` there)."""
    return any(kind in ("ball", "free") for kind in tree.joint_types)


def _rotation_blocks(tree: KinematicTree, addresses: tuple[int, ...], width: int) -> np.ndarray:
    """Indices ``address + (3 if free) + arange(width)`` of every ball and free joint, shape
    ``(k, width)``: the quaternions in ``q`` (``q_addresses``, 4), the angular velocities in ``v``
    (``v_addresses``, 3), in the same order."""
    starts = [
        addresses[i] + (3 if kind == "free" else 0)
        for i, kind in enumerate(tree.joint_types)
        if kind in ("ball", "free")
    ]
    return np.asarray(starts, dtype=np.int32).reshape(-1, 1) + np.arange(width, dtype=np.int32)


def _quaternion_blocks(tree: KinematicTree) -> np.ndarray:
    """The ``q`` indices of every ball's and free joint's quaternion, shape ``(k, 4)``."""
    return _rotation_blocks(tree, tree.q_addresses, 4)


def _angular_blocks(tree: KinematicTree) -> np.ndarray:
    """The ``v`` indices of the same joints' angular velocities, shape ``(k, 3)``."""
    return _rotation_blocks(tree, tree.v_addresses, 3)


def tree_velocity(tree: KinematicTree, q: Array, qd: Array) -> Array:
    r"""``v`` from ``(q, q̇)``: ``θ̇`` for hinges and slides, ``ω = 2 vec(Q̄ ⊗ Q̇) = 2 (w ẋ − ẇ x − x × ẋ)``
    for quaternions ``Q = (w, x)``, and the world velocity ``ṗ`` of a free joint's origin."""
    lay = layout(tree)
    qadr = np.asarray(tree.q_addresses, dtype=np.int32)
    vadr = np.asarray(tree.v_addresses, dtype=np.int32)
    v = jnp.zeros(tree.nv, dtype=q.dtype)
    scalar = np.concatenate([lay.groups["hinge"], lay.groups["slide"]])
    if scalar.size:
        v = v.at[vadr[scalar]].set(qd[qadr[scalar]])
    for kind, offset in (("ball", 0), ("free", 3)):
        links = lay.groups[kind]
        if links.size == 0:
            continue
        block = qadr[links][:, None] + offset + np.arange(4)
        quaternion, rate = q[block], qd[block]
        w, x = quaternion[:, :1], quaternion[:, 1:]
        wd, xd = rate[:, :1], rate[:, 1:]
        omega = 2 * (w * xd - wd * x - jnp.cross(x, xd))
        v = v.at[vadr[links][:, None] + offset + np.arange(3)].set(omega)
        if kind == "free":
            v = v.at[vadr[links][:, None] + np.arange(3)].set(qd[qadr[links][:, None] + np.arange(3)])
    return v


def kinetic_energy(tree: KinematicTree, q: Array, v: Array) -> Array:
    r"""``T = ½ Σ_i v_iᵀ I_i v_i + ½ Σ_d armature_d v_d²`` (link velocities and inertias in world
    coordinates), which equals ``½ vᵀ M(q) v``."""
    motion = joint_motion(tree, q)
    world = world_motion(tree, motion, v)
    inertia = (
        jnp.swapaxes(world.to_link, -1, -2)
        @ spatial_inertia(tree.mass, tree.com, tree.inertia)
        @ world.to_link
    )
    return 0.5 * jnp.einsum("li,lij,lj->", world.velocity, inertia, world.velocity) + 0.5 * jnp.sum(
        tree.armature * v**2
    )


def potential_energy(tree: KinematicTree, q: Array) -> Array:
    r"""``V = −Σ_i m_i g · c_i``, with ``c_i`` each link's centre of mass in the world."""
    motion = joint_motion(tree, q)
    world = world_motion(tree, motion, jnp.zeros(tree.nv, dtype=q.dtype))
    centres = world.poses.translation + jnp.einsum("lij,lj->li", world.poses.rotation, tree.com)
    return -jnp.sum(tree.mass * (centres @ tree.gravity))


def _velocity_map(tree: KinematicTree, q: Array) -> Array:
    """``G(q)`` (nv, nq) with ``v = G(q) q̇`` (``v`` is linear in ``q̇``)."""
    return jax.jacfwd(lambda rate: tree_velocity(tree, q, rate))(jnp.zeros_like(q))


def _quaternion_outer(tree: KinematicTree, q: Array) -> Array:
    r"""``P = Σ Q Qᵀ`` over the tree's quaternion blocks (nq, nq): ``∂²/∂q̇² of ½ Σ (Q·Q̇)²``."""
    blocks = _quaternion_blocks(tree)
    quaternions = q[blocks]
    outer = quaternions[:, :, None] * quaternions[:, None, :]
    return jnp.zeros((q.shape[0], q.shape[0]), q.dtype).at[blocks[:, :, None], blocks[:, None, :]].add(outer)


def _along_quaternions(robot: KinematicTree, q: Array, qd: Array, momentum: Array, forces: Array) -> Array:
    r"""``forces`` with each quaternion block's component along ``Q`` replaced by that of
    ``F_L = ∂L/∂q − (∂²L/∂q̇∂q) q̇``, ``Q·F_L = 2 p_ω·ω − |Q|² |Q̇|²``.

    Scaling a quaternion, ``Q → (1 + ε) Q``, leaves its rotation (normalized) and so ``V`` and
    ``M_v`` alone and scales its ``ω = 2 E(Q) Q̇`` (``E`` is linear in ``Q``): ``Q·∂L/∂q = p_ω·ω +
    (Q·Q̇)²``, with ``p = M_v v`` the momentum conjugate to ``v``. And for the fixed vector ``d = Q``,
    ``∂L/∂q̇·d = p·(2 E(Q) d) + (Q·Q̇)(Q·d)``, whose derivative along ``q̇`` (in ``q``, with
    ``E(Q) Q = 0`` and ``E(Q̇) Q = −E(Q) Q̇``) is ``Q·(∂²L/∂q̇∂q) q̇ = −p_ω·ω + |Q̇|²|Q|² + (Q·Q̇)²``.
    """
    blocks = _quaternion_blocks(robot)
    angular = _angular_blocks(robot)
    quaternion, rate = q[blocks], qd[blocks]
    v = tree_velocity(robot, q, qd)
    norms = jnp.sum(quaternion**2, axis=-1)
    exact = 2 * jnp.sum(momentum[angular] * v[angular], axis=-1) - norms * jnp.sum(rate**2, axis=-1)
    current = jnp.sum(quaternion * forces[blocks], axis=-1)
    correction = (exact - current) / norms
    return forces.at[blocks].add(correction[:, None] * quaternion)


class TreeDynamics(AbstractDynamics):
    r"""``M`` and the Lagrangian forces of a kinematic tree by its recursive algorithms.

    For ``L = T − V`` of the tree (`system`), whose velocity ``v = G(q) q̇`` is linear in ``q̇``
    (``G = I`` for hinges and slides; ``ω = 2 E(Q) Q̇``, ``E(Q) = [−x, w I − [x]×]``, for a ball's
    or a free joint's quaternion ``Q = (w, x)``):

    * ``M = ∂²L/∂q̇² = Gᵀ M_v(q) G + Σ Q Qᵀ``, with ``M_v`` the composite-rigid-body mass matrix
      [`mass_matrix`][jaxlag.robots.mass_matrix] (armature on the diagonal) and ``Q Qᵀ`` from
      the ``½ (Q·Q̇)²`` of each quaternion;
    * ``F_L = −Gᵀ (C(q, v) v + g(q) + M_v Ġ q̇)``: Newton–Euler's
      [`inverse_dynamics`][jaxlag.robots.inverse_dynamics] at the acceleration ``v̇ = Ġ q̇`` that
      the map contributes (zero for hinges and slides, where ``F_L`` is minus the
      [`bias_forces`][jaxlag.robots.bias_forces]).

    For hinges and slides these are exactly ``∂²L/∂q̇²`` and ``∂L/∂q − (∂²L/∂q̇∂q) q̇`` of the
    tree's ``L``. With quaternions the recursive ``F_L`` is that of ``L`` up to a multiple of ``Q``
    on each quaternion block (the direction of the row ``|Q|² − 1 = 0``, which the KKT solve
    absorbs into that row's multiplier: ``q̈`` is ``d/dt`` of
    [`configuration_rate`][jaxlag.robots.configuration_rate] along the articulated-body
    acceleration either way, ``G q̈ = v̇ − Ġ q̇`` and ``Q·Q̈ = −|Q̇|²``); that component is set to
    ``L``'s own, ``Q·F_L = 2 p_ω·ω − |Q|²|Q̇|²`` (``p = M_v v``), so that ``F_L`` and every
    multiplier are those of ``L``.

    Joint damping and motors stay the system's dissipation and actuation, added by jaxlag as for
    any ``L`` (``M q̈ = F_L − Gᵀ damping · v + Gᵀ B u + Jᵀλ``). Both cost ``O(links²)``
    multiply-adds in a program that does not grow with the links, instead of the ``n`` gradients
    of ``L`` of automatic differentiation.

    ``tree`` is used when ``args`` is ``None``; otherwise ``args`` is the tree (its inertial
    parameters differentiable), as for the system's ``L``.
    """

    tree: KinematicTree

    def _robot(self, args: Args) -> KinematicTree:
        return self.tree if args is None else args

    def _quaternions(self) -> bool:
        return _has_quaternions(self.tree)

    def mass_matrix(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Float[Array, "n n"]:
        robot = self._robot(args)
        mass = tree_mass_matrix(robot, q)
        if not self._quaternions():
            return mass
        g = _velocity_map(robot, q)
        return g.T @ mass @ g + _quaternion_outer(robot, q)

    def forces(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Float[Array, " n"]:
        return _lagrangian_forces(self._robot(args), q, qd)

    def mass_and_forces(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> tuple[Float[Array, "n n"], Float[Array, " n"]]:
        robot = self._robot(args)
        mass = tree_mass_matrix(robot, q)
        if not self._quaternions():
            return mass, -bias_forces(robot, q, qd)
        g = _velocity_map(robot, q)
        forces = _lagrangian_forces(robot, q, qd, mass @ (g @ qd))
        return g.T @ mass @ g + _quaternion_outer(robot, q), forces


class ArticulatedBodyDynamics(TreeDynamics):
    r"""[`TreeDynamics`][jaxlag.robots.TreeDynamics] whose solves with ``M`` never form it:
    ``M⁻¹ b`` by the articulated-body algorithm, ``O(links)`` per right-hand side.

    The equations of motion take ``q̈ = M⁻¹(F + Jᵀλ)`` (one right-hand side without constraints,
    ``1 + rows`` with them), impacts and projections ``M⁻¹ Jᵀ``: with this object each is one
    pass of the articulated-body algorithm at rest (``v = 0``, no gravity, no damping; the
    articulated inertias are computed once per state), and ``F_L`` comes from Newton–Euler as in
    `TreeDynamics`. So a step costs ``O(links)`` for a tree without constraints, where
    `TreeDynamics` forms the composite-rigid-body ``M`` (``O(links · depth)``) and factors it
    (``O(links³)``). For quaternions, ``M = Hᵀ diag(M_v, I) H`` with ``H = [G; Qᵀ]`` and
    ``H Hᵀ = diag(1 or 4|Q|², |Q|²)``, so ``M⁻¹ = Hᵀ W diag(M_v⁻¹, I) W H``, ``W = (H Hᵀ)⁻¹``.

    Which is faster depends on the tree and the machine. Measured on one CPU core (``python -m
    benchmarks.bench_robots``): per step this object scales as ``N^0.97`` on a hinge chain
    against ``N^1.44`` for `TreeDynamics` (50–200 links), but costs 2× more at 10–50 links and
    1.14× more at 200 (the two cross near 270 links), and 3.5–5.8× more on floating bases of
    17–87 coordinates, whose quaternion rows add right-hand sides to every step's solves and
    projections. Use it for long unconstrained chains. The system's ``mass_solve`` is not consulted: a
    tree of positive masses and inertias has a positive definite ``M`` (the pivots ``D_i`` of the
    algorithm are its articulated inertias). ``M`` itself (`mass_matrix`) is still the
    composite-rigid-body one, for the analyses that need the matrix.
    """

    def mass_solver(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Factorization:
        robot = self._robot(args)
        return Factorization(lambda b: _inverse_mass_in_q(robot, q, b), jnp.asarray(True))

    def solver_and_forces(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> tuple[Factorization, Float[Array, " n"]]:
        return self.mass_solver(system, q, qd, t, args), self.forces(system, q, qd, t, args)


def _lagrangian_forces(robot: KinematicTree, q: Array, qd: Array, momentum: Array | None = None) -> Array:
    r"""``F_L = −Gᵀ(C v + g + M_v Ġ q̇)`` by Newton–Euler, with each quaternion's component along
    ``Q`` that of ``L`` (`_along_quaternions`); ``momentum`` ``M_v v`` if known (else one more
    Newton–Euler pass, at rest)."""
    if not _has_quaternions(robot):
        return -bias_forces(robot, q, qd)
    v, map_acceleration = jax.jvp(lambda x: tree_velocity(robot, x, qd), (q,), (qd,))
    # C v + g + M_v Ġq̇ (armature included in M_v, damping left to the system's dissipation)
    joint_forces = inverse_dynamics(robot, q, v, map_acceleration) - robot.damping * v
    _, pullback = jax.vjp(lambda rate: tree_velocity(robot, q, rate), qd)
    if momentum is None:
        momentum = inverse_dynamics(_at_rest(robot), q, jnp.zeros_like(v), v)  # M_v v
    return _along_quaternions(robot, q, qd, momentum, -pullback(joint_forces)[0])


def _inverse_mass_in_q(robot: KinematicTree, q: Array, b: Array) -> Array:
    r"""``M⁻¹ b`` for ``M = ∂²L/∂q̇²`` (``b`` a vector or a matrix of columns), by `inverse_mass`."""
    if not _has_quaternions(robot):
        return inverse_mass(robot, q, b)
    if b.ndim == 2:
        return jax.vmap(lambda x: _inverse_mass_in_q(robot, q, x), in_axes=1, out_axes=1)(b)
    blocks, angular = _quaternion_blocks(robot), _angular_blocks(robot)
    quaternion = q[blocks]
    norms = jnp.sum(quaternion**2, axis=-1)
    quarter = jnp.broadcast_to(0.25 / norms[:, None], angular.shape)
    weight = jnp.ones(robot.nv, dtype=b.dtype).at[angular].set(quarter)
    # W H b: the velocity part weighted, and Q·b_Q / |Q|² per quaternion
    velocity_part = weight * tree_velocity(robot, q, b)
    normal_part = jnp.sum(quaternion * b[blocks], axis=-1) / norms
    # Hᵀ W diag(M_v⁻¹, I) (·)
    solved = weight * inverse_mass(robot, q, velocity_part)
    _, pullback = jax.vjp(lambda rate: tree_velocity(robot, q, rate), b)
    return pullback(solved)[0] + jnp.zeros_like(b).at[blocks].add((normal_part / norms)[:, None] * quaternion)


def system(
    tree: KinematicTree,
    *,
    limits: bool = True,
    restitution: float = 0.0,
    dynamics: AbstractDynamics | None = None,
) -> System:
    r"""The tree as a [`jaxlag.System`][jaxlag.System], so that [`jaxlag.simulate`][jaxlag.simulate],
    constraints, events, [`jaxlag.analysis.linearize`][jaxlag.analysis.linearize] and
    [`jaxlag.fit`][jaxlag.fit] apply to it.

    * ``L(q, q̇) = T − V``: ``T = ½ vᵀ M(q) v`` summed link by link, ``V = −Σ m_i g · c_i``, with
      ``v`` from ``(q, q̇)`` (``ω = 2 vec(Q̄ ⊗ Q̇)`` for quaternions), plus ``½ (Q·Q̇)²`` per quaternion.
    * ``|Q|² − 1 = 0`` for each ball's and free joint's quaternion (holonomic, one row each).
    * With ``limits=True`` (default), each limited hinge and slide as two one-sided holonomic rows,
      ``q − lower ≥ 0`` and ``upper − q ≥ 0`` (after the quaternion rows), with Newton's
      ``restitution`` at the stops (0: the joint stays at its stop, plastic). Their multipliers are
      the stops' joint forces.
    * With ``limits=True``, each limited ball joint's range (MuJoCo's: the angle ``θ`` of its
      rotation at most ``upper``, any axis) as one one-sided row (after the stops),
      ``|w|/|Q| − cos(upper/2) ≥ 0`` (``cos(θ/2) = |w|/|Q|``, smooth where the limit acts), with the
      same restitution. Its multiplier ``λ ≥ 0`` is a force in quaternion coordinates: the cone's
      torque on the link, in the link's frame, is ``τ = −λ x/2`` for a unit ``Q = (w, x)`` with
      ``w > 0`` (``|x| = sin(θ/2)``: towards the rotation's undoing).
    * Joint damping as the Rayleigh function ``R = ½ Σ damping_d v_d²``.
    * Motors (``tree.actuation = B``) as the input: ``Q_u = (∂v/∂q̇)ᵀ B u``; give a control law with
      [`System.with_control`][jaxlag.System.with_control].

    Parameters: ``args`` is the tree (or ``None`` for the ``tree`` given here), so its masses,
    centres of mass, inertias, gravity, damping and armature are differentiable inputs:
    ``jl.simulate(sys, q0, qd0, ts, args=eqx.tree_at(lambda t: t.mass, tree, masses))``.

    The equations of motion are jaxlag's, ``M q̈ = F + Jᵀλ``; ``dynamics`` says where ``M`` and
    the forces of ``L`` come from (the [`jl.System`][jaxlag.System] option of that name). By
    default (``None``) from the tree's recursive algorithms, ``TreeDynamics(tree)``
    ([`TreeDynamics`][jaxlag.robots.TreeDynamics]: the composite-rigid-body ``M`` and
    Newton–Euler, mapped to ``q̇`` for quaternions), the same quantities as ``M = ∂²L/∂q̇²`` and
    ``∂L/∂q − (∂²L/∂q̇∂q) q̇`` at a fraction of the cost; with
    ``dynamics=jl.AutodiffDynamics()``, by automatic differentiation of ``L``
    ([`jl.AutodiffDynamics`][jaxlag.AutodiffDynamics]). Energy, momenta and everything else come
    from ``L`` either way.
    """
    if not isinstance(tree, KinematicTree):
        raise TypeError(f"jaxlag.robots.system takes a KinematicTree (jaxlag.robots.load); got {type(tree)}.")
    quaternions = _quaternion_blocks(tree)
    stops = np.asarray(
        [
            i
            for i, kind in enumerate(tree.joint_types)
            if limits and tree.limited[i] and kind in ("hinge", "slide")
        ],
        dtype=np.int32,
    )
    stop_coordinates = np.asarray(tree.q_addresses, dtype=np.int32)[stops]
    cones = np.asarray(
        [i for i, kind in enumerate(tree.joint_types) if limits and tree.limited[i] and kind == "ball"],
        dtype=np.int32,
    )
    cone_quaternions = np.asarray(tree.q_addresses, dtype=np.int32)[cones][:, None] + np.arange(4)

    def resolve(args) -> KinematicTree:
        return tree if args is None else args

    def lagrangian(q: Float[Array, " n"], qd: Float[Array, " n"], args) -> Float[Array, ""]:
        robot = resolve(args)
        v = tree_velocity(robot, q, qd)
        value = kinetic_energy(robot, q, v) - potential_energy(robot, q)
        if quaternions.size:
            value = value + 0.5 * jnp.sum(jnp.sum(q[quaternions] * qd[quaternions], axis=-1) ** 2)
        return value

    def holonomic(q: Float[Array, " n"], args) -> Float[Array, " k"]:
        robot = resolve(args)
        angles = q[stop_coordinates]
        cone = q[cone_quaternions]
        half_angle_cosine = jnp.abs(cone[:, 0]) / jnp.sqrt(jnp.sum(cone**2, axis=-1))
        return jnp.concatenate(
            [
                jnp.sum(q[quaternions] ** 2, axis=-1) - 1.0,
                angles - robot.lower[stops],
                robot.upper[stops] - angles,
                half_angle_cosine - jnp.cos(0.5 * robot.upper[cones]),
            ]
        )

    def dissipation(q: Float[Array, " n"], qd: Float[Array, " n"], args) -> Float[Array, ""]:
        robot = resolve(args)
        return 0.5 * jnp.sum(robot.damping * tree_velocity(robot, q, qd) ** 2)

    def actuation(q: Float[Array, " n"], qd: Float[Array, " n"], u, args) -> Float[Array, " n"]:
        robot = resolve(args)
        force = robot.actuation @ jnp.atleast_1d(u)
        _, pullback = jax.vjp(lambda rate: tree_velocity(robot, q, rate), qd)
        return pullback(force)[0]

    rows = quaternions.shape[0] + 2 * stops.size + cones.size
    one_sided = tuple(range(quaternions.shape[0], rows))
    return System(
        lagrangian,
        holonomic=holonomic if rows else None,
        unilateral=Unilateral(one_sided, restitution=restitution) if one_sided else (),
        dissipation=dissipation,
        actuation=actuation if tree.actuation.shape[1] else None,
        dynamics=TreeDynamics(tree) if dynamics is None else dynamics,
    )
