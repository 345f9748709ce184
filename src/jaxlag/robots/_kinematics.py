r"""Forward kinematics: every link's pose and spatial velocity in the world; ``q̇`` from ``v``."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import _compile as compilation
from ._spatial import inverse_motion_transform, motion_transform
from ._tree import JointMotion, KinematicTree, joint_motion, layout, padded


class LinkPoses(eqx.Module):
    """Every link's frame in the world: ``x_world = translation + rotation @ x_link``."""

    rotation: Float[Array, "links 3 3"]
    translation: Float[Array, "links 3"]


def as_state(tree: KinematicTree, x, kind: str = "v") -> Array:
    """``x`` as an array of the tree's dtype, refused by name unless it has ``nq`` (``kind="q"``)
    or ``nv`` entries."""
    x = jnp.asarray(x, dtype=tree.mass.dtype)
    size = tree.nq if kind == "q" else tree.nv
    if x.shape != (size,):
        what = "configuration q (MuJoCo's qpos)" if kind == "q" else "velocity-space vector (MuJoCo's qvel)"
        raise ValueError(
            f"jaxlag.robots: a {what} of this tree has shape ({size},); got shape {x.shape}. "
            "Batch with jax.vmap."
        )
    return x


def world_poses(tree: KinematicTree, motion: JointMotion) -> LinkPoses:
    """Each link's pose in the world, by pointer jumping: after step ``k`` every row holds its
    pose relative to its ancestor ``2ᵏ`` levels up (composed as ``R_a R``, ``p_a + R_a p``), so
    ``⌈log₂ depth⌉`` vectorized steps replace a sweep down the tree."""
    dtype = motion.rotation.dtype
    rotation = jnp.concatenate([motion.rotation, jnp.eye(3, dtype=dtype)[None]])
    translation = jnp.concatenate([motion.translation, jnp.zeros((1, 3), dtype=dtype)])
    for ancestor in layout(tree).jumps:
        outer_rotation = rotation[ancestor]
        translation = translation[ancestor] + jnp.einsum("lij,lj->li", outer_rotation, translation)
        rotation = outer_rotation @ rotation
    return LinkPoses(rotation=rotation[:-1], translation=translation[:-1])


class WorldMotion(eqx.Module):
    """A tree's motion in world coordinates (spatial vectors at the world's origin)."""

    poses: LinkPoses
    to_link: Float[Array, "links 6 6"]  # motion vectors from the world to each link's frame
    subspace: Float[Array, "links 6 6"]  # each joint's motion subspace, world frame
    joint_velocity: Float[Array, "links 6"]  # S v, world frame
    velocity: Float[Array, "links 6"]  # each link's spatial velocity, world frame


def world_motion(tree: KinematicTree, motion: JointMotion, v: Array) -> WorldMotion:
    r"""Velocities in world coordinates, where a link's velocity is the sum of its ancestors'
    joint velocities: ``v⁰_i = Σ_{j ⪯ i} X⁰_j S_j v_j`` (one masked product, no sweep)."""
    poses = world_poses(tree, motion)
    subspace = inverse_motion_transform(poses.rotation, poses.translation) @ motion.subspace
    joint_velocity = jnp.einsum("lij,lj->li", subspace, padded(tree, v))
    ancestors = jnp.asarray(layout(tree).subtree.T, dtype=v.dtype)  # [i, j]: j ⪯ i
    return WorldMotion(
        poses=poses,
        to_link=motion_transform(poses.rotation, poses.translation),
        subspace=subspace,
        joint_velocity=joint_velocity,
        velocity=ancestors @ joint_velocity,
    )


def forward_kinematics(tree: KinematicTree, q: Float[ArrayLike, " nq"]) -> LinkPoses:
    r"""Every link's pose in the world at configuration ``q``.

    The link's frame composes, from the world down, each link's placement in its parent and its
    joint's motion: ``R_i = R_{parent} R_{i/parent}``, ``p_i = p_{parent} + R_{parent} p_{i/parent}``.
    """
    return _forward_kinematics(tree, as_state(tree, q, "q"))


@compilation.filter_jit
def _forward_kinematics(tree, q):
    return world_poses(tree, joint_motion(tree, q))


def _quaternion_rate(quaternion: Array, omega: Array) -> Array:
    """``Q̇ = ½ Q ⊗ (0, ω)`` for ``ω`` in the rotated (body) frame."""
    w, x, y, z = quaternion[..., 0], quaternion[..., 1], quaternion[..., 2], quaternion[..., 3]
    a, b, c = omega[..., 0], omega[..., 1], omega[..., 2]
    return 0.5 * jnp.stack(
        [-x * a - y * b - z * c, w * a + y * c - z * b, w * b + z * a - x * c, w * c + x * b - y * a],
        axis=-1,
    )


def configuration_rate(
    tree: KinematicTree, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]
) -> Float[Array, " nq"]:
    r"""``q̇`` from the velocity ``v``: ``θ̇ = v`` for hinges and slides; ``Q̇ = ½ Q ⊗ (0, ω)``
    for a ball's quaternion (``ω`` in the link's frame); ``(ṗ, Q̇) = (v_world, ½ Q ⊗ (0, ω))`` for a
    free joint."""
    return _configuration_rate(tree, as_state(tree, q, "q"), as_state(tree, v))


@compilation.filter_jit
def _configuration_rate(tree, q, v):
    lay = layout(tree)
    qadr = np.asarray(tree.q_addresses, dtype=np.int32)
    vadr = np.asarray(tree.v_addresses, dtype=np.int32)
    rate = jnp.zeros_like(q)
    scalar = np.concatenate([lay.groups["hinge"], lay.groups["slide"]])
    if scalar.size:
        rate = rate.at[qadr[scalar]].set(v[vadr[scalar]])
    for kind, offset in (("ball", 0), ("free", 3)):
        links = lay.groups[kind]
        if links.size == 0:
            continue
        quaternion = q[qadr[links][:, None] + offset + np.arange(4)]
        omega = v[vadr[links][:, None] + offset + np.arange(3)]
        rate = rate.at[qadr[links][:, None] + offset + np.arange(4)].set(_quaternion_rate(quaternion, omega))
        if kind == "free":
            rate = rate.at[qadr[links][:, None] + np.arange(3)].set(v[vadr[links][:, None] + np.arange(3)])
    return rate


__all__ = ["LinkPoses", "configuration_rate", "forward_kinematics"]
