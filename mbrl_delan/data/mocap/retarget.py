"""Retargeting CMU motions onto dm_control's ``humanoid_CMU.xml``: AMC -> q, qd, qdd.

The conversion (`amc_to_qpos`) is dm_control's ``parse_amc.Amcvals2qpos``, written out for a
plain ``mujoco.MjModel`` and vectorised over frames:

- every hinge of the model is named after an ASF bone and dof (``lfemurrx``); its angle is
  that AMC channel, in radians. humanoid_CMU's bodies carry the CMU ASF ``axis`` rotations
  and list their hinges as rz, ry, rx, so the hinge chain composes as Rz Ry Rx, the order
  of the ASF's ``axis XYZ``. Bone lengths are the model's, not the subject's.
- the root: CMU is y-up, MuJoCo z-up. The position is ``Rx(90deg) @ (T + position) * s`` with
  ``s = 0.0254 / (:units length)`` metres per ASF unit (0.05644 for CMU's 0.45);
  the orientation is ``Rx(90deg) * R_euler`` with ``R_euler = Rz Ry Rx`` for ``axis XYZ``.

The pipeline (`retarget`) then

1. unwraps every rotation channel (no 360-degree jumps) and holds the bones that CMU does not
   capture (fingers and thumbs: constant or junk values) at the model's reference angle 0;
2. makes the root quaternion sign-continuous (q and -q are the same rotation);
3. low-pass filters every qpos column with a zero-phase Butterworth filter (``sosfiltfilt``)
   at the mocap rate, then re-normalises the quaternion;
4. resamples with a cubic spline to the model timestep ``dt`` (re-normalising again),
   dropping ``edge_trim_s`` at both ends where the filter and spline edge effects live;
5. differentiates positions the way MuJoCo does: with Q_k the resampled positions,
   ``V_k = differentiate_pos(Q_{k-1}, Q_k, dt)`` and a sample k has
   ``q = Q_k``, ``qd = V_k``, ``qdd = (V_{k+1} - V_k) / dt``,
   ``next q = Q_{k+1} = integrate_pos(q, qd + dt qdd, dt)``, ``next qd = V_{k+1}``:
   semi-implicit Euler (MuJoCo's own) maps each sample exactly onto the next one, and
   ``qdd`` is the central second difference of q.

It also measures, at the mocap rate, the largest rotation of any captured bone between two
frames (``jump_deg``): a marker swap or solver flip shows up as 100-180 degrees in 1/120 s;
the dataset drops samples near such glitches.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import mujoco
import numpy as np
import torch
from scipy.interpolate import CubicSpline
from scipy.signal import butter, sosfiltfilt
from scipy.spatial.transform import Rotation
from torch import Tensor

from mbrl_delan.data.mocap.amc import AmcMotion, AsfSkeleton, read_amc, read_asf
from mbrl_delan.systems.external import humanoid_cmu_xml
from mbrl_delan.systems.posarith import differentiate_pos, quat_mul
from mbrl_delan.systems.system import FREE, HINGE, JointLayout, mujoco_layout

log = logging.getLogger(__name__)

F64 = torch.float64
MOCAP_FPS = 120.0  # CMU's capture rate
UNCAPTURED_BONES = ("rfingers", "lfingers", "rthumb", "lthumb")
_INCH = 0.0254
_Y_UP_TO_Z_UP = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0])  # Rx(+90 deg)
_AXES = {"X": 0, "Y": 1, "Z": 2}


def joint_layout(model: mujoco.MjModel) -> JointLayout:
    """The `JointLayout` of an MjModel (as `load_system` builds it)."""
    return mujoco_layout(model)


@dataclass(frozen=True)
class FilterSettings:
    """Low-pass filtering and resampling of a clip; stored with the data as provenance."""

    cutoff_hz: float | None = 6.0  # Butterworth cutoff; None: no filtering
    order: int = 4  # filter order (sosfiltfilt runs it forward and backward)
    mocap_fps: float = MOCAP_FPS  # frame rate of the AMC file
    edge_trim_s: float = 0.1  # dropped at both ends after filtering

    def __post_init__(self) -> None:
        nyquist = 0.5 * self.mocap_fps
        if self.mocap_fps <= 0 or self.edge_trim_s < 0 or self.order < 1:
            raise ValueError(f"need mocap_fps > 0, edge_trim_s >= 0, order >= 1: {self}")
        if self.cutoff_hz is not None and not 0.0 < self.cutoff_hz < nyquist:
            raise ValueError(f"cutoff_hz must be in (0, {nyquist}) or None, got {self.cutoff_hz}")

    def as_dict(self) -> dict[str, float | int | None]:
        return asdict(self)


@dataclass(frozen=True)
class MocapQpos:
    """A motion as MuJoCo positions at the mocap rate, before filtering."""

    qpos: np.ndarray  # (K, nq): unwrapped hinges, sign-continuous unit root quaternion
    frames: np.ndarray  # (K,) AMC frame numbers
    driven: tuple[str, ...]  # hinges set from an AMC channel
    held: tuple[str, ...]  # hinges of uncaptured bones, held at 0
    missing: tuple[str, ...]  # hinges with no AMC channel, left at qpos0
    unused: tuple[str, ...]  # AMC channels with no hinge in the model


@dataclass
class RetargetedClip:
    """A retargeted clip: T consecutive samples at the model timestep, float64 tensors."""

    name: str
    dt: float
    time: Tensor  # (T,) seconds since the clip's first frame
    frame: Tensor  # (T,) fractional AMC frame number of each sample
    q: Tensor  # (T, nq)
    qd: Tensor  # (T, nv)
    qdd: Tensor  # (T, nv)
    next_q: Tensor  # (T, nq): q one step later
    next_qd: Tensor  # (T, nv)
    filter: FilterSettings
    jump_deg: np.ndarray  # (K-1,) largest bone rotation between consecutive mocap frames (deg)
    jump_time: np.ndarray  # (K-1,) time (s) between the two frames of each jump
    held: tuple[str, ...]
    missing: tuple[str, ...]
    unused: tuple[str, ...]
    out_of_range: dict[str, float]  # hinge -> fraction of samples outside its range

    def __len__(self) -> int:
        return int(self.q.shape[0])

    def glitch_times(self, threshold_deg: float) -> np.ndarray:
        """Times (s) where a captured bone turned by more than threshold_deg in one frame."""
        return self.jump_time[self.jump_deg > threshold_deg]


def _euler_quat(angles: np.ndarray, order: str) -> Tensor:
    """Quaternion of Euler angles (rad) applied in ``order`` (``"XYZ"``: R = Rz Ry Rx).

    angles: (K, 3) in X, Y, Z order -> (K, 4) (w, x, y, z).
    """
    out = None
    for axis in order:  # first axis innermost
        half = 0.5 * torch.from_numpy(angles[:, _AXES[axis]])
        q = torch.zeros(angles.shape[0], 4, dtype=F64)
        q[:, 0] = torch.cos(half)
        q[:, 1 + _AXES[axis]] = torch.sin(half)
        out = q if out is None else quat_mul(q, out)
    assert out is not None
    return out


def sign_continuous(quat: np.ndarray) -> np.ndarray:
    """Flip quaternions so that consecutive ones have a non-negative dot product. (K, 4)."""
    dots = np.einsum("ij,ij->i", quat[1:], quat[:-1])
    flips = np.concatenate(([1.0], np.cumprod(np.where(dots < 0, -1.0, 1.0))))
    return quat * flips[:, None]


def _free_joint(model: mujoco.MjModel) -> int:
    free = [j for j in range(model.njnt) if model.jnt_type[j] == FREE]
    if len(free) != 1:
        raise ValueError(f"the model needs exactly one free (root) joint, it has {len(free)}")
    return free[0]


def _joint_name(model: mujoco.MjModel, j: int) -> str:
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"


def amc_to_qpos(
    motion: AmcMotion,
    skeleton: AsfSkeleton,
    model: mujoco.MjModel,
    uncaptured_bones: tuple[str, ...] = UNCAPTURED_BONES,
) -> MocapQpos:
    """Convert AMC frames to the model's qpos, frame by frame (no filtering, mocap rate).

    Rotation channels are unwrapped over time first; the root quaternion is made
    sign-continuous. Returns `MocapQpos` with qpos (K, nq).
    """
    index = {name: i for i, name in enumerate(motion.channels)}
    values = motion.values.copy()  # (K, C)
    rotation = np.array([c[-2:] in ("rx", "ry", "rz") for c in motion.channels])
    if motion.degrees:
        values[:, rotation] = np.deg2rad(values[:, rotation])
    values[:, rotation] = np.unwrap(values[:, rotation], axis=0)

    qpos = np.tile(model.qpos0, (motion.n_frames, 1))  # (K, nq)
    root = _free_joint(model)
    adr = int(model.jnt_qposadr[root])
    position = np.stack([values[:, index["root" + a]] for a in ("tx", "ty", "tz")], axis=1)
    position = (position + np.asarray(skeleton.root_position)) * (_INCH / skeleton.length_unit)
    qpos[:, adr : adr + 3] = np.stack((position[:, 0], -position[:, 2], position[:, 1]), axis=1)
    euler = np.stack([values[:, index["root" + a]] for a in ("rx", "ry", "rz")], axis=1)
    quat = quat_mul(torch.from_numpy(_Y_UP_TO_Z_UP), _euler_quat(euler, skeleton.root_axis))
    qpos[:, adr + 3 : adr + 7] = sign_continuous(quat.numpy())

    driven, held, missing = [], [], []
    for j in range(model.njnt):
        if model.jnt_type[j] != HINGE:
            continue
        name, col = _joint_name(model, j), int(model.jnt_qposadr[j])
        if name[:-2] in uncaptured_bones:
            qpos[:, col] = 0.0
            held.append(name)
        elif name in index:
            qpos[:, col] = values[:, index[name]]
            driven.append(name)
        else:
            missing.append(name)
    hinges = set(driven) | set(held)
    unused = tuple(c for c in motion.channels if not c.startswith("root") and c not in hinges)
    if missing:
        log.warning("%s: no AMC channel for hinges %s; left at qpos0", motion.path, missing)
    if unused:
        log.warning("%s: channels %s have no hinge in the model; ignored", motion.path, unused)
    return MocapQpos(qpos, motion.frames.copy(), tuple(driven), tuple(held), tuple(missing), unused)


def _bone_rotations(model: mujoco.MjModel, qpos: np.ndarray, joints: set[str]) -> list[Rotation]:
    """Per body with hinges in ``joints``: its rotation relative to its parent, (K,) each."""
    out = []
    for body in range(model.nbody):
        first, count = int(model.body_jntadr[body]), int(model.body_jntnum[body])
        hinges = [j for j in range(first, first + count) if _joint_name(model, j) in joints]
        if first < 0 or not hinges:
            continue
        rot = None
        for j in hinges:  # MuJoCo composes a body's joints first-listed outermost
            r = Rotation.from_rotvec(np.outer(qpos[:, model.jnt_qposadr[j]], model.jnt_axis[j]))
            rot = r if rot is None else rot * r
        out.append(rot)
    return out


def frame_jumps(model: mujoco.MjModel, mocap: MocapQpos) -> np.ndarray:
    """Largest rotation (deg) of the root or of any driven bone between consecutive frames.

    Returns (K-1,).
    """
    root = int(model.jnt_qposadr[_free_joint(model)]) + 3
    quat = mocap.qpos[:, root : root + 4]
    rots = [Rotation.from_quat(quat, scalar_first=True)]
    rots += _bone_rotations(model, mocap.qpos, set(mocap.driven))
    jumps = [np.rad2deg((r[:-1].inv() * r[1:]).magnitude()) for r in rots]
    return np.max(np.stack(jumps), axis=0)


class ClipTooShortError(ValueError):
    """A clip with too few frames to filter or resample; the message starts with its path."""


def _lowpass(x: np.ndarray, settings: FilterSettings, name: str) -> np.ndarray:
    """Zero-phase Butterworth low-pass along axis 0. (K, n) -> (K, n)."""
    if settings.cutoff_hz is None:
        return x
    sos = butter(settings.order, settings.cutoff_hz, fs=settings.mocap_fps, output="sos")
    padlen = 3 * (2 * len(sos) + 1)
    if x.shape[0] <= padlen:
        raise ClipTooShortError(f"{name}: {x.shape[0]} frames are too few for the low-pass filter")
    return sosfiltfilt(sos, x, axis=0, padlen=padlen)


def _normalize_quat(qpos: np.ndarray, adr: int) -> None:
    quat = qpos[:, adr : adr + 4]
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)


def retarget(
    motion: AmcMotion,
    skeleton: AsfSkeleton,
    model: mujoco.MjModel,
    settings: FilterSettings = FilterSettings(),
    timestep: float | None = None,
    name: str | None = None,
) -> RetargetedClip:
    """AMC motion -> samples (q, qd, qdd, next q, next qd) on the model, at its timestep.

    Args:
        motion: from `read_amc`.
        skeleton: from `read_asf`.
        model: humanoid_CMU (any model with one free root and hinges named bone+dof).
        settings: filter and resampling settings.
        timestep: sample spacing dt (s); the model's ``opt.timestep`` if None.
        name: clip name for messages; the AMC file stem if None.

    Returns a `RetargetedClip` of T = floor((duration - 2 edge_trim_s) / dt) - 1 samples.
    """
    name = name or motion.path.stem
    dt = float(model.opt.timestep if timestep is None else timestep)
    if dt <= 0:
        raise ValueError(f"timestep must be positive, got {dt}")
    mocap = amc_to_qpos(motion, skeleton, model)
    quat_adr = int(model.jnt_qposadr[_free_joint(model)]) + 3
    fps = settings.mocap_fps
    t_mocap = (mocap.frames - mocap.frames[0]) / fps  # (K,)

    smooth = _lowpass(mocap.qpos, settings, f"{motion.path}")
    _normalize_quat(smooth, quat_adr)
    start, stop = settings.edge_trim_s, t_mocap[-1] - settings.edge_trim_s
    n_grid = int(np.floor((stop - start) / dt + 1e-9)) + 1
    if n_grid < 3:
        raise ClipTooShortError(
            f"{motion.path}: clip too short ({motion.n_frames} frames) to retarget"
        )
    t_grid = start + dt * np.arange(n_grid)  # (J,)
    grid = CubicSpline(t_mocap, smooth, axis=0)(t_grid)  # (J, nq)
    _normalize_quat(grid, quat_adr)

    layout = joint_layout(model)
    q_all = torch.from_numpy(grid)
    v_all = differentiate_pos(layout, q_all[:-1], q_all[1:], dt)  # (J-1, nv): V_1 .. V_{J-1}
    qd, next_qd = v_all[:-1], v_all[1:]
    time = torch.from_numpy(t_grid[1:-1])
    jumps = frame_jumps(model, mocap)
    clip = RetargetedClip(
        name=name,
        dt=dt,
        time=time,
        frame=float(mocap.frames[0]) + time * fps,
        q=q_all[1:-1].clone(),
        qd=qd.clone(),
        qdd=(next_qd - qd) / dt,
        next_q=q_all[2:].clone(),
        next_qd=next_qd.clone(),
        filter=settings,
        jump_deg=jumps,
        jump_time=0.5 * (t_mocap[1:] + t_mocap[:-1]),
        held=mocap.held,
        missing=mocap.missing,
        unused=mocap.unused,
        out_of_range=_out_of_range(model, grid[1:-1]),
    )
    log.info(
        "%s: %d frames -> %d samples at dt=%g; %d hinges leave their range; max jump %.0f deg",
        name,
        motion.n_frames,
        len(clip),
        dt,
        len(clip.out_of_range),
        float(jumps.max(initial=0)),
    )
    return clip


def _out_of_range(model: mujoco.MjModel, qpos: np.ndarray) -> dict[str, float]:
    """Hinge -> fraction of rows of qpos (T, nq) outside the joint range (limited hinges)."""
    out = {}
    for j in range(model.njnt):
        if model.jnt_type[j] != HINGE or not model.jnt_limited[j]:
            continue
        x = qpos[:, model.jnt_qposadr[j]]
        low, high = model.jnt_range[j]
        frac = float(np.mean((x < low) | (x > high)))
        if frac > 0:
            out[_joint_name(model, j)] = frac
    return out


def retarget_files(
    amc_path: str | Path,
    asf_path: str | Path,
    xml_path: str | Path | None = None,
    settings: FilterSettings = FilterSettings(),
    timestep: float | None = None,
    name: str | None = None,
) -> RetargetedClip:
    """Read an ASF + AMC pair and retarget it onto humanoid_CMU (or the model at xml_path)."""
    skeleton = read_asf(asf_path)
    motion = read_amc(amc_path, skeleton)
    model = mujoco.MjModel.from_xml_path(str(xml_path or humanoid_cmu_xml()))
    return retarget(motion, skeleton, model, settings, timestep=timestep, name=name)
