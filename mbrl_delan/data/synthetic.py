"""Synthetic dynamics data from MuJoCo: random states and controls with their exact accelerations.

For system identification: every sample is an independent random state (q, qd) and control,
with MuJoCo's forward acceleration qdd at that state (contacts off), the generalized force
tau = B a, and the state one control step later (MuJoCo's own integrator), so the same data
serve inverse-dynamics losses (q, qd, qdd, tau) and next-state losses.

`reference_terms` gives MuJoCo's mass matrix and gravity force at given positions, the
ground truth that a learned model is compared with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
import torch
from tensordict import TensorDict
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.systems.system import System

F64 = torch.float64


@dataclass
class ReferenceTerms:
    """MuJoCo's mass matrix and gravity generalized force at a batch of positions."""

    mass_matrix: Tensor  # (N, nv, nv), from mj_fullM
    gravity: Tensor  # (N, nv), qfrc_bias at zero velocity


def _contact_free_model(system: System) -> mujoco.MjModel:
    """The system's MjModel with contacts (and hence contact forces) disabled."""
    model = system.mj_model()
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    return model


def _check_scalar_joints(system: System) -> None:
    if not system.layout.only_scalar_joints:
        raise NotImplementedError(
            f"{system.name}: random states are drawn for hinge and slide joints only; "
            "ball and free joints are not supported by dynamics_dataset"
        )


def _uniform(low: Tensor, high: Tensor, n: int, generator: torch.Generator) -> Tensor:
    """n samples uniform in the box [low, high]: (k,), (k,) -> (n, k), float64."""
    u = torch.rand(n, low.shape[0], generator=generator, dtype=F64)
    return low + (high - low) * u


def _position_box(model: mujoco.MjModel, q_scale: float) -> tuple[Tensor, Tensor]:
    """Per-qpos sampling range: the joint range where limited, else [-q_scale, q_scale]."""
    low = torch.full((model.nq,), -q_scale, dtype=F64)
    high = torch.full((model.nq,), q_scale, dtype=F64)
    for j in range(model.njnt):
        if model.jnt_limited[j]:
            adr = int(model.jnt_qposadr[j])
            low[adr], high[adr] = (float(x) for x in model.jnt_range[j])
    return low, high


def _control_box(system: System, action_scale: float) -> tuple[Tensor, Tensor]:
    """The control range; unlimited actuators get [-action_scale, action_scale]."""
    low = torch.where(torch.isfinite(system.ctrl_low), system.ctrl_low, -action_scale)
    high = torch.where(torch.isfinite(system.ctrl_high), system.ctrl_high, action_scale)
    return low.to(F64), high.to(F64)


def _simulate(
    system: System, model: mujoco.MjModel, q: Tensor, qd: Tensor, action: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """MuJoCo's qdd at each sample and the state one control step later.

    (N, nq), (N, nv), (N, nu) -> qdd (N, nv), next q (N, nq), next qd (N, nv).
    """
    data = mujoco.MjData(model)
    n = q.shape[0]
    qdd, q_next, qd_next = np.zeros((n, model.nv)), np.zeros((n, model.nq)), np.zeros((n, model.nv))
    q_np, qd_np, a_np = q.numpy(), qd.numpy(), action.numpy()
    for i in range(n):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:], data.ctrl[:] = q_np[i], qd_np[i], a_np[i]
        mujoco.mj_forward(model, data)
        qdd[i] = data.qacc
        for _ in range(system.frame_skip):
            mujoco.mj_step(model, data)
        q_next[i], qd_next[i] = data.qpos, data.qvel
    return (torch.from_numpy(x) for x in (qdd, q_next, qd_next))


