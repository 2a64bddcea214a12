"""Arms to fit from their own data: the shipped ones, or any hinge/slide MJCF of a user's.

`ARMS` names the project's MJCF files (`systems/assets/`: capsules for meshes, contacts off,
torque motors at the joints' limits) with each joint's velocity limit:

- the Franka Emika Panda (7 DoF), the KUKA LBR iiwa 14 (7) and the Universal Robots UR5e
  (6), with their published kinematics and link inertials;
- ``slim7``, a 7-DoF arm whose three roll joints (upper arm, forearm, flange) have a few
  1e-4 kg m^2 of inertia about their axes, and ``light6``, a light 6-DoF arm (4.6 kg).

`arm(robot)` takes a shipped name or an MJCF file's path; a file's velocity limits are
`DEFAULT_VELOCITY` unless given. `arm_model(robot, friction)` is the arm with joint friction
and rotor inertia of the kind `friction` names (`FRICTION_KINDS`), each a share of the
joint's torque limit (`FRICTION`):

- ``none``: no friction, no armature (a file's own damping, frictionloss and armature are
  set to zero);
- ``frictionloss``: viscous damping (MuJoCo's ``damping``), Coulomb friction as MuJoCo's
  soft ``frictionloss`` constraint, and armature;
- ``coulomb_viscous``: viscous damping and armature in the model; the Coulomb force
  f sign(qd) of a real joint is not MuJoCo's and comes from `coulomb_friction` (the data's
  torques add it: `mbrl_delan.data.excitation`).

`arm_model(robot, friction, structure=...)` adds springs that a CAD file of the arm lacks
(`STRUCTURES`; each sized by its torque at the joints' range ends, a share of the joints'
torque limit, `SPRINGS`):

- ``counterbalance``: a torsion spring on the shoulder (`shoulder_joint`: the joint gravity
  loads most), resting at the range's middle, as industrial arms balance gravity;
- ``coupling``: a tendon spring over two wrist joints (`wrist_pair`), MuJoCo's fixed tendon
  q_a + q_b with a stiffness, so that each joint's spring torque depends on both.

`cad_spec(robot, seed)` is the arm's MJCF as a CAD export gives it (`CAD_ERROR`): every
moving body's mass and rotational inertia scaled by factors drawn in U(0.6, 1.4), its centre
of mass moved by up to 2 cm; the kinematics are the arm's.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from mbrl_delan.systems.system import asset_path

log = logging.getLogger(__name__)

FRICTION_KINDS = ("none", "frictionloss", "coulomb_viscous")
STRUCTURES = ("none", "counterbalance", "coupling")
DEFAULT_VELOCITY = {"hinge": 2.0, "slide": 0.5}  # rad/s, m/s: a user MJCF's joints, if not given


@dataclass(frozen=True)
class Arm:
    """An arm: its shipped asset's stem or an MJCF file, and each joint's velocity limit
    (rad/s or m/s; None: `DEFAULT_VELOCITY` by joint type)."""

    asset: str
    max_velocity: tuple[float, ...] | None = None


ARMS = {
    "panda": Arm("panda", (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61)),
    "iiwa14": Arm("iiwa14", (1.483, 1.483, 1.745, 1.309, 2.269, 2.356, 2.356)),
    "ur5e": Arm("ur5e", (3.1416,) * 6),
    "slim7": Arm("slim7", (2.0, 2.0, 3.0, 2.5, 3.5, 3.5, 4.0)),
    "light6": Arm("light6", (3.1416,) * 6),
}


@dataclass(frozen=True)
class Friction:
    """Joint friction and rotor inertia per N m of the joint's torque limit."""

    viscous: float = 0.01  # N m s/rad
    coulomb: float = 0.02  # N m
    armature: float = 0.001  # kg m^2


FRICTION = Friction()


@dataclass(frozen=True)
class Springs:
    """The added springs' torque at the end of their joints' ranges (the half-width about
    the middle, at most pi), a share of the joint's torque limit (the smaller of two)."""

    counterbalance: float = 0.6
    coupling: float = 0.2


SPRINGS = Springs()


@dataclass(frozen=True)
class CadError:
    """How a CAD file's inertials are off: mass and rotational inertia each times a factor
    in `scale`, the centre of mass moved uniformly within a ball of `com_m` metres."""

    scale: tuple[float, float] = (0.6, 1.4)
    com_m: float = 0.02


CAD_ERROR = CadError()
POSES = 256  # random poses that choose the shoulder (`shoulder_joint`)


def friction_kind(value: str | bool) -> str:
    """A friction setting as one of `FRICTION_KINDS`; true and false (the setting before
    there were kinds, in saved runs) read as ``frictionloss`` and ``none``."""
    if isinstance(value, bool):
        return "frictionloss" if value else "none"
    if value not in FRICTION_KINDS:
        raise ValueError(f"friction {value!r}: choose one of {', '.join(FRICTION_KINDS)}")
    return value


