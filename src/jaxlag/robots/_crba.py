r"""The composite-rigid-body algorithm: the joint-space mass matrix ``M(q)``."""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import _compile as compilation
from ._kinematics import as_state, world_poses
from ._spatial import inverse_motion_transform, motion_transform, spatial_inertia
from ._tree import KinematicTree, joint_motion, layout


def mass_matrix(tree: KinematicTree, q: Float[ArrayLike, " nq"]) -> Float[Array, "nv nv"]:
    r"""The mass matrix ``M(q)`` (MuJoCo's ``mj_fullM``), armature on its diagonal.

    Composite rigid bodies, in world coordinates: each link's inertia ``I_j`` is carried to the
    world, ``I⁰_j = X_jᵀ I_j X_j``; the composite inertia of the subtree at ``i`` is
    ``I^c_i = Σ_{j ⪰ i} I⁰_j``; each velocity coordinate ``d`` of link ``i(d)`` moves the tree
    along the world motion vector ``s_d`` (a column of ``X_i⁻¹ S_i``); and

    ``M_de = s_dᵀ I^c_{i(e)} s_e`` where ``i(d)`` is ``i(e)`` or an ancestor of it,
    ``M_ed = M_de``, and ``M_de = 0`` where neither link is an ancestor of the other.

    The sums over subtrees and the products are dense masked products (``links²`` and ``nv²``
    entries), which cost less than a recursion for trees of a few hundred links.
    """
    return _mass_matrix(tree, as_state(tree, q, "q"))


# Like every public function here, one program per tree structure and shapes (the tree's
# parameters and the state are inputs): called eagerly, each operation would compile a program
# of its own (117 for a 7-joint arm's M); inside a jit (a robot's equations of motion) inlined.
@compilation.filter_jit
def _mass_matrix(tree, q):
    lay = layout(tree)
    motion = joint_motion(tree, q)
    poses = world_poses(tree, motion)
    to_link = motion_transform(poses.rotation, poses.translation)
    inertia = spatial_inertia(tree.mass, tree.com, tree.inertia)
    world_inertia = jnp.swapaxes(to_link, -1, -2) @ inertia @ to_link
    links = tree.num_links
    subtree = jnp.asarray(lay.subtree, dtype=q.dtype)
    composite = (subtree @ world_inertia.reshape(links, 36)).reshape(links, 6, 6)
    world_subspace = inverse_motion_transform(poses.rotation, poses.translation) @ motion.subspace
    columns = world_subspace[lay.dof_link, :, lay.dof_column]  # (nv, 6)
    momenta = jnp.einsum("dij,dj->di", composite[lay.dof_link], columns)
    products = columns @ momenta.T  # [d, e] = s_dᵀ I^c_{i(e)} s_e
    ancestor = jnp.asarray(lay.dof_ancestor)
    zero = jnp.zeros_like(products)
    full = jnp.where(ancestor, products, jnp.where(ancestor.T, products.T, zero))
    return full + jnp.diag(tree.armature)
