r"""Two robots written for the project as MJCF and read by [`jaxlag.robots`](../api/robots.md):
a six-joint arm on a fixed base and a free-flying base carrying two arms.

Their ``args`` is the robot's [`KinematicTree`][jaxlag.robots.KinematicTree] (``None``: the
default tree), not a dict: `default_args` returns that tree, whose masses, centres of mass,
inertias, damping and armature are arrays to edit with ``equinox.tree_at`` or to fit. Loading
the MJCF needs MuJoCo's model compiler, the ``robots`` extra (``pip install "jaxlag[robots]"``):
the import of ``jaxlag.systems`` does not, the first call of one of these models does.
"""

import functools
from types import MappingProxyType
from typing import Any

from .._system import System

ROBOT_ARM_MJCF = """
<mujoco model="jaxlag robot arm">
  <option gravity="0 0 -9.81"/>
  <default><joint type="hinge" damping="0.1" armature="0.01"/></default>
  <worldbody>
    <body name="turret" pos="0 0 0.1">
      <joint name="base_yaw" axis="0 0 1"/>
      <geom type="cylinder" size="0.07 0.05" mass="2.0"/>
      <body name="upper_arm" pos="0 0 0.05">
        <joint name="shoulder" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.4" size="0.04" mass="1.5"/>
        <body name="forearm" pos="0 0 0.4">
          <joint name="elbow" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0.35 0 0" size="0.035" mass="1.0"/>
          <body name="wrist_1" pos="0.35 0 0">
            <joint name="wrist_roll" axis="1 0 0"/>
            <geom type="cylinder" fromto="0 0 0 0.06 0 0" size="0.03" mass="0.3"/>
            <body name="wrist_2" pos="0.06 0 0">
              <joint name="wrist_pitch" axis="0 1 0"/>
              <geom type="cylinder" fromto="0 0 0 0.06 0 0" size="0.03" mass="0.3"/>
              <body name="hand" pos="0.06 0 0">
                <joint name="hand_roll" axis="1 0 0"/>
                <geom type="box" pos="0.04 0 0" size="0.04 0.05 0.015" mass="0.4"/>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="base_yaw"/><motor joint="shoulder"/><motor joint="elbow"/>
    <motor joint="wrist_roll"/><motor joint="wrist_pitch"/><motor joint="hand_roll"/>
  </actuator>
</mujoco>
"""

SPACE_ROBOT_MJCF = """
<mujoco model="jaxlag space robot">
  <option gravity="0 0 0"/>
  <worldbody>
    <body name="base">
      <freejoint name="base"/>
      <geom type="box" size="0.3 0.2 0.15" mass="40"/>
      <body name="left_upper" pos="0.3 0.2 0">
        <joint name="left_shoulder" type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 0.45 0 0" size="0.04" mass="3"/>
        <body name="left_fore" pos="0.45 0 0">
          <joint name="left_elbow" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.035" mass="2"/>
        </body>
      </body>
      <body name="right_upper" pos="0.3 -0.2 0">
        <joint name="right_shoulder" type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 0.45 0 0" size="0.04" mass="3"/>
        <body name="right_fore" pos="0.45 0 0">
          <joint name="right_elbow" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.035" mass="2"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="left_shoulder"/><motor joint="left_elbow"/>
    <motor joint="right_shoulder"/><motor joint="right_elbow"/>
  </actuator>
</mujoco>
"""


def _robot_model(text: str):
    """Decorate a robot's factory: memoized (the same `System` each call), with
    ``factory.tree()`` loading (once) the `KinematicTree` of ``text``, which `default_args`
    returns; ``factory.defaults`` is empty (the parameters are the tree's arrays)."""

    @functools.cache
    def tree() -> Any:
        from .. import robots

        return robots.load(text)

    def wrap(factory):
        cached: Any = functools.cache(factory)
        cached.defaults = MappingProxyType({})
        cached.allow_extra = False
        cached.tree = tree
        cached.mjcf = text
        return cached

    return wrap


@_robot_model(ROBOT_ARM_MJCF)
def robot_arm() -> System:
    r"""A six-joint arm on a fixed base, each joint driven by a motor (z up, gravity ``9.81``).

    Coordinates (MuJoCo's ``qpos``, all hinges, radians, 0 the arm as drawn: the upper arm
    vertical, the forearm horizontal along x): ``base_yaw`` (about z), ``shoulder`` and
    ``elbow`` (about the link's y), ``wrist_roll`` (about x), ``wrist_pitch`` (y), ``hand_roll``
    (x). Links: a turret (2 kg), an upper arm of 0.4 m (1.5 kg), a forearm of 0.35 m (1 kg), two
    wrist links of 0.06 m (0.3 kg each) and a hand (0.4 kg), their inertias computed by MuJoCo
    from their geoms. Every joint has damping ``0.1`` N·m·s and armature ``0.01`` kg·m².

    The input ``u`` (6 values) is the motor torques, ``τ = u``: give a control law with
    [`System.with_control`][jaxlag.System.with_control]. The equation of motion is
    ``M(q) q̈ + C(q, q̇) q̇ + g(q) = u − 0.1 q̇`` (see [`jaxlag.robots`](../api/robots.md)).

    ``args``: the arm's [`KinematicTree`][jaxlag.robots.KinematicTree]
    (``systems.default_args(systems.robot_arm)``, or ``None`` for it); its MJCF text is
    ``robot_arm.mjcf``. Tested: ``M(q)`` and the bias forces agree with MuJoCo's ``mj_fullM``
    and ``qfrc_bias``; without damping and motors the energy ``½ q̇ᵀM q̇ + V`` is conserved.
    """
    from .. import robots

    return robots.system(robot_arm.tree())


@_robot_model(SPACE_ROBOT_MJCF)
def space_robot() -> System:
    r"""A free-flying base (a 40 kg box) carrying two two-link arms, in zero gravity.

    Coordinates (MuJoCo's ``qpos``, 11 of them): the base's position ``(x, y, z)`` and its
    quaternion ``(w, x, y, z)`` (a free joint, with the holonomic constraint ``|Q|² = 1``),
    then ``left_shoulder`` (about the base's z), ``left_elbow`` (about the upper arm's y),
    ``right_shoulder``, ``right_elbow``. At ``q = (0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0)`` both arms
    stretch along the base's x from its front corners at ``y = ±0.2``. Upper arms 0.45 m (3 kg),
    forearms 0.4 m (2 kg); no damping.

    The input ``u`` (4 values) is the torques of the four arm motors. Nothing acts on the base:
    the total linear and angular momentum and (without motors) the energy are conserved, so
    moving an arm turns and shifts the base (the classic free-floating manipulator).

    ``args``: the robot's [`KinematicTree`][jaxlag.robots.KinematicTree]
    (``systems.default_args(systems.space_robot)``, or ``None`` for it); its MJCF text is
    ``space_robot.mjcf``. Tested: ``M(q)`` and the bias forces agree with MuJoCo's ``mj_fullM``
    and ``qfrc_bias``; a free motion conserves the energy and the linear momentum.
    """
    from .. import robots

    return robots.system(space_robot.tree())
