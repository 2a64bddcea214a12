"""MuJoCo's own rigid body beside the learned contact law: the contact model's instrument.

`RigidContactModel` takes M(q) and every non-contact generalized force (the actuators, the
joints' springs, damping and limits, gravity, Coriolis) from MuJoCo with contacts switched off,
and
the floor's force from a `ContactModel` stepped as a DeLaN steps it (semi-implicit Euler, the
contact implicit). Its only learnable numbers are the contact law's, so fitting it on data
answers whether the data identify the law, and scoring it in the fidelity suite whether the
law (at its start or fitted) is good enough to stand on. The joint limits' forces are MuJoCo's
at the step's start; MuJoCo runs per sample on the CPU, so it is slow to plan with.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch
from tensordict import TensorDictBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.models.base import LossOutput, RigidBody, WorldModel
from mbrl_delan.models.contact import ContactModel, JointLimits, implicit_acceleration
from mbrl_delan.models.inertial import rigid_body_at
from mbrl_delan.models.integrators import integrate
from mbrl_delan.systems.posarith import differentiate_pos
from mbrl_delan.systems.system import State, System


class RigidContactModel(WorldModel):
    """MuJoCo's rigid body (contacts off) + an implicit `ContactModel`, stepped by
    `substeps` semi-implicit Euler steps per control step, the joints' damping implicit as in
    MuJoCo's Euler; with `limits`, the joint limits are those (implicit, `JointLimits`)
    instead of MuJoCo's."""

    deterministic = True

    def __init__(
        self, system: System, contact: ContactModel, substeps: int = 2,
        limits: JointLimits | None = None,
    ) -> None:  # fmt: skip
        super().__init__()
        self.system, self.layout, self.substeps = system, system.layout, substeps
        self.contact, self.limits = contact, limits
        self.mj = system.mj_model()
        self.mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        if limits is not None:  # ours instead of MuJoCo's
            self.mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
        self._data = mujoco.MjData(self.mj)
        self.register_buffer("q_scale", torch.ones(system.nv, dtype=torch.float64))
        self.register_buffer("qd_scale", torch.ones(system.nv, dtype=torch.float64))

    def rigid_body(self, q: Tensor) -> RigidBody:
        """MuJoCo's own M, potential force at rest and B (`rigid_body_at`)."""
        flat = q.detach().to("cpu", torch.float64).reshape(-1, q.shape[-1]).numpy()
        mass, force = rigid_body_at(self.mj, flat)
        as_q = lambda x: torch.from_numpy(x).to(q).reshape(*q.shape[:-1], *x.shape[1:])  # noqa: E731
        return RigidBody(as_q(mass), as_q(force), self.system.actuation.to(q))

    def rigid_terms(self, q: Tensor, qd: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        """M (..., nv, nv) and the non-contact generalized force (..., nv) from MuJoCo (no
        gradient through them)."""
        lead, nv = q.shape[:-1], self.system.nv
        flat = [x.detach().to("cpu", torch.float64).reshape(-1, x.shape[-1]).numpy()
                for x in (q, qd, action)]  # fmt: skip
        mass = np.empty((flat[0].shape[0], nv, nv))
        force = np.empty((flat[0].shape[0], nv))
        data, model = self._data, self.mj
        for i in range(flat[0].shape[0]):
            data.qpos[:], data.qvel[:], data.ctrl[:] = flat[0][i], flat[1][i], flat[2][i]
            mujoco.mj_forward(model, data)
            mujoco.mj_fullM(model, data, mass[i])
            force[i] = data.qfrc_smooth + data.qfrc_constraint  # the limits' constraint force
        on = lambda x, *shape: torch.from_numpy(x).to(q).reshape(*lead, *shape)  # noqa: E731
        return on(mass, nv, nv), on(force, nv)

    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        h = self.system.control_dt / self.substeps

        damping = torch.from_numpy(self.mj.dof_damping.copy()).to(q)

        def accel(q_: Tensor, qd_: Tensor) -> Tensor:
            mass, force = self.rigid_terms(q_, qd_, action)
            mass = mass + torch.diag_embed(h * damping.expand_as(qd_))  # as MuJoCo's Euler
            parts = [self.contact.implicit_terms(q_, qd_, h)]
            if self.limits is not None:
                parts.append(self.limits.implicit_terms(q_, qd_, h))
            return implicit_acceleration(parts, qd_, h, mass, force)

        return integrate(self.layout, accel, q, qd, self.system.control_dt, "euler", self.substeps)

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        """The forward loss's per-DoF scales: the std of the one-step change."""
        q, q_next = data[keys.Q].to(torch.float64), data[keys.NEXT_Q].to(torch.float64)
        dq = differentiate_pos(self.layout, q, q_next, 1.0)
        dqd = data[keys.NEXT_QD].to(torch.float64) - data[keys.QD].to(torch.float64)
        self.q_scale.copy_(dq.std(0).clamp_min(1e-2 * float(dq.std(0).max())))
        self.qd_scale.copy_(dqd.std(0).clamp_min(1e-2 * float(dqd.std(0).max())))

    def loss(self, batch: TensorDictBase) -> LossOutput:
        """DeLaN's forward loss: the per-DoF normalised squared error of the next state."""
        pred = self.step(batch[keys.Q].double(), batch[keys.QD].double(), batch[keys.ACTION])
        e_q = differentiate_pos(self.layout, batch[keys.NEXT_Q].double(), pred.q, 1.0)
        e_qd = pred.qd - batch[keys.NEXT_QD].double()
        loss = (e_q / self.q_scale).pow(2).mean() + (e_qd / self.qd_scale).pow(2).mean()
        return LossOutput(loss, {"forward_mse": float(loss.detach())})
