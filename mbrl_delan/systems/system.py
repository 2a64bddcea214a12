"""A MuJoCo system as plain tensors: sizes, joint layout, actuation matrix, limits.

Nothing here learns; models and tasks read a `System` and never an `MjModel`.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import torch
from torch import Tensor

ASSETS = Path(__file__).parent / "assets"

FREE, BALL, SLIDE, HINGE = (
    int(mujoco.mjtJoint.mjJNT_FREE),
    int(mujoco.mjtJoint.mjJNT_BALL),
    int(mujoco.mjtJoint.mjJNT_SLIDE),
    int(mujoco.mjtJoint.mjJNT_HINGE),
)


JOINT_TYPES = {"free": FREE, "ball": BALL, "slide": SLIDE, "hinge": HINGE}  # by MJCF name


@dataclass
class State:
    """A batch of generalized states."""

    q: Tensor  # (..., nq)
    qd: Tensor  # (..., nv)


@dataclass(frozen=True)
class JointLayout:
    """Per-joint type and addresses in qpos / qvel, as MuJoCo lays them out."""

    types: tuple[int, ...]  # mjtJoint per joint
    qpos_adr: tuple[int, ...]
    dof_adr: tuple[int, ...]
    limited: tuple[bool, ...]  # joint has a range (hinge/slide)

    @property
    def nq(self) -> int:
        sizes = {FREE: 7, BALL: 4, SLIDE: 1, HINGE: 1}
        return sum(sizes[t] for t in self.types)

    @property
    def nv(self) -> int:
        sizes = {FREE: 6, BALL: 3, SLIDE: 1, HINGE: 1}
        return sum(sizes[t] for t in self.types)

    @property
    def only_scalar_joints(self) -> bool:
        """True when every joint is a hinge or slide, so q and qd live in the same space."""
        return all(t in (HINGE, SLIDE) for t in self.types)

    @property
    def periodic_dofs(self) -> tuple[int, ...]:
        """qpos indices of hinges without limits: their features are sin and cos."""
        return tuple(
            a
            for t, a, lim in zip(self.types, self.qpos_adr, self.limited, strict=True)
            if t == HINGE and not lim
        )


def layout_from_names(names: Sequence[str]) -> JointLayout:
    """The layout of joints named by type, in order (``["hinge", "hinge", "slide"]``), for a
    system without a model file: hinges unlimited (their features are sin and cos), slides
    limited (standardised as they are). Raises ValueError naming an unknown type."""
    unknown = [n for n in names if n not in JOINT_TYPES]
    if not names or unknown:
        raise ValueError(
            f"joint types {list(names)!r}: give a non-empty list of {', '.join(JOINT_TYPES)}"
            + (f" ({unknown} unknown)" if unknown else "")
        )
    types = tuple(JOINT_TYPES[n] for n in names)
    qpos_sizes = {FREE: 7, BALL: 4, SLIDE: 1, HINGE: 1}
    dof_sizes = {FREE: 6, BALL: 3, SLIDE: 1, HINGE: 1}
    qpos_adr = np.cumsum([0] + [qpos_sizes[t] for t in types[:-1]]).tolist()
    dof_adr = np.cumsum([0] + [dof_sizes[t] for t in types[:-1]]).tolist()
    return JointLayout(
        types=types,
        qpos_adr=tuple(int(a) for a in qpos_adr),
        dof_adr=tuple(int(a) for a in dof_adr),
        limited=tuple(t == SLIDE for t in types),
    )


def mujoco_layout(model: mujoco.MjModel) -> JointLayout:
    """The `JointLayout` of an MjModel."""
    return JointLayout(
        types=tuple(int(t) for t in model.jnt_type),
        qpos_adr=tuple(int(a) for a in model.jnt_qposadr),
        dof_adr=tuple(int(a) for a in model.jnt_dofadr),
        limited=tuple(bool(x) for x in model.jnt_limited),
    )


@dataclass
class System:
    """Everything a learner or a task needs to know about a MuJoCo model, as tensors."""

    name: str
    xml_path: Path
    nq: int
    nv: int
    nu: int
    timestep: float  # MuJoCo's integration step (s)
    frame_skip: int  # MuJoCo steps per control step
    actuation: Tensor  # B, (nv, nu): tau = B @ action
    ctrl_low: Tensor  # (nu,)
    ctrl_high: Tensor  # (nu,)
    damping: Tensor  # joint damping from the MJCF, (nv,)
    layout: JointLayout

    @property
    def control_dt(self) -> float:
        return self.timestep * self.frame_skip

    def mj_model(self) -> mujoco.MjModel:
        """A fresh MjModel of this system (one per thread or env)."""
        return mujoco.MjModel.from_xml_path(str(self.xml_path))

    @property
    def has_free_root(self) -> bool:
        return bool(self.layout.types) and self.layout.types[0] == FREE

    def free_root(self) -> tuple[tuple[float, ...], float]:
        """A free root's six diagonal inertias at qpos0 (MuJoCo's M) and the body's weight
        m |g| from the MJCF; a ValueError without a free root."""
        if not self.has_free_root:
            raise ValueError(f"{self.name} has no free root")
        model = self.mj_model()
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        full = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, full)
        weight = float(model.body_mass.sum() * np.linalg.norm(model.opt.gravity))
        return tuple(float(v) for v in np.diag(full)[:6]), weight


def mjcf_path(name: str | Path) -> Path:
    """An MJCF file (``.xml``) or the stem of a model shipped with the package (``arm2``) as
    the path of an existing file; FileNotFoundError naming it otherwise."""
    path = Path(name)
    path = path if path.suffix == ".xml" else asset_path(str(name))
    if not path.is_file():
        raise FileNotFoundError(f"MJCF file not found: {path}")
    return path


def asset_path(name: str) -> Path:
    """Path of an MJCF file shipped with the package, by stem (e.g. 'pendulum')."""
    path = ASSETS / f"{name}.xml"
    if not path.is_file():
        known = sorted(p.stem for p in ASSETS.glob("*.xml"))
        raise FileNotFoundError(f"no system asset '{name}' in {ASSETS}; known: {known}")
    return path


def actuation_matrix(model: mujoco.MjModel) -> np.ndarray:
    """B with tau = B @ ctrl, read from MuJoCo at qpos0 (constant for joint transmissions):
    column i is the generalized force of ctrl_i = 1, the control range's clamp switched off
    (a range narrower than 1, as Humanoid-v5's +-0.4, would scale the column by it)."""
    model = copy.copy(model)  # MjModel's copy is a deep one
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    B = np.zeros((model.nv, model.nu))
    for i in range(model.nu):
        data.ctrl[:] = 0.0
        data.ctrl[i] = 1.0
        mujoco.mj_fwdActuation(model, data)
        B[:, i] = data.qfrc_actuator
    return B


def load_system(xml_path: str | Path, frame_skip: int = 1, name: str | None = None) -> System:
    """Read an MJCF into a `System`. `xml_path` may be an asset stem or a file path."""
    path = mjcf_path(xml_path)
    if frame_skip < 1:
        raise ValueError(f"frame_skip must be >= 1, got {frame_skip}")
    model = mujoco.MjModel.from_xml_path(str(path))
    f64 = torch.float64
    layout = mujoco_layout(model)
    low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    unlimited = ~model.actuator_ctrllimited.astype(bool)
    low = np.where(unlimited, -np.inf, low)
    high = np.where(unlimited, np.inf, high)
    return System(
        name=name or path.stem,
        xml_path=path,
        nq=model.nq,
        nv=model.nv,
        nu=model.nu,
        timestep=float(model.opt.timestep),
        frame_skip=frame_skip,
        actuation=torch.tensor(actuation_matrix(model), dtype=f64),
        ctrl_low=torch.tensor(low, dtype=f64),
        ctrl_high=torch.tensor(high, dtype=f64),
        damping=torch.tensor(model.dof_damping.copy(), dtype=f64),
        layout=layout,
    )
