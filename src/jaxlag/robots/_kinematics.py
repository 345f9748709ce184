r"""Forward kinematics: every link's pose and spatial velocity in the world; ``q̇`` from ``v``."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._recursion import descend
from ._spatial import motion_transform
from ._tree import JointMotion, KinematicTree, joint_motion, layout, padded


class LinkPoses(eqx.Module):
    """Every link's frame in the world: ``x_world = translation + rotation @ x_link``."""

    rotation: Float[Array, "links 3 3"]
    translation: Float[Array, "links 3"]


def as_state(tree: KinematicTree, x) -> Array:
    return jnp.asarray(x, dtype=tree.mass.dtype)


def world_poses(tree: KinematicTree, motion: JointMotion) -> LinkPoses:
    dtype = motion.rotation.dtype
    root = (jnp.eye(3, dtype=dtype), jnp.zeros(3, dtype=dtype))

    def step(parent, x):
        rp, pp = parent
        r, p = x
        return rp @ r, pp + rp @ p

    rotation, translation = descend(
        layout(tree).parent_slot, root, step, (motion.rotation, motion.translation)
    )
    return LinkPoses(rotation=rotation, translation=translation)


def link_velocities(tree: KinematicTree, motion: JointMotion, v: Array) -> tuple[Array, Array, Array]:
    """``(X, vJ, v_link)``: the parent-to-link motion transforms, the joints' velocities and the
    links' spatial velocities ``v_i = X_i v_{parent} + S_i v``, in the links' frames."""
    transform = motion_transform(motion.rotation, motion.translation)
    joint_velocity = jnp.einsum("lij,lj->li", motion.subspace, padded(tree, v))
    velocities = descend(
        layout(tree).parent_slot,
        jnp.zeros(6, dtype=v.dtype),
        lambda parent, x: x[0] @ parent + x[1],
        (transform, joint_velocity),
    )
    return transform, joint_velocity, velocities


def forward_kinematics(tree: KinematicTree, q: Float[ArrayLike, " nq"]) -> LinkPoses:
    r"""Every link's pose in the world at configuration ``q``.

    The link's frame composes, from the world down, each link's placement in its parent and its
    joint's motion: ``R_i = R_{parent} R_{i/parent}``, ``p_i = p_{parent} + R_{parent} p_{i/parent}``.
    """
    q = as_state(tree, q)
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
    q = as_state(tree, q)
    v = as_state(tree, v)
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
