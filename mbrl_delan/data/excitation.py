"""Excitation data of an arm as robot identification makes it, in the arrays schema.

Each trajectory is one period T of a finite Fourier series per joint,

    q_j(t) = c_j + s_j sum_{l=1..L} (a_jl sin(l w t) - b_jl cos(l w t)) / (l w),  w = 2 pi / T,

with a, b ~ N(0, 1) / l (seeded), shifted to zero mean and scaled (s_j) so that the joint
stays within `use` of its range about the range's centre c_j (at most +-pi where the range is
wider) and of its velocity limit; qd and qdd are the series' exact derivatives. A
trajectory whose torques pass a motor's limit is shrunk about its mean position until they
do not (the gravity torque does not scale with it). Many short trajectories cover the joint
space better than few long ones, and more harmonics than few (the defaults: 2 s, 5
harmonics). The true generalized forces come from MuJoCo's inverse dynamics (`mj_inverse`,
joint friction and armature included when the model has them), split into M qdd, c(q, qd),
g(q) and friction. What a robot logs is then made of them: q and tau with Gaussian noise
(q: `q_noise` rad; tau: `tau_noise` of each joint's torque RMS), qd by central differences
of zero-phase low-passed q and qdd so of qd. The robot moves on through the periods before
and after each one, as a logged excitation run does: the filters see `PAD_S` of it on either
side (no edge effects).

`excitation_arrays` returns the fields of `data.arrays`' schema (q, qd, qdd, tau, t,
trajectory and the true tau_inertial, tau_coriolis, tau_gravity, tau_friction), ready for
`save_arrays`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.signal import butter, sosfiltfilt

from mbrl_delan import keys
from mbrl_delan.systems.arms import arm, arm_model, torque_limits

EXCITATION_FORMAT = "mbrl_delan.excitation/1"  # the provenance format of a fit on such data
SHRINK = 0.9  # a trajectory past a torque limit is shrunk by this factor until it is within
MAX_SHRINKS = 60  # ... at most this many times (0.9^60: 0.2% of its size)
PAD_S = 0.5  # s of the periodic motion on either side of a trajectory that the filters see


@dataclass(frozen=True)
class ExcitationSettings:
    """How trajectories are drawn and measured."""

    samples: int = 10_000  # samples in all (whole trajectories: the last one may be longer)
    period_s: float = 2.0  # one trajectory: one period of the series
    harmonics: int = 5
    rate_hz: float = 100.0  # sampling rate
    use: float = 0.8  # share of the joint range (half-width about its centre) and speed limit
    q_noise: float = 1e-4  # rad, std of the position noise
    tau_noise: float = 0.01  # std of the torque noise, a share of each joint's torque RMS
    cutoff_hz: float | None = 10.0  # low-pass of q before qd, of qd before qdd (None: none)


@dataclass
class Excitation:
    """True trajectories of one arm: t (T,), q, qd, qdd (K, T, nv)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray


def fourier_trajectories(
    model: mujoco.MjModel,
    max_velocity: np.ndarray,
    trajectories: int,
    settings: ExcitationSettings,
    rng: np.random.Generator,
) -> Excitation:
    """`trajectories` seeded Fourier-series trajectories inside the joints' ranges and
    velocity limits (module docstring)."""
    steps = round(settings.period_s * settings.rate_hz)
    t = np.arange(steps) / settings.rate_hz
    w = 2 * math.pi / settings.period_s
    l = np.arange(1, settings.harmonics + 1)  # noqa: E741 (the harmonic's number)
    shape = (trajectories, model.nv, settings.harmonics)
    a, b = rng.normal(size=shape) / l, rng.normal(size=shape) / l
    phase = np.outer(t, l * w)  # (T, L)
    sin, cos = np.sin(phase), np.cos(phase)
    q = np.einsum("kjl,tl->ktj", a / (l * w), sin) - np.einsum("kjl,tl->ktj", b / (l * w), cos)
    qd = np.einsum("kjl,tl->ktj", a, cos) + np.einsum("kjl,tl->ktj", b, sin)
    qdd = w * (np.einsum("kjl,tl->ktj", -a * l, sin) + np.einsum("kjl,tl->ktj", b * l, cos))
    q = q - q.mean(1, keepdims=True)
    low, high = model.jnt_range[:, 0], model.jnt_range[:, 1]
    centre = np.where(model.jnt_limited > 0, (low + high) / 2, 0.0)
    half = np.minimum(np.where(model.jnt_limited > 0, (high - low) / 2, math.pi), math.pi)
    reach = settings.use * np.minimum(half / np.abs(q).max(1), max_velocity / np.abs(qd).max(1))
    scale = reach[:, None, :]  # (K, 1, nv)
    return Excitation(t, centre + scale * q, scale * qd, scale * qdd)


