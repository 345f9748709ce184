r"""The articulated-body algorithm: forward dynamics ``v̇ = M⁻¹(τ − damping · v − C v − g)``, O(links)."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import _compile as compilation
from ._kinematics import as_state, world_motion
from ._recursion import ascend, descend
from ._spatial import force_cross, motion_cross, motion_transform, spatial_inertia
from ._tree import _NV, KinematicTree, joint_bias, joint_motion, layout, padded, unpadded


def forward_dynamics(
    tree: KinematicTree,
    q: Float[ArrayLike, " nq"],
    v: Float[ArrayLike, " nv"],
    force: Float[ArrayLike, " nv"] | None = None,
) -> Float[Array, " nv"]:
    r"""The acceleration ``v̇`` that solves ``M(q) v̇ + C(q, v) v + g(q) = τ − damping · v``
    (MuJoCo's ``qacc`` without contacts or limits), by Featherstone's articulated-body algorithm.

    Outward: link velocities ``v_i`` and velocity-product accelerations ``c_i = Ṡ_i v + v_i × S_i v``;
    inward, the articulated inertias and bias forces: ``U_i = I^A_i S_i``, ``D_i = S_iᵀ U_i +
    diag(armature)``, ``u_i = τ_i − S_iᵀ p^A_i``, passing ``X_iᵀ (I^A_i − U_i D_i⁻¹ U_iᵀ) X_i`` and
    ``X_iᵀ (p^A_i + I^a_i c_i + U_i D_i⁻¹ u_i)`` to the parent; outward again,
    ``v̇_i = D_i⁻¹ (u_i − U_iᵀ (X_i a_λ + c_i))`` from the world's ``a_0 = (0, −g)``.

    Args:
        tree: the robot.
        q, v: configuration and velocity (see [`KinematicTree`][jaxlag.robots.KinematicTree]).
        force: the applied joint forces ``τ`` (``nv``); zero if omitted.
    """
    q = as_state(tree, q, "q")
    v = as_state(tree, v)
    tau = jnp.zeros_like(v) if force is None else as_state(tree, force)
    return _forward_dynamics(tree, q, v, tau)


@compilation.filter_jit
def _forward_dynamics(tree, q, v, tau):
    lay = layout(tree)
    motion = joint_motion(tree, q)
    transform = motion_transform(motion.rotation, motion.translation)
    joint_velocity = jnp.einsum("lij,lj->li", motion.subspace, padded(tree, v))
    # the outward velocity sweep as a sum over ancestors in world coordinates, then in each link's frame
    world = world_motion(tree, motion, v)
    velocities = jnp.einsum("lij,lj->li", world.to_link, world.velocity)
    product = joint_bias(tree, q, v) + jnp.einsum("lij,lj->li", motion_cross(velocities), joint_velocity)
    inertia = spatial_inertia(tree.mass, tree.com, tree.inertia)
    bias = jnp.einsum("lij,lj->li", force_cross(velocities), jnp.einsum("lij,lj->li", inertia, velocities))
    # Past a joint's degrees of freedom its rows are padding: D gets 1 there so that it stays
    # invertible, and u and S are 0, so the padded accelerations are 0.
    # The sweeps carry as many columns of S as the widest joint has degrees of freedom (one for
    # a tree of hinges and slides, where D⁻¹ is a division).
    width = max(1, max(_NV[kind] for kind in tree.joint_types))
    mask = jnp.asarray(lay.dof_mask[:, :width])
    subspace = motion.subspace[:, :, :width]
    diagonal = jnp.where(mask, padded(tree, tree.armature)[:, :width], jnp.ones_like(mask, dtype=q.dtype))
    applied = padded(tree, tau - tree.damping * v)[:, :width]

    def invert(d):
        return 1.0 / d if width == 1 else jnp.linalg.inv(d)

    def inward(total, x):
        articulated, pressure = total
        xi, si, ci, taui, di = x
        u_mat = articulated @ si
        d_inv = invert(si.T @ u_mat + jnp.diag(di))
        u = taui - si.T @ pressure
        reduced = articulated - u_mat @ d_inv @ u_mat.T
        passed = pressure + reduced @ ci + u_mat @ (d_inv @ u)
        return (xi.T @ reduced @ xi, xi.T @ passed), (u_mat, d_inv, u)

    u_mats, d_invs, us = ascend(
        lay.parent_slot, (inertia, bias), inward, (transform, subspace, product, applied, diagonal)
    )

    def outward(parent, x):
        a_parent, _ = parent
        xi, si, ci, u_mat, d_inv, u = x
        a = xi @ a_parent + ci
        acceleration = d_inv @ (u - u_mat.T @ a)
        return a + si @ acceleration, acceleration

    root = (jnp.concatenate([jnp.zeros(3, dtype=q.dtype), -tree.gravity]), jnp.zeros(width, dtype=q.dtype))
    _, accelerations = descend(
        lay.parent_slot, root, outward, (transform, subspace, product, u_mats, d_invs, us)
    )
    return unpadded(tree, accelerations)


def _at_rest(tree: KinematicTree) -> KinematicTree:
    """The tree without gravity and damping: ABA at ``v = 0`` on it applies ``M⁻¹``."""
    return eqx.tree_at(
        lambda t: (t.gravity, t.damping), tree, (jnp.zeros_like(tree.gravity), jnp.zeros_like(tree.damping))
    )


def inverse_mass(
    tree: KinematicTree, q: Float[Array, " nq"], b: Float[Array, " nv *columns"]
) -> Float[Array, " nv *columns"]:
    r"""``M(q)⁻¹ b`` (``b`` a vector or the columns of a matrix) by the articulated-body algorithm
    at rest (``v = 0``, no gravity, no damping): ``O(links)`` per column, ``M`` never formed; the
    articulated inertias depend on ``q`` alone, so ``vmap`` over the columns computes them once."""
    still = _at_rest(tree)
    zero = jnp.zeros(tree.nv, dtype=b.dtype)

    def column(x):
        return forward_dynamics(still, q, zero, x)

    return column(b) if b.ndim == 1 else jax.vmap(column, in_axes=1, out_axes=1)(b)
