"""Real arms shipped with the package, for fitting a robot from its own data.

`ARMS` names the project's MJCF files of the Franka Emika Panda (7 DoF), the KUKA LBR
iiwa 14 (7) and the Universal Robots UR5e (6) (`systems/assets/`: published kinematics and
link inertials, capsules for meshes, contacts off, torque motors at the joints' limits) with
each joint's velocity limit. `arm_model(robot, friction=True)` is the same arm with joint
friction and rotor inertia, each a share of the joint's torque limit (`FRICTION`): viscous
damping (MuJoCo's `damping`), Coulomb friction (`frictionloss`) and armature.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from mbrl_delan.systems.system import asset_path


@dataclass(frozen=True)
class Arm:
    """A shipped arm: its asset's stem and each joint's velocity limit (rad/s)."""

    asset: str
    max_velocity: tuple[float, ...]


ARMS = {
    "panda": Arm("panda", (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61)),
    "iiwa14": Arm("iiwa14", (1.483, 1.483, 1.745, 1.309, 2.269, 2.356, 2.356)),
    "ur5e": Arm("ur5e", (3.1416,) * 6),
}


@dataclass(frozen=True)
class Friction:
    """Joint friction and rotor inertia per N m of the joint's torque limit."""

    viscous: float = 0.01  # N m s/rad
    coulomb: float = 0.02  # N m
    armature: float = 0.001  # kg m^2


FRICTION = Friction()


def arm(robot: str) -> Arm:
    """The shipped arm named `robot`; ValueError naming the known ones otherwise."""
    if robot not in ARMS:
        raise ValueError(f"robot={robot!r} is not a shipped arm; choose one of: {', '.join(ARMS)}")
    return ARMS[robot]


def torque_limits(model: mujoco.MjModel) -> np.ndarray:
    """Each DoF's largest motor torque (N m): |gear| x the control bound. (nv,)"""
    limits = np.zeros(model.nv)
    for a in range(model.nu):
        dof = model.jnt_dofadr[model.actuator_trnid[a, 0]]
        bound = np.abs(model.actuator_ctrlrange[a]).max()
        limits[dof] = abs(model.actuator_gear[a, 0]) * bound
    return limits


def arm_model(robot: str, friction: bool = False, law: Friction = FRICTION) -> mujoco.MjModel:
    """The arm's MjModel; with `friction`, each joint's damping, frictionloss and armature
    set to `law`'s shares of its torque limit."""
    spec = mujoco.MjSpec.from_file(str(asset_path(arm(robot).asset)))
    if friction:
        limits = torque_limits(spec.compile())
        for joint, limit in zip(spec.joints, limits, strict=True):
            damping = np.array(joint.damping)  # linear, then MuJoCo's polynomial terms
            damping[0] = law.viscous * limit
            joint.damping = damping
            joint.frictionloss = law.coulomb * limit
            joint.armature = law.armature * limit
    return spec.compile()
