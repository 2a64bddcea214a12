"""Excitation data of an arm as robot identification makes it, in the arrays schema.

Three trajectory designs (`DESIGNS`, each seeded; every joint within `use` of its range's
half-width about the range's centre, at most +-pi where the range is wider, and of its
velocity limit):

- ``fourier`` (the project's): each trajectory one period T of a finite Fourier series per
  joint, ``q_j(t) = c_j + s_j sum_{l=1..L} (a_jl sin(l w t) - b_jl cos(l w t)) / (l w)``,
  w = 2 pi / T, a, b ~ N(0, 1) / l, shifted to zero mean and scaled (s_j) to the limits
  about the centre c_j. Many short trajectories cover the joint space better than few long
  ones, and more harmonics than few (the defaults: 2 s, 5 harmonics);
- ``sinusoids``: per joint a sum of `SINES` sinusoids of random frequencies in
  `SINE_HZ`, phases and amplitudes, scaled to a random share (`SINE_SIZE`) of the largest
  reach and placed about a random centre inside the range: not periodic, not centred;
- ``point_to_point``: random targets inside the range, every joint moving from one to the
  next together on a minimum-jerk profile (zero velocity and acceleration at each target)
  lasting `P2P_SLOWER` x the shortest time the velocity limits allow.

qd and qdd are the designs' exact derivatives. A trajectory whose torques pass a motor's
limit is shrunk about its mean position until they do not (the gravity torque does not scale
with it). The true generalized forces come from MuJoCo's inverse dynamics (`mj_inverse`,
joint friction, armature and springs included when the model has them) plus, for
``coulomb_viscous`` friction, f sign(qd) (`mbrl_delan.systems.arms.coulomb_friction`), split
into M qdd, c(q, qd), g(q) (gravity and springs: the potential's) and friction. What a
robot logs is then made of them: q and tau with Gaussian noise (q: `q_noise` rad; tau:
`tau_noise` of each joint's torque RMS), qd by central differences of zero-phase low-passed
q and qdd so of qd. The robot moves on before and after each trajectory, as a logged
excitation run does: the filters see `PAD_S` of the motion on either side (no edge effects).

`excitation_arrays` returns the fields of `data.arrays`' schema (q, qd, qdd, tau, t,
trajectory and the true tau_inertial, tau_coriolis, tau_gravity, tau_friction), ready for
`save_arrays`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.signal import butter, sosfiltfilt

from mbrl_delan import keys
from mbrl_delan.systems.arms import (
    arm_model,
    coulomb_friction,
    friction_kind,
    range_middle_and_half,
    torque_limits,
    velocity_limits,
)

EXCITATION_FORMAT = "mbrl_delan.excitation/1"  # the provenance format of a fit on such data
SHRINK = 0.9  # a trajectory past a torque limit is shrunk by this factor until it is within
MAX_SHRINKS = 60  # ... at most this many times (0.9^60: 0.2% of its size)
PAD_S = 0.5  # s of the motion on either side of a trajectory that the filters see
SINES = 4  # design sinusoids: sinusoids per joint
SINE_HZ = (0.1, 1.0)  # ... their frequencies' range
SINE_SIZE = (0.3, 1.0)  # ... a trajectory's share of the largest reach the limits allow
P2P_SLOWER = (1.0, 2.0)  # design point_to_point: a move's duration over the shortest, range
P2P_MIN_S = 0.3  # ... the shortest move
CENTRES = ("middle", "random")  # design fourier: each trajectory about the range's middle or not


@dataclass(frozen=True)
class ExcitationSettings:
    """How trajectories are drawn and measured."""

    samples: int = 10_000  # samples in all (whole trajectories: the last one may be longer)
    period_s: float = 2.0  # one trajectory's length (design fourier: one period of the series)
    harmonics: int = 5  # design fourier: harmonics per joint
    rate_hz: float = 100.0  # sampling rate
    use: float = 0.8  # share of the joint range (half-width about its centre) and speed limit
    q_noise: float = 1e-4  # rad, std of the position noise
    tau_noise: float = 0.01  # std of the torque noise, a share of each joint's torque RMS
    cutoff_hz: float | None = 10.0  # low-pass of q before qd, of qd before qdd (None: none)
    design: str = "fourier"  # fourier | sinusoids | point_to_point (module docstring)
    centres: str = "middle"  # design fourier: about the range's middle | random centres in it
    max_velocity: float | None = None  # every joint's speed limit (None: the arm's own)


@dataclass
class Excitation:
    """True trajectories of one arm: t (T,), q, qd, qdd (K, T, nv)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray


