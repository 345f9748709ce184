r"""Recursive Newton–Euler: inverse dynamics and the bias forces ``C(q, v) v + g(q)``, O(links)."""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._kinematics import as_state, link_velocities
from ._recursion import ascend, descend
from ._spatial import force_cross, motion_cross, spatial_inertia
from ._tree import KinematicTree, joint_bias, joint_motion, layout, padded, unpadded


def _newton_euler(tree: KinematicTree, q: Array, v: Array, a: Array) -> Array:
    r"""``Σ`` of the rigid-body terms: ``M_rb(q) a + C(q, v) v + g(q)`` (no armature, no damping).

    Outward: ``v_i = X_i v_λ + S_i v``, ``a_i = X_i a_λ + S_i a + Ṡ_i v + v_i × S_i v`` with the
    world's ``a_0 = (0, −g)`` (gravity as an upward acceleration of the base); then each link's
    net force ``f_i = I_i a_i + v_i ×* I_i v_i``. Inward: ``τ_i = S_iᵀ f_i`` and ``f_λ += X_iᵀ f_i``.
    """
    lay = layout(tree)
    motion = joint_motion(tree, q)
    transform, joint_velocity, velocities = link_velocities(tree, motion, v)
    joint_acceleration = jnp.einsum("lij,lj->li", motion.subspace, padded(tree, a)) + joint_bias(tree, q, v)
    root = jnp.concatenate([jnp.zeros(3, dtype=q.dtype), -tree.gravity])
    accelerations = descend(
        lay.parent_slot,
        root,
        lambda parent, x: x[0] @ parent + x[1],
        (
            transform,
            joint_acceleration + jnp.einsum("lij,lj->li", motion_cross(velocities), joint_velocity),
        ),
    )
    inertia = spatial_inertia(tree.mass, tree.com, tree.inertia)
    momentum = jnp.einsum("lij,lj->li", inertia, velocities)
    forces = jnp.einsum("lij,lj->li", inertia, accelerations) + jnp.einsum(
        "lij,lj->li", force_cross(velocities), momentum
    )

    def inward(total, x):
        xi, si = x
        return xi.T @ total, si.T @ total

    return unpadded(tree, ascend(lay.parent_slot, forces, inward, (transform, motion.subspace)))


def bias_forces(
    tree: KinematicTree, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]
) -> Float[Array, " nv"]:
    r"""The bias forces ``C(q, v) v + g(q)`` (MuJoCo's ``qfrc_bias``): the joint forces that hold
    the tree at zero acceleration, by the recursive Newton–Euler algorithm with ``v̇ = 0``.

    With them, the equation of motion is ``M(q) v̇ + C(q, v) v + g(q) = τ − damping · v``.
    """
    q = as_state(tree, q)
    v = as_state(tree, v)
    return _newton_euler(tree, q, v, jnp.zeros_like(v))


def inverse_dynamics(
    tree: KinematicTree,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    acceleration: Float[ArrayLike, " nv"],
) -> Float[Array, " nv"]:
    r"""The joint forces ``τ`` that produce ``acceleration = v̇`` at ``(q, v)``:
    ``τ = M(q) v̇ + C(q, v) v + g(q) + damping · v`` (armature included in ``M``), the exact
    inverse of [`forward_dynamics`][jaxlag.robots.forward_dynamics]. Recursive Newton–Euler, O(links).
    """
    q = as_state(tree, q)
    v = as_state(tree, v)
    acceleration = as_state(tree, acceleration)
    return _newton_euler(tree, q, v, acceleration) + tree.armature * acceleration + tree.damping * v
