r"""Robots from files: kinematic trees read from MJCF or URDF, and their rigid-body dynamics.

```python
import jaxlag.robots as jlr

tree = jlr.load("arm.xml")                  # MJCF or URDF, a path or the text itself
M = jlr.mass_matrix(tree, q)                # M(q), armature on the diagonal
b = jlr.bias_forces(tree, q, v)             # C(q, v) v + g(q)
a = jlr.forward_dynamics(tree, q, v, tau)   # v̇ = M⁻¹(τ − damping · v − C v − g)
```

The equation of motion is ``M(q) v̇ + C(q, v) v + g(q) = τ − damping · v``, MuJoCo's
(``mj_fullM``, ``qfrc_bias``, ``qacc`` without contacts or limits). Coordinates ``q`` and velocities
``v`` are MuJoCo's ``qpos`` and ``qvel``: a ball joint's quaternion has four coordinates and three
velocities (the angular velocity in the link's frame), a free joint seven and six (the world
velocity of the link's origin, then the angular velocity in the link's frame); see
[`KinematicTree`][jaxlag.robots.KinematicTree] and
[`configuration_rate`][jaxlag.robots.configuration_rate].

Reading files needs MuJoCo's model compiler, the ``robots`` extra (``pip install
"jaxlag[robots]"``); nothing else here does. Every function is differentiable and works under
``jit`` and ``vmap``; the inertial parameters are arrays of the tree. Called eagerly, each
function compiles one program per tree structure and shapes, reused for new states and
parameters. `system` turns the tree
into a [`jaxlag.System`][jaxlag.System] (``L = T − V``, quaternions with ``|Q|² = 1``), whose
``M`` and forces come from these recursive algorithms (`TreeDynamics`).
"""

from ._aba import forward_dynamics as forward_dynamics
from ._crba import mass_matrix as mass_matrix
from ._kinematics import LinkPoses as LinkPoses
from ._kinematics import configuration_rate as configuration_rate
from ._kinematics import forward_kinematics as forward_kinematics
from ._lagrangian import ArticulatedBodyDynamics as ArticulatedBodyDynamics
from ._lagrangian import TreeDynamics as TreeDynamics
from ._lagrangian import system as system
from ._load import from_mujoco as from_mujoco
from ._load import load as load
from ._rnea import bias_forces as bias_forces
from ._rnea import inverse_dynamics as inverse_dynamics
from ._tree import KinematicTree as KinematicTree

__all__ = [
    "ArticulatedBodyDynamics",
    "KinematicTree",
    "LinkPoses",
    "TreeDynamics",
    "bias_forces",
    "configuration_rate",
    "forward_dynamics",
    "forward_kinematics",
    "from_mujoco",
    "inverse_dynamics",
    "load",
    "mass_matrix",
    "system",
]