def dynamics_dataset(
    system: System,
    n: int,
    generator: torch.Generator,
    q_scale: float = math.pi,
    qd_scale: float = 2.0 * math.pi,
    action_scale: float = 1.0,
) -> TensorDict:
    """n independent samples of MuJoCo's forward dynamics at random states and controls.

    q is uniform in [-q_scale, q_scale] per joint (within the joint range where limited),
    qd uniform in [-qd_scale, qd_scale], the action uniform in the control range
    ([-action_scale, action_scale] for unlimited actuators). Contacts are off.

    Returns a float64 TensorDict of batch size (n,) with keys
    `q` (n, nq), `qd` (n, nv), `action` (n, nu), `qdd` (n, nv) = MuJoCo's `qacc` after
    `mj_forward`, `tau` (n, nv) = B a, and `("next", "q")`, `("next", "qd")`: the state after
    one control step (`frame_skip` `mj_step`s) from that state under that action.
    Hinge and slide joints only.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if q_scale <= 0 or qd_scale < 0 or action_scale <= 0:
        raise ValueError(
            f"need q_scale > 0, qd_scale >= 0, action_scale > 0, "
            f"got {q_scale}, {qd_scale}, {action_scale}"
        )
    _check_scalar_joints(system)
    model = _contact_free_model(system)
    q = _uniform(*_position_box(model, q_scale), n, generator)
    qd_box = torch.full((system.nv,), qd_scale, dtype=F64)
    qd = _uniform(-qd_box, qd_box, n, generator)
    action = _uniform(*_control_box(system, action_scale), n, generator)
    qdd, q_next, qd_next = _simulate(system, model, q, qd, action)
    tau = action @ system.actuation.to(F64).T
    return TensorDict(
        {
            keys.Q: q,
            keys.QD: qd,
            keys.ACTION: action,
            keys.QDD: qdd,
            keys.TAU: tau,
            keys.NEXT_Q: q_next,
            keys.NEXT_QD: qd_next,
        },
        batch_size=[n],
    )


def reference_terms(system: System, q: Tensor) -> ReferenceTerms:
    """MuJoCo's M(q) (`mj_fullM`) and g(q) (`qfrc_bias` at zero velocity). q: (N, nq)."""
    model = _contact_free_model(system)
    data = mujoco.MjData(model)
    n = q.shape[0]
    mass, gravity = np.zeros((n, model.nv, model.nv)), np.zeros((n, model.nv))
    for i, qi in enumerate(q.detach().cpu().to(F64).numpy()):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = qi
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, mass[i])
        gravity[i] = data.qfrc_bias
    return ReferenceTerms(mass_matrix=torch.from_numpy(mass), gravity=torch.from_numpy(gravity))


class PassiveMuJoCo:
    """MuJoCo's conservative dynamics of a system: no damping, no control, contacts off.

    The reference for energy-conservation figures; batched by a loop over samples.
    """

    def __init__(self, system: System) -> None:
        self.model = _contact_free_model(system)
        self.model.dof_damping[:] = 0.0
        self.model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
        self.data = mujoco.MjData(self.model)

    def _forward(self, q: np.ndarray, qd: np.ndarray) -> None:
        self.data.qpos[:], self.data.qvel[:], self.data.ctrl[:] = q, qd, 0.0
        mujoco.mj_forward(self.model, self.data)

    def acceleration(self, q: Tensor, qd: Tensor) -> Tensor:
        """qdd at zero control: (N, nq), (N, nv) -> (N, nv), float64."""
        out = np.zeros(qd.shape)
        for i, (qi, qdi) in enumerate(zip(q.numpy(), qd.numpy(), strict=True)):
            self._forward(qi, qdi)
            out[i] = self.data.qacc
        return torch.from_numpy(out)

    def energy(self, q: Tensor, qd: Tensor) -> Tensor:
        """Kinetic plus potential energy (MuJoCo's `data.energy`): (N, nq), (N, nv) -> (N,)."""
        out = np.zeros(q.shape[0])
        for i, (qi, qdi) in enumerate(zip(q.numpy(), qd.numpy(), strict=True)):
            self._forward(qi, qdi)
            out[i] = self.data.energy.sum()
        return torch.from_numpy(out)


