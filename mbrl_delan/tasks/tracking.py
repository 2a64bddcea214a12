"""Following a reference motion (a retargeted mocap clip): a time-indexed task.

The reference holds T + 1 states ref_0 .. ref_T at the control rate. The episode starts at
ref_0 and the action of episode step t should reach ref_{t+1}; the reward of that action
compares the reached state (q, qd) with ref_k, k = min(t + 1, T) (a planner's horizon may
run past the clip's end: it is scored against the last frame). DeepMimic-style terms, each in
(0, 1], summed with weights that add to 1:

- pose = exp(-k_pose sum_j e_j^2), e = q (-) q_ref over the rotational DoFs (the root's
  rotation vector and every hinge): MuJoCo's position difference in velocity space;
- velocity = exp(-k_vel sum_j (qd_j - qd_ref_j)^2) over the same DoFs;
- end_effector = exp(-k_ee sum_e |(p_e - p_root) - (p_e,ref - p_root,ref)|^2), p the world
  positions of the end-effector bodies (hands, feet, head) from the torch forward kinematics;
- root = exp(-k_root |p_root - p_root,ref|^2).

The episode terminates when the root is more than `fail_distance` from the reference root
(fallen or lost). Every function is batched over leading dims and calls no simulator.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import astuple, dataclass

import mujoco
import numpy as np
import torch
from torch import Tensor

from mbrl_delan.systems.forward_kinematics import ForwardKinematics
from mbrl_delan.systems.posarith import differentiate_pos
from mbrl_delan.systems.system import FREE, JointLayout, State
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.common import PlacedConstants

# dm_control's CMU humanoid: hands, feet and head
CMU_END_EFFECTORS = ("lhand", "rhand", "lfoot", "rfoot", "head")


@dataclass(frozen=True)
class TrackingWeights:
    """Weights of the four terms (DeepMimic's); they must add to 1."""

    pose: float = 0.65
    velocity: float = 0.1
    end_effector: float = 0.15
    root: float = 0.1

    def __post_init__(self) -> None:
        values = astuple(self)
        if not all(math.isfinite(v) and v >= 0 for v in values) or abs(sum(values) - 1.0) > 1e-9:
            raise ValueError(f"tracking weights must be finite, >= 0 and add to 1, got {self}")


@dataclass(frozen=True)
class TrackingScales:
    """k of each term exp(-k * squared error) (DeepMimic's)."""

    pose: float = 2.0  # 1 / rad^2
    velocity: float = 0.1  # 1 / (rad/s)^2
    end_effector: float = 40.0  # 1 / m^2
    root: float = 10.0  # 1 / m^2

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) and v > 0 for v in astuple(self)):
            raise ValueError(f"tracking scales must be finite and > 0, got {self}")


@dataclass
class TrackingTerms:
    """The reward's terms, each (...) in (0, 1]."""

    pose: Tensor
    velocity: Tensor
    end_effector: Tensor
    root: Tensor


@dataclass
class TrackingDistances:
    """How far a state is from the reference, in metres."""

    root: Tensor  # (...) |p_root - p_root,ref|
    end_effector: Tensor  # (..., E) |(p_e - p_root) - (p_e,ref - p_root,ref)|


