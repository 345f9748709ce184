r"""The kinematic tree: links, their joints and their inertias, as one equinox Module.

A *link* carries one joint. A body of the robot's file with several joints becomes a chain of
links, massless but for the last, which carries the body's inertia; a body welded to its parent
is a link with a ``"fixed"`` joint. Links are numbered so that a parent comes before its
children (MuJoCo's body order).

Coordinates (as MuJoCo's ``qpos`` and ``qvel``, in the same order):

============  ==========================================  ============================================
joint         configuration (``nq`` entries)              velocity (``nv`` entries)
============  ==========================================  ============================================
``hinge``     angle ``θ`` (1)                             ``θ̇`` (1)
``slide``     displacement ``d`` (1)                      ``ḋ`` (1)
``ball``      quaternion ``(w, x, y, z)`` of the link      angular velocity ``ω`` in the link's frame (3)
              relative to its parent (4)
``free``      position of the link's origin in the world,  velocity of the origin in the *world* frame,
              then its quaternion (7)                     then ``ω`` in the *link's* frame (6)
``fixed``     none                                        none
============  ==========================================  ============================================

So ``nq ≠ nv`` as soon as a ball or free joint is present; `configuration_rate` gives ``q̇``
from ``v``. Quaternions are normalized before use.
"""

import functools
from typing import Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._spatial import axis_angle_rotation, quaternion_rotation, skew

JointType = Literal["hinge", "slide", "ball", "free", "fixed"]
JOINT_TYPES: tuple[str, ...] = ("hinge", "slide", "ball", "free", "fixed")
_NQ = {"hinge": 1, "slide": 1, "ball": 4, "free": 7, "fixed": 0}
_NV = {"hinge": 1, "slide": 1, "ball": 3, "free": 6, "fixed": 0}