def _random_positions(
    model: mujoco.MjModel, n: int, generator: torch.Generator, q_scale: float
) -> Tensor:
    """(n, nq) float64: hinges and slides as `_position_box`; ball and free joints get a
    uniformly random unit quaternion; a free joint's position is uniform in [-1, 1]^2 x
    [0.5, 1.5] (the physics does not depend on it without contacts)."""
    q = _uniform(*_position_box(model, q_scale), n, generator)
    for j in range(model.njnt):
        adr, jtype = int(model.jnt_qposadr[j]), int(model.jnt_type[j])
        if jtype == mujoco.mjtJoint.mjJNT_FREE:
            q[:, adr : adr + 3] = _uniform(
                torch.tensor([-1.0, -1.0, 0.5], dtype=F64),
                torch.tensor([1.0, 1.0, 1.5], dtype=F64),
                n,
                generator,
            )
            adr += 3
        if jtype in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL):
            quat = torch.randn(n, 4, generator=generator, dtype=F64)
            q[:, adr : adr + 4] = quat / quat.norm(dim=-1, keepdim=True)
    return q


def _free_model(system: System) -> mujoco.MjModel:
    """The system's MjModel with contacts and joint and tendon limits disabled."""
    model = _contact_free_model(system)
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    return model


def inverse_dynamics_dataset(
    system: System,
    n: int,
    generator: torch.Generator,
    q_scale: float = math.pi,
    qd_scale: float = 1.0,
    qdd_scale: float = 5.0,
) -> TensorDict:
    """n random states and accelerations with MuJoCo's inverse dynamics, any joint type.

    q as `_random_positions` (hinges within their ranges where limited), qd ~ N(0, qd_scale^2)
    and qdd ~ N(0, qdd_scale^2) per DoF; tau = `mj_inverse` with contacts and limits disabled:
    the generalized force on every DoF (a floating base's 6 included) that produces qdd.

    Returns a float64 TensorDict of batch size (n,) with keys `q` (n, nq), `qd`, `qdd`,
    `tau` (n, nv) and `action` = tau, so a model with actuation B = I (one "actuator" per
    DoF) learns the generalized force directly.
    """
    if n < 1 or q_scale <= 0 or qd_scale < 0 or qdd_scale < 0:
        raise ValueError(
            f"need n >= 1, q_scale > 0, qd_scale, qdd_scale >= 0, got "
            f"{n}, {q_scale}, {qd_scale}, {qdd_scale}"
        )
    model = _free_model(system)
    q = _random_positions(model, n, generator, q_scale)
    qd = qd_scale * torch.randn(n, model.nv, generator=generator, dtype=F64)
    qdd = qdd_scale * torch.randn(n, model.nv, generator=generator, dtype=F64)
    data = mujoco.MjData(model)
    tau = np.zeros((n, model.nv))
    for i, (qi, qdi, qddi) in enumerate(zip(q.numpy(), qd.numpy(), qdd.numpy(), strict=True)):
        data.qpos[:], data.qvel[:], data.qacc[:] = qi, qdi, qddi
        mujoco.mj_inverse(model, data)
        tau[i] = data.qfrc_inverse
    tau_t = torch.from_numpy(tau)
    return TensorDict(
        {keys.Q: q, keys.QD: qd, keys.QDD: qdd, keys.TAU: tau_t, keys.ACTION: tau_t.clone()},
        batch_size=[n],
    )


