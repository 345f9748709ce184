r"""Kinematic trees from MJCF and URDF, read by MuJoCo's model compiler.

MuJoCo (the ``robots`` extra: ``pip install "jaxlag[robots]"``) parses the file, resolves its
defaults and computes link inertias from geoms where the file gives none; jaxlag copies the
compiled model's arrays (``body_*``, ``jnt_*``, ``dof_*``, ``opt.gravity``, ``actuator_*``).
MuJoCo is not used after loading.
"""

import os
from typing import Any

import jax.numpy as jnp
import numpy as np

from ._tree import KinematicTree

_TYPES = {0: "free", 1: "ball", 2: "slide", 3: "hinge"}


def _mujoco() -> Any:
    try:
        import mujoco
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError(
            "jaxlag.robots reads MJCF and URDF with MuJoCo's model compiler, which is not installed: "
            'pip install "jaxlag[robots]" (or pip install mujoco).'
        ) from error
    return mujoco


def _rotation(quaternion: np.ndarray) -> np.ndarray:
    w, x, y, z = quaternion / np.linalg.norm(quaternion)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _name(mujoco, model, kind, index: int, fallback: str) -> str:
    name = mujoco.mj_id2name(model, kind, index)
    return name if name else fallback


def _refuse(model, mujoco) -> None:
    """Features that change the motion and that the tree does not model: refused by name."""
    problems = []
    if model.neq:
        problems.append(f"{model.neq} equality constraint(s) (add loop closures as holonomic constraints)")
    if np.any(model.dof_frictionloss != 0):
        problems.append("joint friction loss (frictionloss)")
    if np.any(model.jnt_stiffness != 0):
        problems.append("joint stiffness (stiffness)")
    if np.any(model.body_gravcomp != 0):
        problems.append("gravity compensation (gravcomp)")
    if model.ntendon:
        problems.append(f"{model.ntendon} tendon(s)")
    if model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_GRAVITY):
        problems.append("gravity disabled by a flag (set gravity to 0 instead)")
    if problems:
        raise ValueError("jaxlag.robots cannot import this model: it has " + "; ".join(problems) + ".")


def _actuation(model, mujoco, joint_dof: np.ndarray) -> np.ndarray:
    """``B``: plain motors on hinges and slides act as ``τ_dof = gear · gain · u``."""
    columns = np.zeros((model.nv, model.nu))
    for k in range(model.nu):
        name = _name(mujoco, model, mujoco.mjtObj.mjOBJ_ACTUATOR, k, f"actuator {k}")
        joint = int(model.actuator_trnid[k, 0])
        plain = (
            model.actuator_trntype[k] == int(mujoco.mjtTrn.mjTRN_JOINT)
            and model.actuator_dyntype[k] == int(mujoco.mjtDyn.mjDYN_NONE)
            and model.actuator_gaintype[k] == int(mujoco.mjtGain.mjGAIN_FIXED)
            and model.actuator_biastype[k] == int(mujoco.mjtBias.mjBIAS_NONE)
            and _TYPES[int(model.jnt_type[joint])] in ("hinge", "slide")
        )
        if not plain:
            raise ValueError(
                f"jaxlag.robots imports motors on hinge and slide joints (force = gear · ctrl); "
                f"{name!r} is another kind of actuator: remove it from the file, or model it with "
                "jl.System's forces=."
            )
        columns[joint_dof[joint], k] = model.actuator_gear[k, 0] * model.actuator_gainprm[k, 0]
    return columns