@dataclass(frozen=True)
class _Limits:
    """A design's bounds: each joint's range centre, half-width (at most pi) and speed."""

    centre: np.ndarray  # (nv,)
    half: np.ndarray  # (nv,)
    speed: np.ndarray  # (nv,)

    @classmethod
    def of(cls, model: mujoco.MjModel, max_velocity: np.ndarray, use: float) -> _Limits:
        centre, half = range_middle_and_half(model)
        return cls(centre, use * half, use * max_velocity)


def _times(settings: ExcitationSettings, pad: int) -> np.ndarray:
    """A trajectory's sample times with `pad` samples on either side. (T + 2 pad,)"""
    steps = round(settings.period_s * settings.rate_hz)
    return (np.arange(steps + 2 * pad) - pad) / settings.rate_hz


def _largest_reach(q: np.ndarray, qd: np.ndarray, limits: _Limits) -> np.ndarray:
    """The largest scale of zero-mean trajectories q, qd (K, T, nv) within the half-widths
    and speeds. (K, 1, nv)"""
    tiny = 1e-12
    reach = np.minimum(limits.half / np.maximum(np.abs(q).max(1), tiny),
                       limits.speed / np.maximum(np.abs(qd).max(1), tiny))  # fmt: skip
    return reach[:, None, :]


def fourier_trajectories(
    model: mujoco.MjModel,
    max_velocity: np.ndarray,
    trajectories: int,
    settings: ExcitationSettings,
    rng: np.random.Generator,
    pad: int = 0,
) -> Excitation:
    """`trajectories` seeded Fourier-series trajectories (design ``fourier``) inside the
    joints' ranges and velocity limits, with `pad` samples of the periods before and after."""
    t = _times(settings, pad)
    w = 2 * math.pi / settings.period_s
    l = np.arange(1, settings.harmonics + 1)  # noqa: E741 (the harmonic's number)
    shape = (trajectories, model.nv, settings.harmonics)
    a, b = rng.normal(size=shape) / l, rng.normal(size=shape) / l
    phase = np.outer(t, l * w)  # (T, L)
    sin, cos = np.sin(phase), np.cos(phase)
    q = np.einsum("kjl,tl->ktj", a / (l * w), sin) - np.einsum("kjl,tl->ktj", b / (l * w), cos)
    qd = np.einsum("kjl,tl->ktj", a, cos) + np.einsum("kjl,tl->ktj", b, sin)
    qdd = w * (np.einsum("kjl,tl->ktj", -a * l, sin) + np.einsum("kjl,tl->ktj", b * l, cos))
    inner = slice(pad, t.size - pad)
    q = q - q[:, inner].mean(1, keepdims=True)
    limits = _Limits.of(model, max_velocity, settings.use)
    scale = _largest_reach(q, qd, limits)
    centre = limits.centre[None, None, :]
    if settings.centres == "random":
        centre = _random_centres(q, scale, limits, rng)
    return Excitation(t, centre + scale * q, scale * qd, scale * qdd)


def _random_centres(
    q: np.ndarray, scale: np.ndarray, limits: _Limits, rng: np.random.Generator
) -> np.ndarray:
    """A uniform centre per trajectory and joint where zero-mean q (K, T, nv) times `scale`
    (K, 1, nv) stays inside the half-widths about the range's middle. (K, 1, nv)"""
    room = np.maximum(limits.half - scale[:, 0] * np.abs(q).max(1), 0.0)  # (K, nv)
    return (limits.centre + rng.uniform(-1, 1, size=room.shape) * room)[:, None, :]


