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
from .._mechanics.dynamics import AbstractDynamics, AutodiffDynamics
from .._mechanics.impacts import Unilateral
from .._system import System
from ._crba import mass_matrix as tree_mass_matrix
from ._kinematics import world_motion
from ._rnea import bias_forces
from ._spatial import spatial_inertia
from ._tree import KinematicTree, joint_motion, layout


def _quaternion_blocks(tree: KinematicTree) -> np.ndarray:
    """The ``q`` indices of every ball's and free joint's quaternion, shape ``(k, 4)``."""
    starts = [
        tree.q_addresses[i] + (3 if kind == "free" else 0)
        for i, kind in enumerate(tree.joint_types)
        if kind in ("ball", "free")
    ]
    return np.asarray(starts, dtype=np.int32).reshape(-1, 1) + np.arange(4, dtype=np.int32)


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


def recursive(tree: KinematicTree) -> bool:
    """Whether the tree's ``q̇`` is its velocity ``v`` (hinges, slides and fixed links only)."""
    return all(kind in ("hinge", "slide", "fixed") for kind in tree.joint_types)


class TreeDynamics(AbstractDynamics):
    r"""``M`` and the Lagrangian forces of a tree of hinges and slides by its recursive algorithms.

    For ``L = T − V`` of the tree (`system`), with ``q̇ = v``:
    ``M = ∂²L/∂q̇²`` is the composite-rigid-body mass matrix
    [`mass_matrix`][jaxlag.robots.mass_matrix] (armature on the diagonal), and
    ``F_L = ∂L/∂q − (∂²L/∂q̇∂q) q̇ = −(C(q, q̇) q̇ + g(q))``, minus Newton–Euler's
    [`bias_forces`][jaxlag.robots.bias_forces]. Joint damping and motors stay the system's
    dissipation and actuation, added by jaxlag as for any ``L`` (``M q̈ = F_L − damping · q̇ + B u
    + Jᵀλ``). Both cost ``O(links²)`` multiply-adds in a program that does not grow with the
    links, instead of the ``n`` gradients of ``L`` of automatic differentiation.

    ``tree`` is used when ``args`` is ``None``; otherwise ``args`` is the tree (its inertial
    parameters differentiable), as for the system's ``L``. Ball and free joints (``q̇ ≠ v``) are
    refused: their systems keep [`jl.AutodiffDynamics`][jaxlag.AutodiffDynamics].
    """

    tree: KinematicTree

    def __check_init__(self):
        if not recursive(self.tree):
            raise ValueError(
                "TreeDynamics takes trees of hinge and slide joints only (q̇ = v); this one has "
                f"{sorted(set(self.tree.joint_types) - {'hinge', 'slide', 'fixed'})} joints, whose "
                "quaternion rates are not their velocities: keep jl.AutodiffDynamics()."
            )

    def _robot(self, args: Args) -> KinematicTree:
        return self.tree if args is None else args

    def mass_matrix(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Float[Array, "n n"]:
        return tree_mass_matrix(self._robot(args), q)

    def forces(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Float[Array, " n"]:
        return -bias_forces(self._robot(args), q, qd)


def system(
    tree: KinematicTree, *, limits: bool = True, restitution: float = 0.0, recursive_dynamics: bool = True
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
      the stops' joint forces. The limits of ball joints (cones) are not imposed.
    * Joint damping as the Rayleigh function ``R = ½ Σ damping_d v_d²``.
    * Motors (``tree.actuation = B``) as the input: ``Q_u = (∂v/∂q̇)ᵀ B u``; give a control law with
      [`System.with_control`][jaxlag.System.with_control].

    Parameters: ``args`` is the tree (or ``None`` for the ``tree`` given here), so its masses,
    centres of mass, inertias, gravity, damping and armature are differentiable inputs:
    ``jl.simulate(sys, q0, qd0, ts, args=eqx.tree_at(lambda t: t.mass, tree, masses))``.

    The equations of motion are jaxlag's, ``M q̈ = F + Jᵀλ``. With ``recursive_dynamics=True``
    (default) and a tree of hinges and slides only, ``M`` and the forces of ``L`` come from the
    tree's recursive algorithms ([`TreeDynamics`][jaxlag.robots.TreeDynamics]: the
    composite-rigid-body ``M`` and minus Newton–Euler's bias forces), the same quantities as
    ``M = ∂²L/∂q̇²`` and ``∂L/∂q − (∂²L/∂q̇∂q) q̇`` at a fraction of the cost; with ball or free
    joints, or ``recursive_dynamics=False``, by automatic differentiation of ``L``
    ([`jl.AutodiffDynamics`][jaxlag.AutodiffDynamics]). Energy, momenta and everything else
    come from ``L`` either way.
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
        return jnp.concatenate(
            [
                jnp.sum(q[quaternions] ** 2, axis=-1) - 1.0,
                angles - robot.lower[stops],
                robot.upper[stops] - angles,
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

    rows = quaternions.shape[0] + 2 * stops.size
    one_sided = tuple(range(quaternions.shape[0], rows))
    return System(
        lagrangian,
        holonomic=holonomic if rows else None,
        unilateral=Unilateral(one_sided, restitution=restitution) if one_sided else (),
        dissipation=dissipation,
        actuation=actuation if tree.actuation.shape[1] else None,
        dynamics=TreeDynamics(tree) if recursive_dynamics and recursive(tree) else AutodiffDynamics(),
    )
