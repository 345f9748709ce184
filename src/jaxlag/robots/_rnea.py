r"""Newton–Euler: inverse dynamics and the bias forces ``C(q, v) v + g(q)``."""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import _compile as compilation
from ._kinematics import as_state, world_motion
from ._spatial import force_cross, inverse_motion_transform, motion_cross, spatial_inertia
from ._tree import KinematicTree, joint_bias, joint_motion, layout, padded, unpadded


def _newton_euler(tree: KinematicTree, q: Array, v: Array, a: Array) -> Array:
    r"""The rigid-body terms ``M_rb(q) a + C(q, v) v + g(q)`` (no armature, no damping).

    Featherstone's recursive Newton–Euler algorithm in world coordinates, where each outward
    recursion is a sum over a link's ancestors and each inward one a sum over its subtree:

    * ``v_i = Σ_{j ⪯ i} S_j v_j``,
    * ``a_i = a_0 + Σ_{j ⪯ i} (S_j a_j + Ṡ_j v_j)`` with ``Ṡ_j v_j = v_j × S_j v_j + X⁰_j cJ_j``
      and the world's ``a_0 = (0, −g)`` (gravity as an upward acceleration of the base),
    * ``f_i = I_i a_i + v_i ×* I_i v_i``, ``τ_i = S_iᵀ Σ_{j ⪰ i} f_j``.

    The sums are products with the tree's (static) ancestor mask: no sequential sweep, and
    ``O(links²)`` multiply-adds, fewer than a sweep's loop overhead costs below a few hundred links.
    """
    lay = layout(tree)
    motion = joint_motion(tree, q)
    world = world_motion(tree, motion, v)
    from_link = inverse_motion_transform(world.poses.rotation, world.poses.translation)
    joint_bias_world = jnp.einsum("lij,lj->li", from_link, joint_bias(tree, q, v))
    increments = (
        jnp.einsum("lij,lj->li", world.subspace, padded(tree, a))
        + joint_bias_world
        + jnp.einsum("lij,lj->li", motion_cross(world.velocity), world.joint_velocity)
    )
    subtree = jnp.asarray(lay.subtree, dtype=q.dtype)
    root = jnp.concatenate([jnp.zeros(3, dtype=q.dtype), -tree.gravity])
    accelerations = root[None, :] + subtree.T @ increments
    link_inertia = spatial_inertia(tree.mass, tree.com, tree.inertia)
    inertia = jnp.swapaxes(world.to_link, -1, -2) @ link_inertia @ world.to_link
    momentum = jnp.einsum("lij,lj->li", inertia, world.velocity)
    forces = jnp.einsum("lij,lj->li", inertia, accelerations) + jnp.einsum(
        "lij,lj->li", force_cross(world.velocity), momentum
    )
    totals = subtree @ forces
    return unpadded(tree, jnp.einsum("lji,lj->li", world.subspace, totals))


def bias_forces(
    tree: KinematicTree, q: Float[ArrayLike, " nq"], v: Float[ArrayLike, " nv"]
) -> Float[Array, " nv"]:
    r"""The bias forces ``C(q, v) v + g(q)`` (MuJoCo's ``qfrc_bias``): the joint forces that hold
    the tree at zero acceleration, by Newton–Euler with ``v̇ = 0``.

    With them, the equation of motion is ``M(q) v̇ + C(q, v) v + g(q) = τ − damping · v``.
    """
    return _bias_forces(tree, as_state(tree, q, "q"), as_state(tree, v))


@compilation.filter_jit
def _bias_forces(tree, q, v):
    return _newton_euler(tree, q, v, jnp.zeros_like(v))


def inverse_dynamics(
    tree: KinematicTree,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    acceleration: Float[ArrayLike, " nv"],
) -> Float[Array, " nv"]:
    r"""The joint forces ``τ`` that produce ``acceleration = v̇`` at ``(q, v)``:
    ``τ = M(q) v̇ + C(q, v) v + g(q) + damping · v`` (armature included in ``M``), the exact
    inverse of [`forward_dynamics`][jaxlag.robots.forward_dynamics]. Newton–Euler.
    """
    states = as_state(tree, q, "q"), as_state(tree, v), as_state(tree, acceleration)
    return _inverse_dynamics(tree, *states)


@compilation.filter_jit
def _inverse_dynamics(tree, q, v, acceleration):
    return _newton_euler(tree, q, v, acceleration) + tree.armature * acceleration + tree.damping * v