def sinusoid_trajectories(
    model: mujoco.MjModel,
    max_velocity: np.ndarray,
    trajectories: int,
    settings: ExcitationSettings,
    rng: np.random.Generator,
    pad: int = 0,
) -> Excitation:
    """Design ``sinusoids`` (module docstring), with `pad` samples on either side."""
    t = _times(settings, pad)
    shape = (trajectories, 1, model.nv, SINES)
    f = 2 * math.pi * rng.uniform(*SINE_HZ, size=shape)  # rad/s
    phase = rng.uniform(0, 2 * math.pi, size=shape)
    amplitude = rng.uniform(0.2, 1.0, size=shape)
    angle = f * t[None, :, None, None] + phase  # (K, T, nv, S)
    q = (amplitude * np.sin(angle)).sum(-1)
    qd = (amplitude * f * np.cos(angle)).sum(-1)
    qdd = -(amplitude * f**2 * np.sin(angle)).sum(-1)
    q = q - q.mean(1, keepdims=True)
    limits = _Limits.of(model, max_velocity, settings.use)
    size = rng.uniform(*SINE_SIZE, size=(trajectories, 1, model.nv))
    scale = size * _largest_reach(q, qd, limits)
    centre = _random_centres(q, scale, limits, rng)
    return Excitation(t, centre + scale * q, scale * qd, scale * qdd)


def point_to_point_trajectories(
    model: mujoco.MjModel,
    max_velocity: np.ndarray,
    trajectories: int,
    settings: ExcitationSettings,
    rng: np.random.Generator,
    pad: int = 0,
) -> Excitation:
    """Design ``point_to_point`` (module docstring), with `pad` samples on either side."""
    t = _times(settings, pad)
    limits = _Limits.of(model, max_velocity, settings.use)
    out = np.zeros((3, trajectories, t.size, model.nv))
    for k in range(trajectories):
        start, clock = limits.centre + limits.half * rng.uniform(-1, 1, model.nv), t[0]
        clock -= rng.uniform(0, P2P_MIN_S)  # the first move under way at the first sample
        while clock < t[-1]:
            goal = limits.centre + limits.half * rng.uniform(-1, 1, model.nv)
            # min-jerk: peak speed 1.875 |delta| / duration
            fastest = max(P2P_MIN_S, float(np.max(1.875 * np.abs(goal - start) / limits.speed)))
            duration = fastest * rng.uniform(*P2P_SLOWER)
            rows = (t >= clock) & (t < clock + duration)
            s = (t[rows] - clock) / duration
            delta = goal - start
            out[0, k, rows] = start + np.outer(10 * s**3 - 15 * s**4 + 6 * s**5, delta)
            out[1, k, rows] = np.outer((30 * s**2 - 60 * s**3 + 30 * s**4) / duration, delta)
            out[2, k, rows] = np.outer((60 * s - 180 * s**2 + 120 * s**3) / duration**2, delta)
            start, clock = goal, clock + duration
    return Excitation(t, *out)


DesignFn = Callable[
    [mujoco.MjModel, np.ndarray, int, ExcitationSettings, np.random.Generator, int], Excitation
]
DESIGNS: dict[str, DesignFn] = {
    "fourier": fourier_trajectories,
    "sinusoids": sinusoid_trajectories,
    "point_to_point": point_to_point_trajectories,
}