def from_mujoco(model: Any) -> KinematicTree:
    r"""A [`KinematicTree`][jaxlag.robots.KinematicTree] from a compiled `mujoco.MjModel`.

    Each body becomes one link per joint (massless but for the last, which carries the body's
    ``body_mass``, ``body_ipos`` and ``body_inertia`` turned by ``body_iquat``), or one fixed
    link if it has none; the first link sits at ``body_pos``, ``body_quat`` in its parent
    (a free joint's link at the identity: its ``q`` is the world pose). Joints keep MuJoCo's
    ``qpos`` and ``qvel`` layout. Refused, by name: equality constraints, tendons, friction loss,
    joint stiffness, gravity compensation, and actuators other than motors on hinges and slides.
    Geoms (contacts) are not imported. Joint limits are kept on the tree (``limited``, ``lower``,
    ``upper``); [`system`][jaxlag.robots.system] imposes those of hinges, slides and ball joints
    (a cone on the rotation angle) as one-sided constraints, while the recursive algorithms ignore
    them (as MuJoCo's ``qacc`` does away from the limits).
    """
    mujoco = _mujoco()
    _refuse(model, mujoco)
    parents: list[int] = []
    joint_types: list[str] = []
    q_addresses: list[int] = []
    v_addresses: list[int] = []
    names: list[str] = []
    limited: list[bool] = []
    rows: dict[str, list] = {
        key: []
        for key in (
            "placement_rotation",
            "placement_translation",
            "axis",
            "anchor",
            "reference",
            "mass",
            "com",
            "inertia",
            "lower",
            "upper",
        )
    }
    last_link = {0: -1}  # body -> its last link; the world is -1
    for body in range(1, model.nbody):
        first = int(model.body_jntadr[body])
        joints = list(range(first, first + int(model.body_jntnum[body])))
        body_name = _name(mujoco, model, mujoco.mjtObj.mjOBJ_BODY, body, f"body{body}")
        body_rotation = _rotation(model.body_quat[body])
        principal = _rotation(model.body_iquat[body])
        body_inertia = principal @ np.diag(model.body_inertia[body]) @ principal.T
        for position, joint in enumerate([*joints] if joints else [None]):
            last = position == max(len(joints), 1) - 1
            kind = "fixed" if joint is None else _TYPES[int(model.jnt_type[joint])]
            parents.append(last_link[int(model.body_parentid[body])] if position == 0 else len(parents) - 1)
            joint_types.append(kind)
            q_addresses.append(-1 if joint is None else int(model.jnt_qposadr[joint]))
            v_addresses.append(-1 if joint is None else int(model.jnt_dofadr[joint]))
            joint_name = None if joint is None else mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, joint)
            names.append(body_name if last else (joint_name or f"{body_name}/joint{position}"))
            limited.append(bool(joint is not None and model.jnt_limited[joint]))
            placed = position == 0 and kind != "free"
            rows["placement_rotation"].append(body_rotation if placed else np.eye(3))
            rows["placement_translation"].append(model.body_pos[body] if placed else np.zeros(3))
            rows["axis"].append(np.zeros(3) if joint is None else model.jnt_axis[joint])
            rows["anchor"].append(np.zeros(3) if joint is None or kind == "free" else model.jnt_pos[joint])
            rows["reference"].append(
                model.qpos0[model.jnt_qposadr[joint]]
                if kind in ("hinge", "slide") and joint is not None
                else 0.0
            )
            rows["mass"].append(model.body_mass[body] if last else 0.0)
            rows["com"].append(model.body_ipos[body] if last else np.zeros(3))
            rows["inertia"].append(body_inertia if last else np.zeros((3, 3)))
            rows["lower"].append(model.jnt_range[joint, 0] if joint is not None else 0.0)
            rows["upper"].append(model.jnt_range[joint, 1] if joint is not None else 0.0)
        last_link[body] = len(parents) - 1
    joint_dof = np.asarray(model.jnt_dofadr)
    arrays = {key: jnp.asarray(np.asarray(value, dtype=np.float64)) for key, value in rows.items()}
    return KinematicTree(
        parents=tuple(parents),
        joint_types=tuple(joint_types),
        q_addresses=tuple(q_addresses),
        v_addresses=tuple(v_addresses),
        names=tuple(names),
        limited=tuple(limited),
        gravity=jnp.asarray(np.asarray(model.opt.gravity, dtype=np.float64)),
        damping=jnp.asarray(np.asarray(model.dof_damping, dtype=np.float64)),
        armature=jnp.asarray(np.asarray(model.dof_armature, dtype=np.float64)),
        actuation=jnp.asarray(_actuation(model, mujoco, joint_dof)),
        default_configuration=jnp.asarray(np.asarray(model.qpos0, dtype=np.float64)),
        **arrays,
    )


def load(source: str | os.PathLike) -> KinematicTree:
    r"""A [`KinematicTree`][jaxlag.robots.KinematicTree] from an MJCF or URDF file, or from its
    text (a string that starts with ``<``, after blanks and comments or an XML declaration).

    MuJoCo's compiler reads either format (it tells them apart by the root element: ``<mujoco>``
    or ``<robot>``); see [`from_mujoco`][jaxlag.robots.from_mujoco] for what is imported.
    Needs the ``robots`` extra.
    """
    mujoco = _mujoco()
    text = os.fspath(source)
    if text.lstrip().startswith("<"):
        model = mujoco.MjModel.from_xml_string(text)
    else:
        model = mujoco.MjModel.from_xml_path(text)
    return from_mujoco(model)
