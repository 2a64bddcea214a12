"""DeLaN's equations on closed-form M(q) and V(q) reproduce MuJoCo's own dynamics.

The `MechanicsField` here is exact (L = chol(M) of the textbook mass matrix, V the textbook
potential, derivatives by torch.func), so any mismatch with MuJoCo's `qfrc_bias` and
`mj_inverse` would be an error in the Lagrangian equations (Coriolis assembly, signs, pullback).
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np
import pytest
import torch
from closed_form import (
    arm2_gravity,
    arm2_mass_matrix,
    arm2_potential,
    pendulum_mass_matrix,
    pendulum_potential,
)
from torch import Tensor

from mbrl_delan.models.lagrangian import (
    Dissipation,
    LagrangianDynamics,
    MechanicsField,
    MechanicsJet,
)
from mbrl_delan.systems.system import load_system


class ExactField(MechanicsField):
    def __init__(
        self, mass_matrix: Callable[[Tensor], Tensor], potential: Callable[[Tensor], Tensor]
    ):
        super().__init__()
        self.mass_matrix, self.potential = mass_matrix, potential

    def _cholesky(self, q: Tensor) -> Tensor:
        return torch.linalg.cholesky(self.mass_matrix(q))

    def jet(self, q: Tensor, qd: Tensor) -> MechanicsJet:
        L, L_dot = torch.func.jvp(self._cholesky, (q,), (qd,))
        both = lambda x: (self._cholesky(x), self.potential(x))  # noqa: E731
        (_, V), vjp = torch.func.vjp(both, q)
        return MechanicsJet(
            L=L, L_dot=L_dot, potential_energy=V, pullback=lambda d_L, d_V: vjp((d_L, d_V))[0]
        )


SYSTEMS = {
    "pendulum": (pendulum_mass_matrix, pendulum_potential),
    "arm2": (arm2_mass_matrix, arm2_potential),
}


def exact_dynamics(name: str) -> tuple[LagrangianDynamics, mujoco.MjModel]:
    system = load_system(name)
    dissipation = Dissipation(system.nv, coulomb=False).double()
    with torch.no_grad():  # softplus^-1 of the MJCF damping: exactly MuJoCo's viscous term
        dissipation.raw_viscous.copy_(torch.log(torch.expm1(system.damping)))
    dynamics = LagrangianDynamics(ExactField(*SYSTEMS[name]), dissipation, system.actuation)
    return dynamics, system.mj_model()


def random_states(nv: int, n: int = 32) -> tuple[Tensor, Tensor, Tensor]:
    g = torch.Generator().manual_seed(7)
    return tuple(3.0 * torch.randn(n, nv, generator=g, dtype=torch.float64) for _ in range(3))


@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_bias_force_equals_mujoco_qfrc_bias(name: str) -> None:
    dynamics, model = exact_dynamics(name)
    data = mujoco.MjData(model)
    q, qd, _ = random_states(model.nv)
    terms = dynamics.terms(q, qd)
    for i in range(q.shape[0]):
        data.qpos[:], data.qvel[:] = q[i].numpy(), qd[i].numpy()
        mujoco.mj_forward(model, data)
        full = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, full)
        np.testing.assert_allclose(terms.mass_matrix[i].numpy(), full, rtol=1e-10, atol=1e-12)
        c_plus_g = (terms.coriolis + terms.gravity)[i].numpy()
        np.testing.assert_allclose(c_plus_g, data.qfrc_bias, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_inverse_dynamics_equals_mj_inverse(name: str) -> None:
    """tau = M qdd + c + g + D qd equals MuJoCo's qfrc_inverse (damping included)."""
    dynamics, model = exact_dynamics(name)
    data = mujoco.MjData(model)
    q, qd, qdd = random_states(model.nv)
    with torch.no_grad():
        tau = dynamics.inverse_dynamics(q, qd, qdd)
    for i in range(q.shape[0]):
        data.qpos[:], data.qvel[:], data.qacc[:] = q[i].numpy(), qd[i].numpy(), qdd[i].numpy()
        mujoco.mj_inverse(model, data)
        np.testing.assert_allclose(tau[i].numpy(), data.qfrc_inverse, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_forward_dynamics_equals_mujoco_qacc(name: str) -> None:
    """qdd = M^-1 (B a - c - g - d) by Cholesky solves equals MuJoCo's forward dynamics."""
    dynamics, model = exact_dynamics(name)
    data = mujoco.MjData(model)
    q, qd, _ = random_states(model.nv)
    action = torch.rand(q.shape[0], model.nu, dtype=torch.float64) * 2 - 1
    with torch.no_grad():
        qdd = dynamics.forward_dynamics(q, qd, dynamics.generalized_force(action))
    for i in range(q.shape[0]):
        data.qpos[:], data.qvel[:], data.ctrl[:] = q[i].numpy(), qd[i].numpy(), action[i].numpy()
        mujoco.mj_forward(model, data)
        np.testing.assert_allclose(qdd[i].numpy(), data.qacc, rtol=1e-8, atol=1e-9)


def test_closed_form_gravity_is_the_potential_gradient() -> None:
    """The closed-form arm's g(q) equals dV/dq of its potential (guards the test's own inputs)."""
    q, _, _ = random_states(2)
    grad = torch.func.vmap(torch.func.grad(arm2_potential))(q)
    torch.testing.assert_close(grad, arm2_gravity(q))


def _frictional_arm2(lead: bool) -> tuple[LagrangianDynamics, mujoco.MjModel]:
    """arm2 with MuJoCo's ``frictionloss`` 0.5 N m on both joints, and the exact DeLaN with
    Coulomb friction F = 0.5 (v_c 1e-3) and, with `lead`, the lead l = 1 / b of MuJoCo's
    soft friction constraint."""
    from mbrl_delan.models.rigid_body import friction_damping

    system = load_system("arm2")
    model = system.mj_model()
    model.dof_frictionloss[:] = 0.5
    dissipation = Dissipation(system.nv, coulomb=True, coulomb_velocity=1e-3, lead=lead).double()
    inverse_softplus = lambda x: torch.log(torch.expm1(torch.as_tensor(x)))  # noqa: E731
    with torch.no_grad():
        dissipation.raw_viscous.copy_(inverse_softplus(system.damping))
        dissipation.raw_coulomb.copy_(inverse_softplus(torch.full((2,), 0.5)))
        if lead:
            unit = Dissipation.LEAD_UNIT
            dissipation.raw_lead.copy_(inverse_softplus(1.0 / friction_damping(model) / unit))
    dynamics = LagrangianDynamics(ExactField(*SYSTEMS["arm2"]), dissipation, system.actuation)
    return dynamics, model


def test_a_coulomb_lead_gives_mujocos_frictionloss() -> None:
    """MuJoCo's soft ``frictionloss`` opposes qdd + b qd, not qd: with the lead l = 1 / b the
    DeLaN's inverse dynamics is `mj_inverse`'s wherever the constraint is saturated; without
    it, the states whose qd and qdd + b qd point apart are 2 F off."""
    from mbrl_delan.models.rigid_body import friction_damping

    q, qd, qdd = random_states(2, 1024)
    qd = 0.01 * qd  # slow enough that qdd decides the friction's direction in some states
    model = _frictional_arm2(lead=True)[1]
    argument = qdd + torch.from_numpy(friction_damping(model)) * qd
    saturated = argument.abs() > 5.0  # (N, 2): the constraint's force is +-F there
    data = mujoco.MjData(model)
    reference = []
    for i in range(q.shape[0]):
        data.qpos[:], data.qvel[:], data.qacc[:] = q[i].numpy(), qd[i].numpy(), qdd[i].numpy()
        mujoco.mj_inverse(model, data)
        reference.append(data.qfrc_inverse.copy())
    reference = torch.from_numpy(np.stack(reference))[saturated]
    with torch.no_grad():
        led = _frictional_arm2(lead=True)[0].inverse_dynamics(q, qd, qdd)[saturated]
        plain = _frictional_arm2(lead=False)[0].inverse_dynamics(q, qd, qdd)[saturated]
    assert int(saturated.sum()) > 150
    torch.testing.assert_close(led, reference, rtol=0.0, atol=1e-6)
    apart = ((torch.sign(qd) != torch.sign(argument)) & (qd.abs() > 0.01))[saturated]
    assert int(apart.sum()) > 10
    torch.testing.assert_close((plain - reference)[apart].abs(), torch.ones_like(plain[apart]))


def test_forward_dynamics_takes_the_lead_linearly_implicit() -> None:
    """With a lead, forward dynamics solves (M + diag(dd/dqdd at 0)) qdd = tau - c - g - d(qd, 0)
    and `lead_inertia` is that derivative."""
    dynamics, _ = _frictional_arm2(lead=True)
    q, qd, tau = random_states(2)
    qd = 0.002 * qd  # inside the tanh's band, where the lead's inertia is large
    with torch.no_grad():
        qdd = dynamics.forward_dynamics(q, qd, tau)
        terms = dynamics.terms(q, qd)
    friction = dynamics.dissipation
    slope = torch.func.vmap(torch.func.jacrev(lambda v, a: friction(v, a), argnums=1))(
        qd, torch.zeros_like(qd)
    )  # (N, 2, 2)
    torch.testing.assert_close(torch.diagonal(slope, dim1=-2, dim2=-1), friction.lead_inertia(qd))
    lhs = (terms.mass_matrix + slope) @ qdd.unsqueeze(-1)
    rhs = tau - terms.coriolis - terms.gravity - terms.dissipation
    torch.testing.assert_close(lhs.squeeze(-1), rhs, rtol=1e-9, atol=1e-9)


def _fit_coulomb_width(qd_noise: float, steps: int = 400) -> Tensor:
    """A learned-width Coulomb term (F known) fitted to tau = F sign(qd) seen through
    velocities with Gaussian noise of std `qd_noise`; its width per DoF after the fit."""
    g = torch.Generator().manual_seed(3)
    qd = 0.2 * torch.randn(4096, 2, generator=g, dtype=torch.float64)
    tau = 0.5 * torch.sign(qd)
    seen = qd + qd_noise * torch.randn(qd.shape, generator=g, dtype=torch.float64)
    dissipation = Dissipation(2, coulomb=True, coulomb_velocity=0.01, learn_velocity=True)
    dissipation = dissipation.double()
    with torch.no_grad():
        dissipation.raw_viscous.fill_(-30.0)  # no viscous friction
        dissipation.raw_coulomb.copy_(torch.log(torch.expm1(torch.tensor(0.5))))
    optimizer = torch.optim.Adam([dissipation.raw_velocity], lr=0.05)
    for _ in range(steps):
        optimizer.zero_grad()
        (dissipation(seen) - tau).square().mean().backward()
        optimizer.step()
    return dissipation.velocity.detach()


def test_a_learned_coulomb_width_follows_the_velocities_noise() -> None:
    """The width starts at `coulomb_velocity` (F tanh(qd / v_c) as with it fixed); fitted to
    F sign(qd), exact velocities narrow it below its start, and velocities with noise sigma
    widen it to the scale of sigma: E[sign(qd) | qd + e] = erf(.) is best matched by a tanh
    of width about 1.2 sigma for qd spread much wider than sigma."""
    fixed = Dissipation(2, coulomb=True, coulomb_velocity=0.01)
    learned = Dissipation(2, coulomb=True, coulomb_velocity=0.01, learn_velocity=True)
    learned.load_state_dict(fixed.state_dict(), strict=False)
    qd = torch.linspace(-0.05, 0.05, 11)[:, None].expand(11, 2)
    torch.testing.assert_close(learned(qd), fixed(qd))
    assert (_fit_coulomb_width(0.0) < 0.005).all()
    sigma = 0.02
    width = _fit_coulomb_width(sigma)
    assert ((width > 0.7 * sigma) & (width < 2.0 * sigma)).all(), width
