"""PD tracking of a retargeted clip in MuJoCo: torques a simulated humanoid applies to follow it.

The alternative to `inverse_dynamics` (``mj_inverse``) as the source of the torques: the
humanoid is simulated along the reference motion (contacts and joint limits off, as in
`inverse_dynamics`), every DoF driven by a PD law on its tracking error

    tau = tau_ff + K (q_ref (-) q) + D (qd_ref - qd),

``q_ref (-) q`` being MuJoCo's position difference (velocity space: the root's quaternion
error is a body-frame rotation vector). The gains come from the inertia at the current state,
recomputed every step, so that every DoF (fingers and the whole body alike) behaves like a
damped oscillator of natural frequency ``omega`` and damping ratio ``zeta``:

- ``gains="mass_matrix"`` (default): ``K = omega^2 M(q)``, ``D = 2 zeta omega M(q)``. Then
  ``M^-1 K = omega^2 I`` exactly: every mode of the body, coupled or not, gets ``omega``.
- ``gains="diagonal"``: ``kp_i = m_eff_i omega^2``, ``kd_i = 2 zeta m_eff_i omega`` with the
  effective inertia ``m_eff = 1 / diag(M^-1)`` (what DoF i shows when all others move
  freely). Stable, but soft: humanoid_CMU's spine, neck and shoulder bodies carry three nearly
  coaxial hinges each, whose m_eff is close to the armature (0.01), so the common rotation of
  a triplet gets about 3 x 0.01 x omega^2 of stiffness against the inertia of everything above
  it. On the 20 shared clips, omega = 40 tracks with 7-21 deg RMS hinge error and ~20 deg root
  orientation error (one clip diverges), against 1-8 deg and 1-6 deg with ``mass_matrix`` at
  omega = 80.

The PD force is explicit (computed from the state at the start of the step) and the step is
MuJoCo's semi-implicit Euler; with the MJCF's dampers also explicit (below), omega = 80 rad/s
(``omega dt = 0.16``) is stable on every shared clip and 150 is not. A blow-up raises
`TrackingUnstableError`.

- The root (the free joint) is held by the same PD law: a residual force and torque on the
  root, which in reality the ground provides. With feed-forward it also gets the
  ``mj_inverse`` root residual.
- ``feedforward=True`` adds ``tau_ff = mj_inverse(q_ref, qd_ref, qdd_ref)``; the PD part then
  only corrects round-off and stays tiny (the reference chains exactly under semi-implicit
  Euler). Without it the PD part carries everything and the motion lags the reference.
- The model's joint springs and dampers stay on with ``passive=True`` (as in
  `inverse_dynamics`); Euler's implicit damping is switched off (``mjDSBL_EULERDAMP``) so
  that ``next qd = qd + dt qdd`` holds exactly for the recorded acceleration.

What is recorded at step k is consistent with the model: the state (q_k, qd_k), the
acceleration MuJoCo's forward dynamics gives under the applied force, qdd_k, and that force
tau_k (so ``mj_inverse(q_k, qd_k, qdd_k) = tau_k``); the next state is the simulated one.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import mujoco
import numpy as np
import torch
from torch import Tensor

from mbrl_delan.data.mocap.inverse import copy_model, inverse_dynamics, root_dofs
from mbrl_delan.data.mocap.retarget import RetargetedClip

log = logging.getLogger(__name__)

_OFF = (
    int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    | int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    | int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)
)
_PASSIVE = int(mujoco.mjtDisableBit.mjDSBL_SPRING) | int(mujoco.mjtDisableBit.mjDSBL_DAMPER)
GAINS = ("mass_matrix", "diagonal")
_BADQACC = int(mujoco.mjtWarning.mjWARN_BADQACC)


class TrackingUnstableError(RuntimeError):
    """The tracking simulation blew up (MuJoCo's bad-acceleration warning)."""


@dataclass(frozen=True)
class TrackingSettings:
    """PD tracking gains and options; stored with the data as provenance."""

    omega: float = 80.0  # closed-loop natural frequency (rad/s)
    zeta: float = 1.0  # damping ratio (1: critically damped)
    gains: str = "mass_matrix"  # "mass_matrix": K = w^2 M(q); "diagonal": m_eff = 1/diag(M^-1)
    feedforward: bool = False  # add mj_inverse of the reference motion
    passive: bool = True  # keep the MJCF's joint springs and dampers

    def __post_init__(self) -> None:
        if not (math.isfinite(self.omega) and self.omega > 0):
            raise ValueError(f"omega must be a positive number (rad/s), got {self.omega}")
        if not (math.isfinite(self.zeta) and self.zeta > 0):
            raise ValueError(f"zeta must be a positive number, got {self.zeta}")
        if self.gains not in GAINS:
            raise ValueError(f"gains must be one of {GAINS}, got {self.gains!r}")

    def as_dict(self) -> dict[str, float | bool]:
        return dataclasses.asdict(self)


@dataclass
class TrackingErrors:
    """Summary of how closely the simulation followed the reference."""

    hinge_rms_deg: float  # RMS over samples and hinges of q_ref (-) q
    hinge_max_deg: float  # largest hinge error
    root_position_rms_m: float  # RMS of the root position error (norm per sample)
    root_rotation_rms_deg: float  # RMS of the root orientation error (angle per sample)
    pd_share: float  # RMS(pd part) / RMS(applied torque), over the hinges

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


@dataclass
class TrackingResult:
    """One tracked clip, T steps at dt, float64 tensors."""

    dt: float
    q: Tensor  # (T, nq) achieved positions
    qd: Tensor  # (T, nv) achieved velocities
    qdd: Tensor  # (T, nv) forward-dynamics accelerations under `tau`
    next_q: Tensor  # (T, nq) the simulated state one step later
    next_qd: Tensor  # (T, nv)
    tau: Tensor  # (T, nv) applied generalized force: feedforward + pd
    pd_tau: Tensor  # (T, nv) the PD part
    feedforward_tau: Tensor  # (T, nv) the mj_inverse part (zeros without feed-forward)
    position_error: Tensor  # (T, nv) q_ref (-) q, velocity space
    velocity_error: Tensor  # (T, nv) qd_ref - qd
    root_dofs: tuple[int, ...]  # the free joint's 6 dofs (force first, then torque)

    def errors(self) -> TrackingErrors:
        """RMS and max tracking errors, and the share of the torque made by the PD part."""
        root = list(self.root_dofs)
        hinge = [i for i in range(self.position_error.shape[1]) if i not in set(root)]
        e_hinge = self.position_error[:, hinge]  # (T, n_hinge)
        e_pos = self.position_error[:, root[:3]].norm(dim=1) if root else torch.zeros(1)
        e_rot = self.position_error[:, root[3:]].norm(dim=1) if root else torch.zeros(1)
        tau_rms = self.tau[:, hinge].pow(2).mean().sqrt()
        pd_rms = self.pd_tau[:, hinge].pow(2).mean().sqrt()
        return TrackingErrors(
            hinge_rms_deg=math.degrees(float(e_hinge.pow(2).mean().sqrt())),
            hinge_max_deg=math.degrees(float(e_hinge.abs().max())),
            root_position_rms_m=float(e_pos.pow(2).mean().sqrt()),
            root_rotation_rms_deg=math.degrees(float(e_rot.pow(2).mean().sqrt())),
            pd_share=float(pd_rms / tau_rms.clamp_min(1e-12)),
        )

    def as_clip(self, reference: RetargetedClip) -> RetargetedClip:
        """The reference clip with the achieved motion in place of the retargeted one."""
        return dataclasses.replace(
            reference,
            q=self.q,
            qd=self.qd,
            qdd=self.qdd,
            next_q=self.next_q,
            next_qd=self.next_qd,
        )


def tracking_model(model: mujoco.MjModel, dt: float, passive: bool = True) -> mujoco.MjModel:
    """A copy of ``model`` for tracking: contacts, limits and Euler's implicit damping off,
    semi-implicit Euler at timestep dt (springs and dampers off too unless ``passive``)."""
    out = copy_model(model)
    out.opt.disableflags |= _OFF | (0 if passive else _PASSIVE)
    out.opt.integrator = int(mujoco.mjtIntegrator.mjINT_EULER)
    out.opt.timestep = dt
    return out


def effective_inertia(model: mujoco.MjModel, data: mujoco.MjData, eye: np.ndarray) -> np.ndarray:
    """1 / diag(M^-1) at the state in ``data`` (M must be factorised). (nv,)."""
    minv = np.empty_like(eye)  # (nv, nv)
    mujoco.mj_solveM(model, data, minv, eye)
    return 1.0 / np.diag(minv)


def _pd_force(
    model: mujoco.MjModel, data: mujoco.MjData, accel: np.ndarray, gains: str, eye: np.ndarray
) -> np.ndarray:
    """The PD force for the wanted acceleration ``w^2 e + 2 zeta w de`` (nv,)."""
    if gains == "diagonal":
        return effective_inertia(model, data, eye) * accel
    out = np.empty_like(accel)
    mujoco.mj_mulM(model, data, out, accel)
    return out


def track_clip(
    model: mujoco.MjModel,
    clip: RetargetedClip,
    settings: TrackingSettings = TrackingSettings(),
) -> TrackingResult:
    """Simulate the model following ``clip`` under PD control (see the module docstring).

    Starts at the clip's first state; one MuJoCo step per clip sample (dt = clip.dt).
    """
    m = tracking_model(model, clip.dt, settings.passive)
    data = mujoco.MjData(m)
    q_ref, qd_ref = clip.q.numpy(), clip.qd.numpy()
    n, nv = q_ref.shape[0], m.nv
    if settings.feedforward:
        ff = inverse_dynamics(model, clip.q, clip.qd, clip.qdd, passive=settings.passive).tau
        ff_np = ff.numpy()
    else:
        ff_np = np.zeros((n, nv))
    out = {k: np.empty((n, nv)) for k in ("qd", "qdd", "next_qd", "tau", "pd", "e_q", "e_qd")}
    q_out, next_q = np.empty((n, m.nq)), np.empty((n, m.nq))
    eye = np.eye(nv)
    e_q = np.empty(nv)
    w, z = settings.omega, settings.zeta
    data.qpos[:], data.qvel[:] = q_ref[0], qd_ref[0]
    for k in range(n):
        q_out[k], out["qd"][k] = data.qpos, data.qvel
        mujoco.mj_step1(m, data)  # positions, velocities, M and its factorisation
        mujoco.mj_differentiatePos(m, e_q, 1.0, data.qpos, q_ref[k])  # q_ref (-) q
        e_qd = qd_ref[k] - data.qvel
        pd = _pd_force(m, data, w * w * e_q + 2.0 * z * w * e_qd, settings.gains, eye)
        data.qfrc_applied[:] = ff_np[k] + pd
        mujoco.mj_step2(m, data)  # accelerations under the applied force, then integrate
        if data.warning[_BADQACC].number:
            raise TrackingUnstableError(
                f"{clip.name}: PD tracking became unstable at step {k} (t = {k * clip.dt:.3f} s) "
                f"with omega={w}, gains={settings.gains!r}; lower omega (w dt = {w * clip.dt:.2g})"
            )
        out["qdd"][k], out["tau"][k], out["pd"][k] = data.qacc, data.qfrc_applied, pd
        out["e_q"][k], out["e_qd"][k] = e_q, e_qd
        next_q[k], out["next_qd"][k] = data.qpos, data.qvel
    t = {k: torch.from_numpy(v) for k, v in out.items()}
    result = TrackingResult(
        dt=clip.dt,
        q=torch.from_numpy(q_out),
        qd=t["qd"],
        qdd=t["qdd"],
        next_q=torch.from_numpy(next_q),
        next_qd=t["next_qd"],
        tau=t["tau"],
        pd_tau=t["pd"],
        feedforward_tau=torch.from_numpy(ff_np),
        position_error=t["e_q"],
        velocity_error=t["e_qd"],
        root_dofs=root_dofs(m),
    )
    err = result.errors()
    log.info(
        "%s: PD tracking (w=%g, zeta=%g, feed-forward %s): hinge error RMS %.3g deg "
        "(max %.3g), root %.3g m / %.3g deg, PD share of the torque %.3g",
        clip.name,
        w,
        z,
        "on" if settings.feedforward else "off",
        err.hinge_rms_deg,
        err.hinge_max_deg,
        err.root_position_rms_m,
        err.root_rotation_rms_deg,
        err.pd_share,
    )
    return result