def inverse_dynamics(
    model: mujoco.MjModel,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    coulomb: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """MuJoCo's generalized forces along states (N, nv), plus `coulomb` (nv,) x sign(qd) when
    given: tau (all of them, friction included) and its parts M qdd (armature included),
    c(q, qd), g(q) (the potential's: gravity and the model's springs) and the joints'
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
        mujoco.mj_forward(model, data)  # the bias at rest: gravity; the passive: springs
        out[keys.TAU_GRAVITY][i] = data.qfrc_bias - data.qfrc_passive
        out[keys.TAU_CORIOLIS][i] = bias - data.qfrc_bias
    if coulomb is not None:
        out["tau"] = out["tau"] + coulomb * np.sign(qd)
    rough = (model.dof_damping > 0) | (model.dof_frictionloss > 0)  # (nv,) joints with friction
    if coulomb is not None:
        rough = rough | (coulomb > 0)
    out[keys.TAU_FRICTION] = np.where(rough, out["tau"] - sum(out[k] for k in _PARTS[:3]), 0.0)
    return out


_PARTS = (keys.TAU_INERTIAL, keys.TAU_CORIOLIS, keys.TAU_GRAVITY, keys.TAU_FRICTION)


def excitation_arrays(
    robot: str,
    friction: str | bool,
    settings: ExcitationSettings,
    seed: int,
    structure: str = "none",
) -> dict[str, np.ndarray]:
    """Measured excitation data of an arm (a shipped one's name or an MJCF file;
    `mbrl_delan.systems.arms`, with the springs `structure` names) in `data.arrays`' schema
    (module docstring): whole trajectories of `settings.design` until `settings.samples`,
    seeded by `seed`."""
    if settings.design not in DESIGNS:
        raise ValueError(f"design {settings.design!r}: choose one of {', '.join(DESIGNS)}")
    model = arm_model(robot, friction, structure=structure)
    coulomb = (coulomb_friction(robot, friction)
               if friction_kind(friction) == "coulomb_viscous" else None)  # fmt: skip
    rng = np.random.default_rng(seed)
    steps = round(settings.period_s * settings.rate_hz)
    count = max(1, math.ceil(settings.samples / steps))
    pad = min(round(PAD_S * settings.rate_hz), steps)
    design = DESIGNS[settings.design]
    speed = velocity_limits(model, robot)
    if settings.max_velocity is not None:
        speed = np.full(model.nv, settings.max_velocity)
    true = design(model, speed, count, settings, rng, pad)
    forces = _within_torque_limits(model, true, pad, coulomb)
    flat = lambda x: x.reshape(-1, model.nv)  # noqa: E731
    rms = np.sqrt((forces["tau"] ** 2).mean(0))
    tau = forces["tau"] + settings.tau_noise * rms * rng.normal(size=forces["tau"].shape)
    q = true.q + settings.q_noise * rng.normal(size=true.q.shape)
    qd = _derivative(q, settings)
    qdd = _derivative(qd, settings)
    inner = slice(pad, pad + steps)
    return {
        "q": flat(q[:, inner]), "qd": flat(qd[:, inner]), "qdd": flat(qdd[:, inner]), "tau": tau,
        "t": np.tile(true.t[inner] - true.t[pad], count),
        "trajectory": np.repeat(np.arange(count), steps),
        **{k: forces[k] for k in _PARTS},
    }  # fmt: skip


def _within_torque_limits(
    model: mujoco.MjModel, true: Excitation, pad: int, coulomb: np.ndarray | None
) -> dict[str, np.ndarray]:
    """The forces along each trajectory's inner part (without `pad` samples at either end),
    shrunk about its mean position (qd and qdd with it) by `SHRINK` until its torques are
    within the motors' limits; `true` is changed in place. The forces' fields (K x T, nv)."""
    limits = torque_limits(model)
    parts = []
    cut = slice(pad, true.t.size - pad)
    for k in range(true.q.shape[0]):
        for _ in range(MAX_SHRINKS):
            forces = inverse_dynamics(
                model, true.q[k, cut], true.qd[k, cut], true.qdd[k, cut], coulomb
            )
            if (np.abs(forces["tau"]) <= limits).all():
                break
            mean = true.q[k, cut].mean(0)
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


def _derivative(x: np.ndarray, settings: ExcitationSettings) -> np.ndarray:
    """d/dt of measured signals (K, T, nv): central differences of zero-phase low-passed x."""
    if settings.cutoff_hz is not None:
        sos = butter(4, settings.cutoff_hz, fs=settings.rate_hz, output="sos")
        x = sosfiltfilt(sos, x, axis=1)
    return np.gradient(x, 1.0 / settings.rate_hz, axis=1)


def mass_matrix_error(robot: str, friction: str | bool, q: np.ndarray, mass: np.ndarray) -> float:
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