def arm(robot: str) -> Arm:
    """The shipped arm named `robot`, or the arm of an MJCF file (a path ending in .xml);
    ValueError naming the known arms, FileNotFoundError for a missing file."""
    if robot in ARMS:
        return ARMS[robot]
    if robot.endswith(".xml"):
        if not Path(robot).is_file():
            raise FileNotFoundError(f"robot MJCF file not found: {robot}")
        return Arm(str(Path(robot).resolve()))
    raise ValueError(
        f"robot={robot!r} is neither a shipped arm ({', '.join(ARMS)}) nor an MJCF file (.xml)"
    )


def _asset(entry: Arm) -> Path:
    return Path(entry.asset) if entry.asset.endswith(".xml") else asset_path(entry.asset)


def torque_limits(model: mujoco.MjModel) -> np.ndarray:
    """Each DoF's largest motor torque (N m): |gear| x the control bound of the joint motors
    driving it; inf for a DoF no control-limited motor drives. (nv,)"""
    limits = np.zeros(model.nv)
    driven = np.zeros(model.nv, dtype=bool)
    for a in range(model.nu):
        if int(model.actuator_trntype[a]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            continue
        dof = model.jnt_dofadr[model.actuator_trnid[a, 0]]
        if not model.actuator_ctrllimited[a]:
            limits[dof] = np.inf
        else:
            bound = np.abs(model.actuator_ctrlrange[a]).max()
            limits[dof] += abs(model.actuator_gear[a, 0]) * bound
        driven[dof] = True
    limits[~driven] = np.inf
    return limits


def velocity_limits(model: mujoco.MjModel, robot: str) -> np.ndarray:
    """Each joint's velocity limit (nv,): the arm's, else `DEFAULT_VELOCITY` by type."""
    given = arm(robot).max_velocity
    if given is not None:
        return np.array(given, dtype=float)
    hinge = model.jnt_type == int(mujoco.mjtJoint.mjJNT_HINGE)
    return np.where(hinge, DEFAULT_VELOCITY["hinge"], DEFAULT_VELOCITY["slide"])


def check_arm(model: mujoco.MjModel, robot: str) -> None:
    """ValueError unless every joint of `model` is a hinge or a slide with one DoF."""
    allowed = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    for j in range(model.njnt):
        if int(model.jnt_type[j]) not in allowed:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"#{j}"
            kind = mujoco.mjtJoint(model.jnt_type[j]).name.removeprefix("mjJNT_").lower()
            raise ValueError(f"{robot}: joint {name} is a {kind} joint; an arm's joints must "
                             "be hinges or slides")  # fmt: skip
    if model.nv == 0:
        raise ValueError(f"{robot}: the model has no joints")


def arm_model(
    robot: str, friction: str | bool = "none", law: Friction = FRICTION, structure: str = "none"
) -> mujoco.MjModel:
    """The arm's MjModel; with friction (module docstring), each joint's damping, armature
    and (``frictionloss``) frictionloss set to `law`'s shares of its torque limit; with a
    `structure` (`STRUCTURES`), its springs."""
    kind = friction_kind(friction)
    if structure not in STRUCTURES:
        raise ValueError(f"structure {structure!r}: choose one of {', '.join(STRUCTURES)}")
    spec = mujoco.MjSpec.from_file(str(_asset(arm(robot))))
    model = spec.compile()
    check_arm(model, robot)
    if kind == "none":
        _without_friction(spec, model, robot)
    else:
        limits = _finite_limits(model, robot, kind)
        for joint, limit in zip(spec.joints, limits, strict=True):
            damping = np.array(joint.damping)  # linear, then MuJoCo's polynomial terms
            damping[0] = law.viscous * limit
            joint.damping = damping
            joint.frictionloss = law.coulomb * limit if kind == "frictionloss" else 0.0
            joint.armature = law.armature * limit
    if structure != "none":
        _add_springs(spec, model, robot, structure)
    return spec.compile()


def _without_friction(spec: mujoco.MjSpec, model: mujoco.MjModel, robot: str) -> None:
    """Friction ``none``: a file's own damping, frictionloss and armature set to zero (said
    in the log where it had any)."""
    had = [name for name, values in (("damping", model.dof_damping),
                                     ("frictionloss", model.dof_frictionloss),
                                     ("armature", model.dof_armature)) if values.any()]  # fmt: skip
    if had:
        log.info("%s: friction=none sets the file's %s to zero", robot, ", ".join(had))
    for joint in spec.joints:
        joint.damping = np.zeros_like(np.array(joint.damping, dtype=float))
        joint.frictionloss = 0.0
        joint.armature = 0.0


def range_middle_and_half(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """Each joint's range middle and half-width (at most pi; 0 and pi where unlimited)."""
    low, high = model.jnt_range[:, 0], model.jnt_range[:, 1]
    limited = model.jnt_limited > 0
    middle = np.where(limited, (low + high) / 2, 0.0)
    return middle, np.minimum(np.where(limited, (high - low) / 2, np.pi), np.pi)


def shoulder_joint(model: mujoco.MjModel) -> int:
    """The joint gravity loads most: the largest RMS of its gravity torque over `POSES`
    poses drawn uniformly within the ranges (seeded)."""
    middle, half = range_middle_and_half(model)
    poses = middle + half * np.random.default_rng(0).uniform(-1, 1, (POSES, model.nq))
    data = mujoco.MjData(model)
    gravity = np.zeros((POSES, model.nv))
    for i, q in enumerate(poses):
        data.qpos[:] = q
        mujoco.mj_forward(model, data)
        gravity[i] = data.qfrc_bias
    return int(np.argmax(np.sqrt((gravity**2).mean(0))))


def wrist_pair(model: mujoco.MjModel) -> tuple[int, int]:
    """The two wrist joints a coupling spring spans: the third and second from the end."""
    if model.nv < 3:
        raise ValueError(f"a coupling spring spans two wrist joints; the arm has {model.nv}")
    return model.nv - 3, model.nv - 2


def _add_springs(spec: mujoco.MjSpec, model: mujoco.MjModel, robot: str, kind: str) -> None:
    """`kind`'s springs (module docstring) added to `spec` of the arm `model`."""
    limits = _finite_limits(model, robot, f"structure={kind} (sized by the torque limits)")
    middle, half = range_middle_and_half(model)
    if kind == "counterbalance":
        j = shoulder_joint(model)
        joint = spec.joints[j]
        stiffness = np.array(joint.stiffness)  # linear, then MuJoCo's polynomial terms
        stiffness[0] = SPRINGS.counterbalance * limits[j] / half[j]
        joint.stiffness = stiffness
        joint.springref = middle[j]
        return
    a, b = wrist_pair(model)
    for j in (a, b):
        spec.joints[j].name = spec.joints[j].name or f"joint{j}"
    tendon = spec.add_tendon()
    tendon.name = "coupling"
    tendon.wrap_joint(spec.joints[a].name, 1.0)
    tendon.wrap_joint(spec.joints[b].name, 1.0)
    stiffness = np.zeros_like(np.array(tendon.stiffness))
    stiffness[0] = SPRINGS.coupling * min(limits[a], limits[b]) / (half[a] + half[b])
    tendon.stiffness = stiffness
    tendon.springlength = [middle[a] + middle[b]] * 2


def spring_torque(model: mujoco.MjModel, q: np.ndarray) -> np.ndarray:
    """The torque the motors spend on `model`'s springs (joints' and tendons') at rest in
    each configuration q (N, nq): -qfrc_passive with qd = 0. (N, nv)"""
    data = mujoco.MjData(model)
    out = np.zeros((q.shape[0], model.nv))
    for i, qi in enumerate(q):
        data.qpos[:] = qi
        mujoco.mj_fwdPosition(model, data)
        mujoco.mj_fwdVelocity(model, data)
        out[i] = -data.qfrc_passive
    return out


def cad_spec(robot: str, seed: int, error: CadError = CAD_ERROR) -> mujoco.MjSpec:
    """The arm's MjSpec with inertials off as a CAD export's are (module docstring),
    drawn from `seed`: the same seed, the same file."""
    spec = mujoco.MjSpec.from_file(str(_asset(arm(robot))))
    rng = np.random.default_rng(seed)
    for body in spec.bodies[1:]:  # the world body has no inertial
        if body.mass <= 0:
            continue
        mass, inertia = rng.uniform(*error.scale, size=2)
        direction = rng.normal(size=3)
        shift = error.com_m * rng.uniform() ** (1 / 3) * direction / np.linalg.norm(direction)
        body.mass = body.mass * mass
        if np.isfinite(body.fullinertia).all() and np.abs(body.fullinertia).sum() > 0:
            body.fullinertia = np.asarray(body.fullinertia) * inertia
        else:
            body.inertia = np.asarray(body.inertia) * inertia
        body.ipos = np.asarray(body.ipos) + shift
    return spec


def coulomb_friction(robot: str, friction: str | bool, law: Friction = FRICTION) -> np.ndarray:
    """Each DoF's Coulomb force f of ``coulomb_viscous`` friction (tau += f sign(qd)); zeros
    for the other kinds, whose Coulomb friction (if any) is in the MjModel. (nv,)"""
    model = arm_model(robot)
    if friction_kind(friction) != "coulomb_viscous":
        return np.zeros(model.nv)
    return law.coulomb * _finite_limits(model, robot, "coulomb_viscous")


def _finite_limits(model: mujoco.MjModel, robot: str, kind: str) -> np.ndarray:
    limits = torque_limits(model)
    if not np.isfinite(limits).all():
        free = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, int(j)) or f"#{j}"
                for j in model.dof_jntid[~np.isfinite(limits)]]  # fmt: skip
        raise ValueError(f"{robot}: friction={kind} is set from each joint's torque limit, and "
                         f"joints {free} have no control-limited motor")  # fmt: skip
    return limits
