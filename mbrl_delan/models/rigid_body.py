"""The white-box inverse dynamics of a robot whose kinematic tree is known: `WhiteBoxInverse`.

The model is the robot's MJCF (joints, bodies, frames) with the numbers a user rarely knows
well identified from data: every moving body's inertial parameters, and each joint's viscous
and Coulomb friction and armature. Inverse dynamics is linear in them, the classical fact
robot identification rests on:

    tau = Y(q, qd, qdd) p,   p = [pi_1 .. pi_B, b, f, a]

with pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] a body's mass, first moment
(mass times centre of mass) and rotational inertia about its frame's origin, in its frame;
per DoF b (viscous, column qd), f (Coulomb) and a (armature, column qdd). The Coulomb column
is the friction law's direction (`FRICTION_LAWS`): ``coulomb_viscous``, a real joint's
f sign(qd); ``frictionloss``, MuJoCo's soft constraint, whose force opposes qdd + b' qd
(`friction_damping`) and is f only once saturated.
`regressor` takes Y from MuJoCo: torque is affine in each pi, so a column is the change of
`mj_inverse`'s torque when one parameter moves (exact to round-off).

`identify_parameters` solves the weighted least squares (rows in units of each DoF's torque
scale, as the fits' loss) with a weak ridge toward a prior (directions the data leave
undetermined, such as the base link's tilt inertias, keep the prior's values), then refines
it by Gauss-Newton (`mujoco.minimize.least_squares`) over the log-Cholesky factor of each
body's pseudo-inertia ``J = [[tr(I)/2 1 - I, h], [h^T, m]]``: J positive definite is physical
consistency (positive mass, inertia about the centre of mass positive definite and
satisfying the triangle inequalities). Friction and armature are bounded below by zero.

Predictions use the law the fit identified: `mj_inverse` on the MJCF with the identified
inertials, damping and armature, plus f sign(qd) (``coulomb_viscous``), or with f as MuJoCo's
``frictionloss`` (``frictionloss``: only for data made by that constraint). The forward
dynamics (`acceleration`) is the same law solved for qdd, so forward(inverse) is the identity.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass

import mujoco
import numpy as np
import torch
from mujoco import minimize
from tensordict import TensorDictBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.models.inertial import (
    cholesky_of_pi,
    inertial_parameters,
    moving_bodies,
    physically_consistent,
    pi_from_cholesky,
    set_inertial_parameters,
)
from mbrl_delan.models.inverse import InverseDynamicsModel

log = logging.getLogger(__name__)

N_INERTIAL = 10  # pi per body
LENGTH = 0.1  # m, the length unit of a body's parameter scales (first moment, inertia)
FD_STEP = 1e-4  # a regressor column's step, a share of the parameter's scale
BOUND = 1e6  # |theta|, friction and armature: far beyond any arm's
FRICTION_LAWS = ("coulomb_viscous", "frictionloss")  # the Coulomb force's law (module docstring)


# ---------------------------------------------------------------- the regressor


def rigid_body_model(model: mujoco.MjModel) -> mujoco.MjModel:
    """A copy of `model` whose inverse dynamics is the rigid body's alone: no joint friction,
    armature, passive forces or constraints."""
    rigid = _copy(model)
    rigid.dof_damping[:] = rigid.dof_frictionloss[:] = rigid.dof_armature[:] = 0.0
    for flag in ("CONSTRAINT", "SPRING", "DAMPER"):
        rigid.opt.disableflags |= getattr(mujoco.mjtDisableBit, f"mjDSBL_{flag}")
    return rigid


def _copy(model: mujoco.MjModel) -> mujoco.MjModel:
    return copy.copy(model)  # MjModel's copy is a deep one


def friction_damping(model: mujoco.MjModel) -> np.ndarray:
    """Each DoF's reference damping b of MuJoCo's soft ``frictionloss`` constraint,
    2 / (dmax timeconst) of its ``solimp`` and ``solref``: the force opposes qdd + b qd (the
    velocity's direction except within qdd / b of zero). (nv,)"""
    timeconst = np.maximum(model.dof_solref[:, 0], 2 * model.opt.timestep)
    return 2.0 / (model.dof_solimp[:, 1] * timeconst)


def parameter_scales(model: mujoco.MjModel, bodies: list[int]) -> np.ndarray:
    """Each body's inertial parameters' natural size: m, m LENGTH, m LENGTH^2. (B, 10)"""
    mass = np.maximum(model.body_mass[bodies], 1e-3)[:, None]
    unit = np.array([1.0, *(3 * [LENGTH]), *(6 * [LENGTH**2])])
    return mass * unit


def inverse_torques(
    model: mujoco.MjModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
) -> np.ndarray:
    """`mj_inverse`'s generalized forces along states (N, nq), (N, nv), (N, nv). (N, nv)"""
    data = mujoco.MjData(model)
    out = np.zeros_like(qd)
    for i in range(q.shape[0]):
        data.qpos[:], data.qvel[:], data.qacc[:] = q[i], qd[i], qdd[i]
        mujoco.mj_inverse(model, data)
        out[i] = data.qfrc_inverse
    return out


def data_friction_law(kind: str | None) -> str:
    """The Coulomb law of data made with friction `kind` (`systems.arms.FRICTION_KINDS`;
    None: unknown, a robot's logs): MuJoCo's soft constraint only for data it made."""
    return "frictionloss" if kind == "frictionloss" else "coulomb_viscous"


def coulomb_direction(
    model: mujoco.MjModel, qd: np.ndarray, qdd: np.ndarray, law: str
) -> np.ndarray:
    """The unit Coulomb force's direction under `law` (`FRICTION_LAWS`): sign(qd), or the
    saturated direction sign(qdd + b qd) of MuJoCo's soft ``frictionloss``. (N, nv)"""
    if law == "frictionloss":
        return np.sign(qdd + friction_damping(model) * qd)
    return np.sign(qd)


def regressor(
    model: mujoco.MjModel,
    bodies: list[int],
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    law: str = "coulomb_viscous",
) -> np.ndarray:
    """Y with tau = Y p (module docstring) along states (N, nq), (N, nv), (N, nv), taken by
    differences of MuJoCo's inverse dynamics about `model`'s own inertials; the Coulomb
    column by `law`. -> (N, nv, 10 B + 3 nv)"""
    rigid = rigid_body_model(model)
    base = inverse_torques(rigid, q, qd, qdd)
    scales = parameter_scales(model, bodies)
    columns = []
    for b, body in enumerate(bodies):
        pi = inertial_parameters(rigid, body)
        for j in range(N_INERTIAL):
            step = FD_STEP * scales[b, j]
            set_inertial_parameters(rigid, body, pi + step * np.eye(N_INERTIAL)[j])
            columns.append((inverse_torques(rigid, q, qd, qdd) - base) / step)
        set_inertial_parameters(rigid, body, pi)
    eye = np.eye(model.nv)
    coulomb = coulomb_direction(model, qd, qdd, law)
    friction = [eye * x[:, None, :] for x in (qd, coulomb, qdd)]  # each (N, nv, nv)
    return np.concatenate([np.stack(columns, -1), *friction], -1)


# ---------------------------------------------------------------- identification


@dataclass
class Identified:
    """What `identify_parameters` found: pi per body (B, 10), viscous, Coulomb and armature
    per DoF (nv,), and the weighted data residual's mean square (normalised torque units)."""

    inertials: np.ndarray
    viscous: np.ndarray
    coulomb: np.ndarray
    armature: np.ndarray
    mse: float


def identify_parameters(
    Y: np.ndarray,
    tau: np.ndarray,
    tau_scale: np.ndarray,
    prior: np.ndarray,
    scales: np.ndarray,
    prior_weight: float,
    max_iter: int = 50,
) -> Identified:
    """Weighted least squares of tau (N, nv) on Y (N, nv, P) with a ridge toward the prior
    inertials (B, 10) in units of `scales` (B, 10), then the physically consistent refinement
    (module docstring). Rows are divided by `tau_scale` (nv,); the data term is the mean over
    rows, the ridge `prior_weight` times the sum of squares over the parameters."""
    n_rows = tau.size
    A = (Y / tau_scale[:, None]).reshape(n_rows, -1)  # (N nv, P)
    b = (tau / tau_scale).reshape(n_rows)
    R, z, floor = _compressed(A, b)
    n_inertial = prior.size
    n_dof = (A.shape[1] - n_inertial) // 3
    ridge = np.sqrt(prior_weight) / scales.reshape(-1)
    # the linear problem: [R / sqrt(rows); diag(ridge) on the inertials] p = [z; ridge prior]
    lhs = np.concatenate([R / np.sqrt(n_rows), np.diag(np.r_[ridge, np.zeros(3 * n_dof)])])
    rhs = np.concatenate(
        [z / np.sqrt(n_rows), np.r_[ridge * prior.reshape(-1), np.zeros(3 * n_dof)]]
    )
    p = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    theta = np.stack([cholesky_of_pi(pi) for pi in p[:n_inertial].reshape(prior.shape)])
    x0 = np.r_[theta.reshape(-1), np.maximum(p[n_inertial:], 0.0)]

    def parameters(x: np.ndarray) -> np.ndarray:  # (n, k) -> (P, k)
        inertial = pi_from_cholesky(x[:n_inertial].T.reshape(-1, *prior.shape))
        return np.concatenate([inertial.reshape(x.shape[1], -1).T, x[n_inertial:]])

    def residual(x: np.ndarray) -> np.ndarray:
        p = parameters(x)
        data = (R @ p - z[:, None]) / np.sqrt(n_rows)
        return np.concatenate([data, ridge[:, None] * (p[:n_inertial] - prior.reshape(-1, 1))])

    lower = np.r_[np.full(n_inertial, -BOUND), np.zeros(3 * n_dof)]  # the solver's box is finite
    upper = np.full(x0.size, BOUND)
    x, _ = minimize.least_squares(x0, residual, bounds=(lower, upper), max_iter=max_iter, verbose=0)
    p = parameters(x[:, None])[:, 0]
    mse = float(((R @ p - z) ** 2).sum() + floor) / n_rows
    viscous, coulomb, armature = p[n_inertial:].reshape(3, n_dof)
    return Identified(p[:n_inertial].reshape(prior.shape), viscous, coulomb, armature, mse)


def _compressed(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """R, z with ||A p - b||^2 = ||R p - z||^2 + floor for every p (thin QR of [A b])."""
    Rb = np.linalg.qr(np.concatenate([A, b[:, None]], 1), mode="r")
    return Rb[:-1, :-1], Rb[:-1, -1], float(Rb[-1, -1] ** 2)


# ---------------------------------------------------------------- the model


class WhiteBoxInverse(InverseDynamicsModel):
    """tau = MuJoCo's inverse dynamics of `model` with identified inertials, friction and
    armature (module docstring). The numbers are buffers (saved with the state dict):
    ``inertials`` (B, 10), ``viscous``, ``coulomb``, ``armature`` (nv,); before `identify`
    they are the prior's: the MJCF's inertials times `prior_scale`, no friction or armature.

    Args:
        model: the robot's MJCF (its tree and frames; its own inertials give the prior).
        prior_scale: the prior's share of the MJCF's inertials (a documented wrong start).
        prior_weight: the ridge toward the prior (`identify_parameters`).
        std_floor: see `InverseDynamicsModel`.
        friction_law: the Coulomb force's law, identified and predicted (`FRICTION_LAWS`).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        prior_scale: float = 0.5,
        prior_weight: float = 1e-6,
        std_floor: float = 1e-3,
        friction_law: str = "coulomb_viscous",
    ) -> None:
        super().__init__(model.nv, std_floor)
        if prior_scale <= 0 or prior_weight < 0:
            raise ValueError(
                f"need prior_scale > 0, prior_weight >= 0: {prior_scale}, {prior_weight}"
            )
        if friction_law not in FRICTION_LAWS:
            raise ValueError(f"friction_law {friction_law!r}: one of {', '.join(FRICTION_LAWS)}")
        self.prior_weight = prior_weight
        self.friction_law = friction_law
        self.bodies = moving_bodies(model)
        prior = prior_scale * np.stack([inertial_parameters(model, b) for b in self.bodies])
        self._model = _copy(model)
        self._data = mujoco.MjData(self._model)
        self.register_buffer("prior", torch.as_tensor(prior))
        self.register_buffer("inertials", torch.as_tensor(prior.copy()))
        for name in ("viscous", "coulomb", "armature"):
            self.register_buffer(name, torch.zeros(model.nv, dtype=torch.float64))

    def mujoco_model(self) -> mujoco.MjModel:
        """The MJCF with the model's current numbers (MuJoCo's constants recomputed)."""
        model = self._model
        for body, pi in zip(self.bodies, self.inertials.cpu().numpy(), strict=True):
            set_inertial_parameters(model, body, pi)
        model.dof_damping[:] = self.viscous.cpu().numpy()
        soft = self.friction_law == "frictionloss"
        model.dof_frictionloss[:] = self.coulomb.cpu().numpy() if soft else 0.0
        model.dof_armature[:] = self.armature.cpu().numpy()
        mujoco.mj_setConst(model, self._data)
        return model

    @torch.no_grad()
    def identify(self, data: TensorDictBase) -> Identified:
        """Identify every number from samples (N,) with q, qd, qdd, tau; `fit_normalization`
        first (the rows' units)."""
        q, qd, qdd, tau = (data[k].to("cpu", torch.float64).numpy()
                           for k in (keys.Q, keys.QD, keys.QDD, keys.TAU))  # fmt: skip
        prior = self.prior.cpu().numpy()
        start = _with_inertials(self._model, self.bodies, prior)
        Y = regressor(start, self.bodies, q, qd, qdd, self.friction_law)
        found = identify_parameters(
            Y, tau, self.tau_scale.to("cpu", torch.float64).numpy(), prior,
            parameter_scales(start, self.bodies), self.prior_weight,
        )  # fmt: skip
        for name in ("inertials", "viscous", "coulomb", "armature"):
            getattr(self, name).copy_(torch.as_tensor(getattr(found, name)))
        return found

    def predict_torque(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        lead = qd.shape[:-1]
        arrays = [x.detach().reshape(-1, x.shape[-1]).to("cpu", torch.float64).numpy()
                  for x in (q, qd, qdd)]  # fmt: skip
        tau = inverse_torques(self.mujoco_model(), *arrays) + self._sign_coulomb(arrays[1])
        return torch.as_tensor(tau).to(qd).reshape(*lead, self.nv)

    def _sign_coulomb(self, qd: np.ndarray) -> np.ndarray:
        """f sign(qd) of the ``coulomb_viscous`` law (zero under ``frictionloss``, whose
        force is in the MJCF). (N, nv)"""
        if self.friction_law == "frictionloss":
            return np.zeros_like(qd)
        return self.coulomb.cpu().numpy() * np.sign(qd)

    @torch.no_grad()
    def acceleration(self, q: Tensor, qd: Tensor, tau: Tensor) -> Tensor:
        """The forward dynamics of the same model: qdd with `predict_torque(q, qd, qdd)` =
        tau (MuJoCo's forward dynamics of the identified MJCF under tau, less f sign(qd) for
        ``coulomb_viscous``). (..., nv)"""
        lead = qd.shape[:-1]
        q_, qd_, tau_ = (x.reshape(-1, x.shape[-1]).to("cpu", torch.float64).numpy()
                         for x in (q, qd, tau))  # fmt: skip
        model = self.mujoco_model()
        applied = tau_ - self._sign_coulomb(qd_)
        out = np.zeros_like(qd_)
        for i in range(q_.shape[0]):
            self._data.qpos[:], self._data.qvel[:] = q_[i], qd_[i]
            self._data.qfrc_applied[:] = applied[i]
            mujoco.mj_forward(model, self._data)
            out[i] = self._data.qacc
        self._data.qfrc_applied[:] = 0.0
        return torch.as_tensor(out).to(qd).reshape(*lead, self.nv)

    def friction_torque(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        """The joints' friction in the predicted torque (viscous and Coulomb): (..., nv)."""
        with_friction = self.predict_torque(q, qd, qdd)
        saved = {k: getattr(self, k).clone() for k in ("viscous", "coulomb")}
        try:
            for tensor in saved:
                getattr(self, tensor).zero_()
            return with_friction - self.predict_torque(q, qd, qdd)
        finally:
            for name, value in saved.items():
                getattr(self, name).copy_(value)

    def mass_matrix(self, q: Tensor) -> Tensor:
        """M(q) of the identified model, armature included: (..., nv, nv)."""
        model = self.mujoco_model()
        flat = q.detach().reshape(-1, q.shape[-1]).to("cpu", torch.float64).numpy()
        out = np.zeros((flat.shape[0], self.nv, self.nv))
        for i, qi in enumerate(flat):
            self._data.qpos[:] = qi
            mujoco.mj_forward(model, self._data)
            mujoco.mj_fullM(model, self._data, out[i])
        return torch.as_tensor(out).to(q).reshape(*q.shape[:-1], self.nv, self.nv)

    def consistent(self) -> bool:
        """Whether every body's identified inertials are physically consistent."""
        return all(physically_consistent(pi) for pi in self.inertials.cpu().numpy())

    def identified(self) -> dict[str, object]:
        """The numbers for a summary: each moving body's mass and centre of mass, each DoF's
        friction and armature, and whether every body is physically consistent."""
        model = self.mujoco_model()
        names = [model.body(b).name or f"body{b}" for b in self.bodies]
        return {
            "physically_consistent": self.consistent(),
            "friction_law": self.friction_law,
            "mass": dict(zip(names, model.body_mass[self.bodies].tolist(), strict=True)),
            "com": dict(zip(names, model.body_ipos[self.bodies].tolist(), strict=True)),
            **{k: getattr(self, k).tolist() for k in ("viscous", "coulomb", "armature")},
        }


def _with_inertials(
    model: mujoco.MjModel, bodies: list[int], inertials: np.ndarray
) -> mujoco.MjModel:
    out = _copy(model)
    for body, pi in zip(bodies, inertials, strict=True):
        set_inertial_parameters(out, body, pi)
    return out
