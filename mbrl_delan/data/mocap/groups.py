"""The generalized forces of humanoid_CMU grouped by body part, for per-group errors.

The 56 hinges are named after a CMU ASF bone and a dof (``lfemurrx``); a bone belongs to one
body part. The free joint's 6 dofs are the ``root`` group (the root residual). Hinges of
bones outside `BODY_PARTS` (another model) form an ``other`` group.
"""

from __future__ import annotations

import mujoco

from mbrl_delan.systems.system import FREE

ROOT_GROUP = "root"
OTHER_GROUP = "other"
_SIDES = ("l", "r")
BODY_PARTS: dict[str, tuple[str, ...]] = {
    "legs": tuple(s + b for s in _SIDES for b in ("femur", "tibia", "foot", "toes")),
    "spine_neck_head": ("lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head"),
    "arms": tuple(s + b for s in _SIDES for b in ("clavicle", "humerus", "radius", "wrist")),
    "hands": tuple(s + b for s in _SIDES for b in ("hand", "fingers", "thumb")),
}
_PART_OF_BONE = {bone: part for part, bones in BODY_PARTS.items() for bone in bones}


def _bone(joint_name: str) -> str:
    """``"lfemurrx" -> "lfemur"``: the joint name without its dof suffix."""
    return joint_name[:-2] if joint_name[-2:] in ("rx", "ry", "rz") else joint_name


def dof_groups(model: mujoco.MjModel) -> dict[str, tuple[int, ...]]:
    """Group name -> dof indices: ``root`` (the free joint), then the body parts, ``other``.

    Groups without dofs are left out; every dof is in exactly one group.
    """
    groups: dict[str, list[int]] = {ROOT_GROUP: [], **{p: [] for p in BODY_PARTS}}
    groups[OTHER_GROUP] = []
    for j in range(model.njnt):
        start = int(model.jnt_dofadr[j])
        if model.jnt_type[j] == FREE:
            groups[ROOT_GROUP] += range(start, start + 6)
            continue
        width = {int(mujoco.mjtJoint.mjJNT_BALL): 3}.get(int(model.jnt_type[j]), 1)
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or ""
        groups[_PART_OF_BONE.get(_bone(name), OTHER_GROUP)] += range(start, start + width)
    return {name: tuple(dofs) for name, dofs in groups.items() if dofs}