def inverse_dynamics(
    model: mujoco.MjModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
) -> dict[str, np.ndarray]:
    """MuJoCo's generalized forces along states (N, nv): tau (all of them, friction
    included) and its parts M qdd (armature included), c(q, qd), g(q) and the joints'
    friction (the rest)."""
    data = mujoco.MjData(model)
    out = {k: np.zeros_like(q) for k in ("tau", *_PARTS)}
    mass = np.zeros((model.nv, model.nv))
    for i in range(q.shape[0]):
        data.qpos[:], data.qvel[:], data.qacc[:] = q[i], qd[i], qdd[i]
        mujoco.mj_inverse(model, data)
        out["tau"][i] = data.qfrc_inverse
        mujoco.mj_fullM(model, data, mass)
        out[keys.TAU_INERTIAL][i] = mass @ qdd[i]
        bias = data.qfrc_bias.copy()
        data.qvel[:] = 0
        mujoco.mj_forward(model, data)  # the bias at rest: gravity
        out[keys.TAU_GRAVITY][i] = data.qfrc_bias
        out[keys.TAU_CORIOLIS][i] = bias - data.qfrc_bias
    rough = (model.dof_damping > 0) | (model.dof_frictionloss > 0)  # (nv,) joints with friction
    out[keys.TAU_FRICTION] = np.where(rough, out["tau"] - sum(out[k] for k in _PARTS[:3]), 0.0)
    return out


_PARTS = (keys.TAU_INERTIAL, keys.TAU_CORIOLIS, keys.TAU_GRAVITY, keys.TAU_FRICTION)


def excitation_arrays(
    robot: str, friction: bool, settings: ExcitationSettings, seed: int
) -> dict[str, np.ndarray]:
    """Measured excitation data of a shipped arm in `data.arrays`' schema (module docstring):
    whole trajectories until `settings.samples`, seeded by `seed`."""
    model = arm_model(robot, friction)
    rng = np.random.default_rng(seed)
    steps = round(settings.period_s * settings.rate_hz)
    count = max(1, math.ceil(settings.samples / steps))
    true = fourier_trajectories(model, np.array(arm(robot).max_velocity), count, settings, rng)
    forces = _within_torque_limits(model, true)
    flat = lambda x: x.reshape(-1, model.nv)  # noqa: E731
    rms = np.sqrt((forces["tau"] ** 2).mean(0))
    tau = forces["tau"] + settings.tau_noise * rms * rng.normal(size=forces["tau"].shape)
    pad = min(round(PAD_S * settings.rate_hz), steps)
    q = _periodic(true.q, pad) + settings.q_noise * rng.normal(
        size=(count, steps + 2 * pad, model.nv)
    )
    qd = _derivative(q, settings)
    qdd = _derivative(qd, settings)
    inner = slice(pad, pad + steps)
    return {
        "q": flat(q[:, inner]), "qd": flat(qd[:, inner]), "qdd": flat(qdd[:, inner]), "tau": tau,
        "t": np.tile(true.t, count),
        "trajectory": np.repeat(np.arange(count), steps),
        **{k: forces[k] for k in _PARTS},
    }  # fmt: skip


def _within_torque_limits(model: mujoco.MjModel, true: Excitation) -> dict[str, np.ndarray]:
    """The forces of each trajectory, shrunk about its mean position (qd and qdd with it) by
    `SHRINK` until its torques are within the motors' limits; `true` is changed in place.
    The forces' fields (K x T, nv)."""
    limits = torque_limits(model)
    parts = []
    for k in range(true.q.shape[0]):
        for _ in range(MAX_SHRINKS):
            forces = inverse_dynamics(model, true.q[k], true.qd[k], true.qdd[k])
            if (np.abs(forces["tau"]) <= limits).all():
                break
            mean = true.q[k].mean(0)
            true.q[k] = mean + SHRINK * (true.q[k] - mean)
            true.qd[k] *= SHRINK
            true.qdd[k] *= SHRINK
        else:
            raise ValueError(
                f"trajectory {k}: torques past the motors' limits even nearly at rest "
                f"(joints {np.flatnonzero((np.abs(forces['tau']) > limits).any(0)).tolist()})"
            )
        parts.append(forces)
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def _periodic(x: np.ndarray, pad: int) -> np.ndarray:
    """Periodic trajectories (K, T, nv) with `pad` steps of the periods before and after."""
    return np.concatenate([x[:, x.shape[1] - pad :], x, x[:, :pad]], axis=1)


def _derivative(x: np.ndarray, settings: ExcitationSettings) -> np.ndarray:
    """d/dt of measured signals (K, T, nv): central differences of zero-phase low-passed x."""
    if settings.cutoff_hz is not None:
        sos = butter(4, settings.cutoff_hz, fs=settings.rate_hz, output="sos")
        x = sosfiltfilt(sos, x, axis=1)
    return np.gradient(x, 1.0 / settings.rate_hz, axis=1)


def mass_matrix_error(robot: str, friction: bool, q: np.ndarray, mass: np.ndarray) -> float:
    """Median over states q (N, nv) of ||M_model - M||_F / ||M||_F, M the arm's own
    (`mj_fullM`, armature included) and `mass` (N, nv, nv) a model's."""
    model = arm_model(robot, friction)
    data = mujoco.MjData(model)
    true = np.zeros((model.nv, model.nv))
    errors = []
    for qi, mi in zip(q, mass, strict=True):
        data.qpos[:] = qi
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, true)
        errors.append(np.linalg.norm(mi - true) / np.linalg.norm(true))
    return float(np.median(errors))
