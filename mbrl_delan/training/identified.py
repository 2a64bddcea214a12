"""The identified model back to the user: ``identified.xml`` beside a fit with an MJCF.

A fit of the white box (`WhiteBoxInverse`) or of DeLaN on the kinematic tree (``tree_delan``:
`DeLaNInverse` with a `RigidBodyTree`) learns every moving body's ten inertial parameters and
each joint's damping and armature (the white box also its Coulomb force, the tree its springs
where ``learn_springs``). `identified_numbers` reads them; `identified_xml` writes them into
the MJCF the fit was given (its kinematics, geoms and actuators untouched): each body's mass,
centre of mass and principal inertia (``inertial``), each joint's ``damping``, ``armature``,
``frictionloss`` (the Coulomb force f: MuJoCo's soft frictionloss constraint is its nearest
law) and ``stiffness``/``springref``. `identified_summary` lists them beside the file's own
numbers and, for tree_delan, what the DeLaN residual holds: per joint, the RMS of its torque
over the RMS of the torques (``residual_torque_share``; the tree cannot say what that is).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
import torch
from tensordict import TensorDictBase

from mbrl_delan import keys
from mbrl_delan.models.inertial import inertial_parameters, set_inertial_parameters
from mbrl_delan.models.inverse import DeLaNInverse, InverseDynamicsModel
from mbrl_delan.models.rigid_body import WhiteBoxInverse
from mbrl_delan.models.tree import TreeDynamics

IDENTIFIED_FILE = "identified.xml"
JOINT_FIELDS = ("damping", "armature", "frictionloss", "stiffness", "springref")


@dataclass(frozen=True)
class IdentifiedNumbers:
    """A fit's physical numbers: per moving body (ids `bodies`) pi (B, 10) as
    `mbrl_delan.models.inertial` defines it, and per DoF the `JOINT_FIELDS` it learned
    (name -> (nv,))."""

    bodies: list[int]
    inertials: np.ndarray
    joints: dict[str, np.ndarray]


def _six(inertia: np.ndarray) -> np.ndarray:
    """[xx, yy, zz, xy, xz, yz] of symmetric (..., 3, 3)."""
    i, j = [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]
    return inertia[..., i, j]


@torch.no_grad()
def identified_numbers(model: InverseDynamicsModel) -> IdentifiedNumbers | None:
    """The white box's or the tree's numbers (module docstring); None for other models."""
    if isinstance(model, WhiteBoxInverse):
        joints = {"damping": model.viscous, "armature": model.armature,
                  "frictionloss": model.coulomb}  # fmt: skip
        return IdentifiedNumbers(
            list(model.bodies), model.inertials.cpu().double().numpy(),
            {k: v.cpu().double().numpy() for k, v in joints.items()},
        )  # fmt: skip
    if isinstance(model, DeLaNInverse) and isinstance(model.dynamics, TreeDynamics):
        tree = model.dynamics.tree
        parts = tree.inertial()
        pi = torch.cat([parts["mass"][:, None], parts["first_moment"],
                        torch.as_tensor(_six(parts["inertia"].cpu().numpy()))
                        .to(parts["mass"])], dim=-1)  # fmt: skip
        joints = {"damping": tree.damping, "armature": tree.armature}
        if tree.learn_springs:
            joints |= {"stiffness": tree.spring_stiffness(), "springref": tree.spring_ref}
        return IdentifiedNumbers(
            list(tree.bodies), pi.cpu().double().numpy(),
            {k: v.detach().cpu().double().numpy() for k, v in joints.items()},
        )  # fmt: skip
    return None


def identified_xml(spec: mujoco.MjSpec, numbers: IdentifiedNumbers) -> str:
    """The MJCF of `spec` (the file the fit was given) with `numbers` in place of its
    inertials and joint parameters (module docstring), as XML text."""
    model = spec.compile()
    for body, pi in zip(numbers.bodies, numbers.inertials, strict=True):
        set_inertial_parameters(model, body, pi)
        target = spec.bodies[body]
        target.explicitinertial = True
        target.mass = float(model.body_mass[body])
        target.ipos = model.body_ipos[body].copy()
        target.iquat = model.body_iquat[body].copy()
        target.fullinertia = [np.nan] * 6  # the principal inertia and its frame instead
        target.inertia = model.body_inertia[body].copy()
    for field, values in numbers.joints.items():
        for dof, value in enumerate(values):
            joint = spec.joints[int(model.dof_jntid[dof])]
            if field in ("damping", "stiffness"):  # linear, then MuJoCo's polynomial terms
                coefficients = np.array(getattr(joint, field), dtype=float)
                coefficients[0] = value
                setattr(joint, field, coefficients)
            else:
                setattr(joint, field, float(value))
    return spec.to_xml()


def _file_joint_numbers(model: mujoco.MjModel) -> dict[str, list[float]]:
    """The file's own per-DoF numbers, as `JOINT_FIELDS` names them."""
    joint = model.dof_jntid
    return {
        "damping": model.dof_damping.tolist(),
        "armature": model.dof_armature.tolist(),
        "frictionloss": model.dof_frictionloss.tolist(),
        "stiffness": model.jnt_stiffness[joint].tolist(),
        "springref": model.qpos_spring[model.jnt_qposadr[joint]].tolist(),
    }