def _smooth_path(
    low: Tensor, high: Tensor, steps: int, dt: float, knot_s: float, generator: torch.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """A path (steps, k) through uniform random knots in [low, high] every `knot_s` seconds,
    joined by a cubic spline (scipy's, not-a-knot), and its velocity (steps, k)."""
    from scipy.interpolate import CubicSpline

    n_knots = max(int(math.ceil(steps * dt / knot_s)) + 1, 4)
    knots = _uniform(low, high, n_knots, generator).numpy()  # (K, k)
    t = np.arange(steps) * dt
    spline = CubicSpline(np.linspace(0.0, float(t[-1]), n_knots), knots)
    return spline(t), spline(t, 1)


def trajectory_dataset(
    system: System,
    trajectories: int,
    steps: int,
    generator: torch.Generator,
    knot_s: float = 1.0,
    q_scale: float = math.pi,
    omega: float = 2.0 * math.pi,
    damping: bool = True,
) -> TensorDict:
    """Logged data of `trajectories` smooth random motions of `steps` control steps each.

    Each trajectory tracks a smooth random reference (`_smooth_path`: positions within
    [-q_scale, q_scale], or the joint range) from rest at its start by critically damped PD
    control at natural frequency `omega` (rad/s): tau_pd = M (omega^2 (q_ref - q) + 2 omega
    (qd_ref - qd)) with the mass matrix M(q), and a = B^-1 tau_pd clipped to the control range (one
    actuator per joint), in MuJoCo with contacts off. Per sample, at the state before each
    control step: q, qd, qdd (MuJoCo's qacc), tau = B a, the time t (s), the trajectory's
    index, and MuJoCo's parts of tau = M qdd + c + g + D qd: ``tau_inertial`` = M qdd,
    ``tau_coriolis`` = c(q, qd) and ``tau_gravity`` = g(q) (`qfrc_bias` at qd and at rest).
    Hinge and slide joints only. A float64 TensorDict (trajectories x steps,) in the schema
    of `mbrl_delan.data.arrays` (``t``, ``trajectory``). `damping=False`: the system with its
    joints' damping D removed (frictionless joints).
    """
    if trajectories < 1 or steps < 2:
        raise ValueError(f"need trajectories >= 1 and steps >= 2, got {trajectories}, {steps}")
    _check_scalar_joints(system)
    if system.nu != system.nv:
        raise ValueError(f"{system.name}: PD tracking needs one actuator per joint")
    model = _contact_free_model(system)
    if not damping:
        model.dof_damping[:] = 0.0
    data = mujoco.MjData(model)
    n, dt = trajectories * steps, system.control_dt
    out = {name: np.zeros((n, model.nv)) for name in ("qd", "qdd", "tau", "ti", "tc")}
    q = np.zeros((n, model.nq))
    mass = np.zeros((model.nv, model.nv))
    low, high = (x.numpy() for x in _control_box(system, 1.0))
    B = system.actuation.to(F64).numpy()
    for j in range(trajectories):
        q_ref, qd_ref = _smooth_path(*_position_box(model, q_scale), steps, dt, knot_s, generator)
        mujoco.mj_resetData(model, data)
        data.qpos[:] = q_ref[0]
        for k in range(steps):
            i = j * steps + k
            mujoco.mj_forward(model, data)
            mujoco.mj_fullM(model, data, mass)
            error = omega**2 * (q_ref[k] - data.qpos) + 2 * omega * (qd_ref[k] - data.qvel)
            data.ctrl[:] = np.clip(np.linalg.solve(B, mass @ error), low, high)
            mujoco.mj_forward(model, data)
            q[i], out["qd"][i], out["qdd"][i] = data.qpos, data.qvel, data.qacc
            out["tau"][i] = B @ data.ctrl
            out["ti"][i] = mass @ data.qacc
            out["tc"][i] = data.qfrc_bias
            for _ in range(system.frame_skip):
                mujoco.mj_step(model, data)
    gravity = reference_terms(system, torch.from_numpy(q)).gravity.numpy()
    return TensorDict(
        {
            keys.Q: torch.from_numpy(q),
            keys.QD: torch.from_numpy(out["qd"]),
            keys.QDD: torch.from_numpy(out["qdd"]),
            keys.TAU: torch.from_numpy(out["tau"]),
            keys.TAU_INERTIAL: torch.from_numpy(out["ti"]),
            keys.TAU_CORIOLIS: torch.from_numpy(out["tc"] - gravity),
            keys.TAU_GRAVITY: torch.from_numpy(gravity),
            "t": torch.from_numpy(np.tile(np.arange(steps) * dt, trajectories)),
            "trajectory": torch.arange(trajectories).repeat_interleave(steps),
        },
        batch_size=[n],
    )