class MotionTracking(Task):
    """Follow reference states ref_q (T + 1, nq), ref_qd (T + 1, nv) with a free-root model.

    Args:
        model: the MuJoCo model (its free joint first: q[0:7], qd[0:6]; any other joints
            hinges or slides).
        layout: the model's joint layout (`System.layout`).
        ref_q: the reference positions (T + 1, nq) at the control rate, ref_0 first.
        ref_qd: the reference velocities (T + 1, nv).
        end_effectors: body names scored by the end-effector term.
        weights: of the terms (see the module docstring).
        scales: k of each term exp(-k * squared error).
        fail_distance: root distance (m) from the reference root that ends the episode.
        q_noise: half-width of the uniform noise on the hinges and on qd at reset.
        episode_len: control steps per episode (default T, the reference's length).
        name: task name.
    """

    time_indexed = True

    def __init__(
        self,
        model: mujoco.MjModel,
        layout: JointLayout,
        ref_q: Tensor,
        ref_qd: Tensor,
        end_effectors: Sequence[str] = CMU_END_EFFECTORS,
        weights: TrackingWeights = TrackingWeights(),
        scales: TrackingScales = TrackingScales(),
        fail_distance: float = 0.5,
        q_noise: float = 0.01,
        episode_len: int | None = None,
        name: str = "cmu_track",
    ) -> None:
        _check_reference(layout, ref_q, ref_qd)
        self.layout, self.name = layout, name
        self.weights, self.scales = weights, scales
        self.fail_distance, self.q_noise = fail_distance, q_noise
        self.ref_q, self.ref_qd = ref_q.double(), ref_qd.double()  # (T+1, nq), (T+1, nv)
        self.episode_len = ref_q.shape[0] - 1 if episode_len is None else episode_len
        self.fk = ForwardKinematics.from_mujoco(model)
        self.bodies = _body_ids(model, end_effectors)  # (E,)
        self.indices = PlacedConstants(bodies=self.bodies)
        self.root_body = int(model.jnt_bodyid[0])
        self.ref_root, self.ref_ee = self._points(self.ref_q)  # (T+1, 3), (T+1, E, 3)
        self.constants = PlacedConstants(
            ref_q=self.ref_q, ref_qd=self.ref_qd, ref_root=self.ref_root, ref_ee=self.ref_ee
        )

    def _points(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Root position (..., 3) and end-effector positions relative to it (..., E, 3)."""
        xpos = self.fk(q).xpos  # (..., nbody, 3)
        root = xpos[..., self.root_body, :]
        ee = xpos.index_select(-2, self.indices.on(q)["bodies"])
        return root, ee - root.unsqueeze(-2)

    def reference_poses(self, states: int) -> Tensor:
        """The reference pose of each of an episode's `states` states (its start, then one
        per step): ref_q[min(t, T)]. (states, nq)"""
        index = torch.arange(states).clamp(max=self.ref_q.shape[0] - 1)
        return self.ref_q[index]

    def reference_index(self, step: Tensor) -> Tensor:
        """Index of the reference state the action of `step` should reach: min(step + 1, T)."""
        return torch.clamp(step + 1, max=self.ref_q.shape[0] - 1)

    def _point_errors(self, q: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
        """Root (..., 3) and root-relative end-effector (..., E, 3) errors against ref_k."""
        ref = self.constants.on(q)
        root, ee = self._points(q)
        return root - rows(ref["ref_root"], k), ee - rows(ref["ref_ee"], k)

    def terms(self, q: Tensor, qd: Tensor, step: Tensor) -> TrackingTerms:
        """The four terms of the reward. (..., nq), (..., nv), step -> each (...)."""
        k = self.reference_index(step.to(device=q.device, dtype=torch.long))
        ref = self.constants.on(q)
        q, ref_q = torch.broadcast_tensors(q, rows(ref["ref_q"], k))  # the state or the steps
        qd, ref_qd = torch.broadcast_tensors(qd, rows(ref["ref_qd"].to(qd), k))  # may be batched
        rot = slice(3, None)  # the root's rotation and the hinges, in velocity space
        pose_err = differentiate_pos(self.layout, ref_q, q, 1.0)[..., rot]
        vel_err = (qd - ref_qd)[..., rot]
        root_err, ee_err = self._point_errors(q, k)
        s = self.scales
        return TrackingTerms(
            pose=torch.exp(-s.pose * pose_err.square().sum(-1)),
            velocity=torch.exp(-s.velocity * vel_err.square().sum(-1)),
            end_effector=torch.exp(-s.end_effector * ee_err.square().sum((-2, -1))),
            root=torch.exp(-s.root * root_err.square().sum(-1)),
        )

    def distances(self, q: Tensor, step: Tensor) -> TrackingDistances:
        """Distances of the root and the end effectors from the reference the action of
        `step` should reach. (..., nq), step (...) -> `TrackingDistances`."""
        k = self.reference_index(step.to(device=q.device, dtype=torch.long))
        root_err, ee_err = self._point_errors(q, k)
        return TrackingDistances(
            root=torch.linalg.vector_norm(root_err, dim=-1),
            end_effector=torch.linalg.vector_norm(ee_err, dim=-1),
        )

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        raise TypeError(f"{self.name} is time-indexed: call reward_at(q, qd, action, step)")

    def reward_at(self, q: Tensor, qd: Tensor, action: Tensor, step: Tensor) -> Tensor:
        """Weighted sum of the terms, in (0, 1]. (..., nq), (..., nv), (..., nu), step -> (...)"""
        t, w = self.terms(q, qd, step), self.weights
        return (
            w.pose * t.pose
            + w.velocity * t.velocity
            + w.end_effector * t.end_effector
            + w.root * t.root
        )

    def terminated_at(self, q: Tensor, qd: Tensor, step: Tensor) -> Tensor:
        """The root farther than `fail_distance` from the reference root. -> (...) bool"""
        return self.distances(q, step).root > self.fail_distance

    def terminated(self, q: Tensor, qd: Tensor) -> Tensor:
        raise TypeError(f"{self.name} is time-indexed: call terminated_at(q, qd, step)")

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        """ref_0, its hinges and velocities moved by U(-q_noise, q_noise)."""
        shape = tuple(batch_shape)
        dev = generator.device

        def noise(n: int) -> Tensor:
            u = torch.rand((*shape, n), generator=generator, dtype=torch.float64, device=dev)
            return self.q_noise * (2.0 * u - 1.0)

        q = self.ref_q[0].to(dev).expand(*shape, -1).clone()
        qd = self.ref_qd[0].to(dev).expand(*shape, -1).clone()
        q[..., 7:] += noise(q.shape[-1] - 7)
        qd += noise(qd.shape[-1])
        return State(q=q, qd=qd)


def rows(table: Tensor, index: Tensor) -> Tensor:
    """table[index] for an integer index of any shape (...), without reading it on the host
    (a 0-dim index tensor would be read with `.item()`, which a CUDA graph cannot capture).
    (T, *row), (...) -> (..., *row)"""
    return table.index_select(0, index.reshape(-1)).reshape(*index.shape, *table.shape[1:])


def _check_reference(layout: JointLayout, ref_q: Tensor, ref_qd: Tensor) -> None:
    if not layout.types or layout.types[0] != FREE or FREE in layout.types[1:]:
        raise ValueError("motion tracking needs a model with one free root joint, first")
    if ref_q.ndim != 2 or ref_qd.ndim != 2 or ref_q.shape[0] != ref_qd.shape[0]:
        raise ValueError(
            f"reference q (T+1, nq) and qd (T+1, nv) must have as many rows, got "
            f"{tuple(ref_q.shape)} and {tuple(ref_qd.shape)}"
        )
    if ref_q.shape[1] != layout.nq or ref_qd.shape[1] != layout.nv or ref_q.shape[0] < 2:
        raise ValueError(
            f"reference of shape {tuple(ref_q.shape)}, {tuple(ref_qd.shape)} does not fit the "
            f"model (nq {layout.nq}, nv {layout.nv}) or has fewer than 2 states"
        )
    if not (torch.isfinite(ref_q).all() and torch.isfinite(ref_qd).all()):
        raise ValueError("the reference motion holds NaN or inf")


def _body_ids(model: mujoco.MjModel, names: Sequence[str]) -> Tensor:
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in names]
    missing = [n for n, i in zip(names, ids, strict=True) if i < 0]
    if missing:
        raise ValueError(f"end-effector bodies not in the model: {', '.join(missing)}")
    return torch.tensor(ids, dtype=torch.long)


def floor_clearance(model: mujoco.MjModel, ref_q: Tensor, max_distance: float = 1.0) -> Tensor:
    """Per frame, the smallest signed distance between the floor and the model's other geoms.

    The floor: the model's plane geoms. ref_q (T + 1, nq) -> (T + 1,) in metres; negative
    where a geom sinks into the floor; `max_distance` where none is nearer (or no floor).
    """
    planes = np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE)
    bodies = np.setdiff1d(np.arange(model.ngeom), planes)
    data, fromto = mujoco.MjData(model), np.zeros(6)
    clearance = np.full(ref_q.shape[0], max_distance)
    for t, q in enumerate(ref_q.detach().cpu().double().numpy()):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        for plane in planes:
            for geom in bodies:
                dist = mujoco.mj_geomDistance(model, data, plane, geom, max_distance, fromto)
                clearance[t] = min(clearance[t], dist)
    return torch.from_numpy(clearance)


def ground_reference(
    model: mujoco.MjModel, ref_q: Tensor, ref_qd: Tensor, dt: float, window_s: float = 0.5
) -> tuple[Tensor, Tensor]:
    """Shift a retargeted clip's root height so that it stands on the floor.

    Mocap clips retargeted onto a model rarely sit on its floor (02_01 on the CMU humanoid
    floats 4 to 8.5 cm above it, rising over the clip), so a tracker would be asked to hover.
    The lowest clearance (`floor_clearance`) of each `window_s` of the clip, a stance moment
    in a walk or a run, is taken as a floor contact; a straight line fitted to those minima by
    least squares (a constant for a clip of one window) is subtracted from the root height:
    the offset and drift go, steps and flight phases stay. The root's vertical velocity loses
    the line's slope, so q and qd stay consistent.
    (T + 1, nq), (T + 1, nv), control period dt -> grounded copies. Needs a free root first.
    """
    clearance = floor_clearance(model, ref_q)  # (T + 1,)
    time = torch.arange(ref_q.shape[0], dtype=torch.float64) * dt
    frames = max(1, round(window_s / dt))
    lowest = torch.stack([chunk.argmin() + start for start, chunk in _chunks(clearance, frames)])
    t_low, c_low = time[lowest], clearance[lowest]  # (W,)
    slope = torch.zeros((), dtype=torch.float64)
    if len(lowest) > 1:
        design = torch.stack([torch.ones_like(t_low), t_low], dim=1)  # (W, 2)
        slope = torch.linalg.lstsq(design, c_low.unsqueeze(1)).solution[1, 0]
    offset = (c_low - slope * t_low).mean()
    q, qd = ref_q.clone(), ref_qd.clone()
    q[:, 2] -= (offset + slope * time).to(q)
    qd[:, 2] -= slope.to(qd)
    return q, qd


def _chunks(values: Tensor, size: int) -> list[tuple[int, Tensor]]:
    """Consecutive pieces of `size` (the last one longer, never shorter than half of it)."""
    starts = list(range(0, values.shape[0], size))
    if len(starts) > 1 and values.shape[0] - starts[-1] < size // 2 + 1:
        starts.pop()
    ends = [*starts[1:], values.shape[0]]
    return [(a, values[a:b]) for a, b in zip(starts, ends, strict=True)]