def identified_summary(
    model: InverseDynamicsModel, numbers: IdentifiedNumbers, file_model: mujoco.MjModel,
    test: TensorDictBase | None = None,
) -> dict[str, Any]:  # fmt: skip
    """summary.json's ``identified``: per body its mass and centre of mass, identified and
    the file's; per joint each learned number beside the file's; for tree_delan the
    residual's share of the torques on `test` (module docstring) and, where learned, its
    Coulomb width per joint (``residual_coulomb_velocity``)."""
    names = [file_model.body(b).name or f"body{b}" for b in numbers.bodies]
    own = np.stack([inertial_parameters(file_model, b) for b in numbers.bodies])
    com = numbers.inertials[:, 1:4] / numbers.inertials[:, :1]
    bodies = {
        name: {"mass": float(pi[0]), "mass_file": float(mine[0]), "com": c.tolist(),
               "com_file": (mine[1:4] / mine[0]).tolist()}
        for name, pi, mine, c in zip(names, numbers.inertials, own, com, strict=True)
    }  # fmt: skip
    files = _file_joint_numbers(file_model)
    joints = {field: {"identified": values.tolist(), "file": files[field]}
              for field, values in numbers.joints.items()}  # fmt: skip
    out: dict[str, Any] = {"file": IDENTIFIED_FILE, "bodies": bodies, "joints": joints}
    if test is not None and isinstance(model, DeLaNInverse):
        out["residual_torque_share"] = residual_torque_share(model, test)
    if isinstance(model, DeLaNInverse) and (width := learned_coulomb_velocity(model)) is not None:
        out["residual_coulomb_velocity"] = width
    return out


@torch.no_grad()
def learned_coulomb_velocity(model: DeLaNInverse) -> list[float] | None:
    """The residual's learned Coulomb width per DoF (rad/s or m/s); None where not learned.
    (nv,)"""
    dissipation = model.dynamics.dissipation  # the residual's under a tree
    if dissipation is None or dissipation.raw_velocity is None:
        return None
    return dissipation.velocity.cpu().double().tolist()


@torch.no_grad()
def residual_torque_share(model: DeLaNInverse, data: TensorDictBase) -> list[float] | None:
    """Per DoF: RMS of the DeLaN residual's inverse-dynamics torque over the samples (N,)
    of `data` / RMS of their torques; None without a residual. (nv,)"""
    dynamics = model.dynamics
    if not isinstance(dynamics, TreeDynamics) or dynamics.residual is None:
        return None
    q, qd, qdd, tau = (data[k].to(model.tau_scale) for k in (keys.Q, keys.QD, keys.QDD, keys.TAU))
    residual = dynamics.residual.inverse_dynamics(q, qd, qdd)
    rms = lambda x: x.double().pow(2).mean(0).sqrt()  # noqa: E731
    return (rms(residual) / rms(tau).clamp_min(1e-12)).tolist()