class KinematicTree(eqx.Module):
    r"""A tree of rigid links connected by joints, with its inertial parameters as arrays.

    Each link's frame sits, in its parent's frame, at the fixed *placement*
    ``(placement_rotation, placement_translation)`` followed by the joint's motion: a hinge
    turns by ``θ − reference`` about ``axis`` through ``anchor``; a slide moves by ``(d −
    reference) axis``; a ball turns by its quaternion about ``anchor``; a free joint places
    the link directly (its placement is the identity). All vectors are in the link's own
    frame, as MuJoCo's ``jnt_axis`` and ``jnt_pos``.

    The inertial parameters (``mass``, ``com``, ``inertia``), ``gravity``, ``damping`` and
    ``armature`` are arrays, so they can be traced, batched and fitted (replace them with
    `equinox.tree_at`); the tree's structure is static.

    Fields:
        parents: each link's parent link, ``-1`` for the world (static).
        joint_types: each link's joint, one of ``"hinge"``, ``"slide"``, ``"ball"``, ``"free"``,
            ``"fixed"`` (static).
        q_addresses, v_addresses: where each link's coordinates start in ``q`` and ``v``
            (static; ``-1`` for a fixed joint).
        names: each link's name (static).
        placement_rotation, placement_translation: the link's frame in its parent's frame at
            zero joint motion: ``R`` maps link components to parent components, ``p`` is the link's
            origin in the parent's coordinates.
        axis, anchor, reference: the joint's unit axis, the point it turns about and the
            coordinate at which it is at rest (MuJoCo's ``qpos0`` of hinges and slides).
        mass, com, inertia: each link's mass, centre of mass and rotational inertia about the
            centre of mass (3 × 3, link frame).
        gravity: the gravitational acceleration in world coordinates, e.g. ``(0, 0, −9.81)``.
        damping, armature: per velocity coordinate: viscous damping (a generalized force
            ``−damping · v``) and the rotor inertia added to ``M``'s diagonal.
        limited, lower, upper: per link: whether the joint's range is limited, and the range.
        actuation: ``B`` (``nv × nu``): actuator commands ``u`` act as ``τ = B u``.
        default_configuration: the configuration at which the model was built (``qpos0``).
    """

    parents: tuple[int, ...] = eqx.field(static=True)
    joint_types: tuple[str, ...] = eqx.field(static=True)
    q_addresses: tuple[int, ...] = eqx.field(static=True)
    v_addresses: tuple[int, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    limited: tuple[bool, ...] = eqx.field(static=True)
    placement_rotation: Float[Array, "links 3 3"]
    placement_translation: Float[Array, "links 3"]
    axis: Float[Array, "links 3"]
    anchor: Float[Array, "links 3"]
    reference: Float[Array, " links"]
    mass: Float[Array, " links"]
    com: Float[Array, "links 3"]
    inertia: Float[Array, "links 3 3"]
    gravity: Float[Array, "3"]
    damping: Float[Array, " nv"]
    armature: Float[Array, " nv"]
    lower: Float[Array, " links"]
    upper: Float[Array, " links"]
    actuation: Float[Array, "nv nu"]
    default_configuration: Float[Array, " nq"]

    def __check_init__(self):
        links = len(self.parents)
        for name in ("joint_types", "q_addresses", "v_addresses", "names", "limited"):
            if len(getattr(self, name)) != links:
                raise ValueError(
                    f"KinematicTree: {name} has {len(getattr(self, name))} entries for {links} links."
                )
        for i, parent in enumerate(self.parents):
            if not -1 <= parent < i:
                raise ValueError(
                    f"KinematicTree: link {i}'s parent is {parent}; parents must come before their children."
                )
        for kind in self.joint_types:
            if kind not in JOINT_TYPES:
                raise ValueError(
                    f"KinematicTree: unknown joint type {kind!r}; expected one of {JOINT_TYPES}."
                )
        for i, kind in enumerate(self.joint_types):
            if kind == "free" and self.parents[i] != -1:
                raise ValueError(f"KinematicTree: link {i} has a free joint but its parent is not the world.")

    @property
    def num_links(self) -> int:
        """The number of links."""
        return len(self.parents)

    @property
    def nq(self) -> int:
        """The number of configuration coordinates (a quaternion counts 4)."""
        return sum(_NQ[kind] for kind in self.joint_types)

    @property
    def nv(self) -> int:
        """The number of velocity coordinates (degrees of freedom)."""
        return sum(_NV[kind] for kind in self.joint_types)


class Layout(eqx.Module):
    """Index tables derived from a tree's static structure (NumPy, computed once per structure)."""

    parent_slot: np.ndarray  # (links,) the parent's row in arrays of links + 1 rows (world last)
    dof_index: np.ndarray  # (links, 6) each link's velocity coordinates, padded with nv
    dof_mask: np.ndarray  # (links, 6) True where dof_index is a coordinate
    dof_link: np.ndarray  # (nv,) the link of each velocity coordinate
    dof_column: np.ndarray  # (nv,) its column in the link's padded motion subspace
    subtree: np.ndarray  # (links, links) subtree[i, j]: j is i or a descendant of i
    dof_ancestor: np.ndarray  # (nv, nv) [d, e]: the link of d is the link of e or an ancestor of it
    jumps: tuple  # pointer jumping: the ancestor 1, 2, 4, ... levels up of each row (world = links)
    groups: dict  # joint type -> array of its links
    order: np.ndarray  # the permutation from links grouped by type back to link order


@functools.lru_cache(maxsize=64)
def _layout(parents: tuple[int, ...], joint_types: tuple[str, ...], v_addresses: tuple[int, ...]) -> Layout:
    links = len(parents)
    nv = sum(_NV[kind] for kind in joint_types)
    dof_index = np.full((links, 6), nv, dtype=np.int32)
    dof_link = np.zeros(nv, dtype=np.int32)
    dof_column = np.zeros(nv, dtype=np.int32)
    for i, kind in enumerate(joint_types):
        for k in range(_NV[kind]):
            dof_index[i, k] = v_addresses[i] + k
            dof_link[v_addresses[i] + k] = i
            dof_column[v_addresses[i] + k] = k
    subtree = np.eye(links, dtype=bool)
    for j in range(links):
        i = parents[j]
        while i >= 0:
            subtree[i, j] = True
            i = parents[i]
    # ancestors 2^k levels up, for each of the ceil(log2(depth)) steps that compose a path to the root
    ancestor = np.array([p if p >= 0 else links for p in parents] + [links], dtype=np.int32)
    depth = np.zeros(links, dtype=np.int64)
    for i, parent in enumerate(parents):
        depth[i] = 1 + (depth[parent] if parent >= 0 else 0)
    jumps = []
    reach = 1
    while reach < (depth.max() if links else 0):
        jumps.append(ancestor)
        ancestor = ancestor[ancestor]
        reach *= 2
    groups = {
        kind: np.array([i for i in range(links) if joint_types[i] == kind], dtype=np.int32)
        for kind in JOINT_TYPES
    }
    grouped = np.concatenate([groups[kind] for kind in JOINT_TYPES])
    order = np.argsort(grouped).astype(np.int32)
    return Layout(
        parent_slot=np.array([p if p >= 0 else links for p in parents], dtype=np.int32),
        dof_index=dof_index,
        dof_mask=dof_index < nv,
        dof_link=dof_link,
        dof_column=dof_column,
        subtree=subtree,
        jumps=tuple(jumps),
        dof_ancestor=subtree[dof_link][:, dof_link],
        groups=groups,
        order=order,
    )


def layout(tree: KinematicTree) -> Layout:
    return _layout(tree.parents, tree.joint_types, tree.v_addresses)


class JointMotion(eqx.Module):
    """Each link's pose in its parent's frame and its joint's motion subspace, at one ``q``."""

    rotation: Float[Array, "links 3 3"]  # link components -> parent components
    translation: Float[Array, "links 3"]  # the link's origin in the parent's coordinates
    subspace: Float[Array, "links 6 6"]  # S: padded velocities -> the joint's spatial velocity, link frame


def joint_motion(tree: KinematicTree, q: Float[Array, " nq"]) -> JointMotion:
    r"""``(R, p)`` of every link in its parent and ``S(q)``, the joint's motion subspace in the
    link's frame: the link's velocity relative to its parent is ``S v_link``."""
    lay = layout(tree)
    dtype = q.dtype
    eye = jnp.eye(3, dtype=dtype)
    rotations, translations, subspaces = [], [], []
    qadr = np.asarray(tree.q_addresses, dtype=np.int32)
    for kind in JOINT_TYPES:
        links = lay.groups[kind]
        k = links.shape[0]
        if k == 0:
            continue
        axis = tree.axis[links]
        anchor = tree.anchor[links]
        s = jnp.zeros((k, 6, 6), dtype=dtype)
        if kind == "hinge":
            angle = q[qadr[links]] - tree.reference[links]
            r = axis_angle_rotation(axis, angle)
            p = anchor - jnp.einsum("kij,kj->ki", r, anchor)
            s = s.at[:, :3, 0].set(axis).at[:, 3:, 0].set(jnp.cross(anchor, axis))
        elif kind == "slide":
            d = q[qadr[links]] - tree.reference[links]
            r = jnp.broadcast_to(eye, (k, 3, 3))
            p = axis * d[:, None]
            s = s.at[:, 3:, 0].set(axis)
        elif kind == "ball":
            r = quaternion_rotation(q[qadr[links][:, None] + np.arange(4)])
            p = anchor - jnp.einsum("kij,kj->ki", r, anchor)
            s = s.at[:, :3, :3].set(jnp.broadcast_to(eye, (k, 3, 3))).at[:, 3:, :3].set(skew(anchor))
        elif kind == "free":
            block = q[qadr[links][:, None] + np.arange(7)]
            r = quaternion_rotation(block[:, 3:])
            p = block[:, :3]
            # v = (world velocity of the origin, body angular velocity): ω_link = ω, v_link = Rᵀ v_world.
            s = (
                s.at[:, :3, 3:]
                .set(jnp.broadcast_to(eye, (k, 3, 3)))
                .at[:, 3:, :3]
                .set(jnp.swapaxes(r, -1, -2))
            )
        else:
            r = jnp.broadcast_to(eye, (k, 3, 3))
            p = jnp.zeros((k, 3), dtype=dtype)
        rotations.append(r)
        translations.append(p)
        subspaces.append(s)
    order = lay.order
    rj = jnp.concatenate(rotations)[order]
    pj = jnp.concatenate(translations)[order]
    r0 = tree.placement_rotation
    return JointMotion(
        rotation=r0 @ rj,
        translation=tree.placement_translation + jnp.einsum("lij,lj->li", r0, pj),
        subspace=jnp.concatenate(subspaces)[order],
    )


def padded(tree: KinematicTree, v: Float[Array, " nv"]) -> Float[Array, "links 6"]:
    """The velocity coordinates of each link in its row, zero past the joint's degrees of freedom."""
    extended = jnp.concatenate([v, jnp.zeros((1,), dtype=v.dtype)])
    return extended[layout(tree).dof_index]


def unpadded(tree: KinematicTree, rows: Float[Array, "links width"]) -> Float[Array, " nv"]:
    """The velocity coordinates from each link's row (its first ``width`` columns)."""
    lay = layout(tree)
    return rows[lay.dof_link, lay.dof_column]


def joint_bias(
    tree: KinematicTree, q: Float[Array, " nq"], v: Float[Array, " nv"]
) -> Float[Array, "links 6"]:
    r"""``cJ = Ṡ v``, the joint's velocity-product acceleration in the link's frame. Zero but for
    free joints, whose ``S`` turns the world velocity into the link's: ``cJ = (0, −ω × Rᵀ v_world)``."""
    lay = layout(tree)
    links = lay.groups["free"]
    out = jnp.zeros((tree.num_links, 6), dtype=q.dtype)
    if links.shape[0] == 0:
        return out
    qadr = np.asarray(tree.q_addresses, dtype=np.int32)[links]
    vadr = np.asarray(tree.v_addresses, dtype=np.int32)[links]
    r = quaternion_rotation(q[qadr[:, None] + 3 + np.arange(4)])
    v_world = v[vadr[:, None] + np.arange(3)]
    omega = v[vadr[:, None] + 3 + np.arange(3)]
    v_link = jnp.einsum("kji,kj->ki", r, v_world)
    return out.at[links, 3:].set(-jnp.cross(omega, v_link))
