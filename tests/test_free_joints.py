"""Ball and free joints: body-frame angular velocities need the Euler-Poincare term.

A free-floating rigid body whose centre of mass is off the body origin has a mass matrix
that depends on its orientation, so every term of the equations is exercised: with its exact
M(q) and V(q), DeLaN's equations must give MuJoCo's `qfrc_bias`; with networks, the explicit
jvp/vjp must equal autograd through `integrate_pos`.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
from torch import Tensor

from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.features import QFeatures, rotation_matrix, skew
from mbrl_delan.models.integrators import integrate
from mbrl_delan.models.lagrangian import LagrangianDynamics, MechanicsField, MechanicsJet
from mbrl_delan.models.structure import Structure, rotational_dofs
from mbrl_delan.systems.posarith import integrate_pos
from mbrl_delan.systems.system import FREE, HINGE, JointLayout, load_system

MASS, GRAVITY = 2.0, 9.81
OFFSET = torch.tensor([0.1, -0.2, 0.15], dtype=torch.float64)  # COM in the body frame
INERTIA = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)  # principal, about the COM

FREE_BODY = f"""
<mujoco>
  <option gravity="0 0 -{GRAVITY}"><flag contact="disable"/></option>
  <worldbody>
    <body name="b" pos="0 0 1">
      <freejoint/>
      <inertial pos="{" ".join(map(str, OFFSET.tolist()))}" mass="{MASS}"
                diaginertia="{" ".join(map(str, INERTIA.tolist()))}"/>
    </body>
  </worldbody>
</mujoco>
"""

MIXED = """
<mujoco>
  <option><flag contact="disable"/></option>
  <worldbody>
    <body pos="0 0 1"><freejoint/><geom size="0.1" mass="1"/>
      <body pos="0.2 0 0"><joint type="ball"/><geom size="0.05" pos="0.1 0 0" mass="0.5"/>
        <body pos="0.2 0 0"><joint type="hinge" axis="0 1 0" range="-1 1"/>
          <geom size="0.05" pos="0.1 0 0" mass="0.3"/></body>
        <body pos="0 0.2 0"><joint type="hinge" axis="0 0 1"/>
          <geom size="0.05" pos="0.1 0 0" mass="0.3"/></body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(autouse=True)
def float64():
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def system_of(xml: str, tmp_path):
    path = tmp_path / "model.xml"
    path.write_text(xml)
    return load_system(path)


def free_body_mass_matrix(q: Tensor) -> Tensor:
    """(..., 7) -> (..., 6, 6) for qvel = (world linear velocity of the origin, body omega)."""
    R = rotation_matrix(q[..., 3:7])
    r_x = skew(OFFSET).expand(R.shape)
    eye = torch.eye(3).expand(R.shape)
    top = torch.cat([MASS * eye, -MASS * R @ r_x], dim=-1)
    bottom = torch.cat(
        [
            MASS * r_x @ R.transpose(-1, -2),
            torch.diag(INERTIA) + MASS * r_x.transpose(-1, -2) @ r_x,
        ],
        dim=-1,
    )
    return torch.cat([top, bottom], dim=-2)


def free_body_potential(q: Tensor) -> Tensor:
    """m g (height of the COM): (..., 7) -> (...)."""
    R = rotation_matrix(q[..., 3:7])
    return MASS * GRAVITY * (q[..., 2] + (R @ OFFSET)[..., 2])


class ExactField(MechanicsField):
    """Closed-form L = chol(M) and V, differentiated through integrate_pos (velocity space)."""

    def __init__(self, layout, mass_matrix, potential) -> None:
        super().__init__()
        self.layout, self.mass_matrix, self.potential = layout, mass_matrix, potential

    def _at(self, q: Tensor, v: Tensor, eps: Tensor) -> tuple[Tensor, Tensor]:
        moved = integrate_pos(self.layout, q, v, eps)
        return torch.linalg.cholesky(self.mass_matrix(moved)), self.potential(moved)

    def jet(self, q: Tensor, qd: Tensor) -> MechanicsJet:
        zero = torch.zeros(q.shape[:-1] + (1,))
        (L, V), (L_dot, _) = torch.func.jvp(
            lambda e: self._at(q, qd, e), (zero,), (torch.ones_like(zero),)
        )
        _, vjp = torch.func.vjp(lambda d: self._at(q, d, 1.0), torch.zeros_like(qd))
        return MechanicsJet(L, L_dot, V, pullback=lambda d_L, d_V: vjp((d_L, d_V))[0])


def random_states(system, n: int, seed: int = 0) -> tuple[Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed)
    q0 = torch.tensor(system.mj_model().qpos0).expand(n, -1)
    q = integrate_pos(system.layout, q0, torch.randn(n, system.nv, generator=g), 1.0)
    return q, 2.0 * torch.randn(n, system.nv, generator=g)


def test_free_body_equations_match_mujoco(tmp_path) -> None:
    system = system_of(FREE_BODY, tmp_path)
    field = ExactField(system.layout, free_body_mass_matrix, free_body_potential)
    dynamics = LagrangianDynamics(field, None, system.actuation, rotational_dofs(system.layout))
    assert_equations_are_mujocos(dynamics, system, *random_states(system, 16))


def assert_equations_are_mujocos(dynamics, system, q: Tensor, qd: Tensor) -> None:
    """M is mj_fullM's, c + g is qfrc_bias and the forward dynamics of a random generalized
    force is MuJoCo's qacc, state by state."""
    terms, model = dynamics.terms(q, qd), system.mj_model()
    data, full = mujoco.MjData(model), np.zeros((model.nv, model.nv))
    tau = torch.randn(q.shape[0], model.nv, generator=torch.Generator().manual_seed(3))
    qdd = dynamics.forward_dynamics(q, qd, tau)
    for i in range(q.shape[0]):
        data.qpos[:], data.qvel[:] = q[i].numpy(), qd[i].numpy()
        data.qfrc_applied[:] = tau[i].numpy()
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, full)
        np.testing.assert_allclose(terms.mass_matrix[i].detach().numpy(), full, atol=1e-12)
        bias = (terms.coriolis + terms.gravity)[i].detach().numpy()
        np.testing.assert_allclose(bias, data.qfrc_bias, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(qdd[i].detach().numpy(), data.qacc, rtol=1e-6, atol=1e-9)


def test_without_euler_poincare_the_free_body_is_wrong(tmp_path) -> None:
    """Guards the test above: plain Euler-Lagrange misses omega x (M qd)_omega."""
    system = system_of(FREE_BODY, tmp_path)
    field = ExactField(system.layout, free_body_mass_matrix, free_body_potential)
    plain = LagrangianDynamics(field, None, system.actuation)  # no rotational dofs
    q, qd = random_states(system, 4)
    model, data = system.mj_model(), None
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = q[0].numpy(), qd[0].numpy()
    mujoco.mj_forward(model, data)
    terms = plain.terms(q, qd)
    bias = (terms.coriolis + terms.gravity)[0].detach().numpy()
    assert np.abs(bias - data.qfrc_bias).max() > 1e-2


@pytest.mark.parametrize("yaw_invariant", [False, True])
def test_features_jvp_vjp_equal_autograd_through_integrate_pos(tmp_path, yaw_invariant) -> None:
    system = system_of(MIXED, tmp_path)
    features = QFeatures(system.layout, yaw_invariant=yaw_invariant)
    q, v = random_states(system, 8, seed=1)
    zero = torch.zeros(q.shape[:-1] + (1,))
    _, expected = torch.func.jvp(
        lambda e: features(integrate_pos(system.layout, q, v, e)), (zero,), (torch.ones_like(zero),)
    )
    torch.testing.assert_close(features.jvp(q, v), expected)
    cot = torch.randn(8, features.n_features)
    _, vjp = torch.func.vjp(
        lambda d: features(integrate_pos(system.layout, q, d, 1.0)), torch.zeros_like(v)
    )
    torch.testing.assert_close(features.vjp(q, cot), vjp(cot)[0])
    root = 3 if yaw_invariant else 9  # the root's tilt e_z^T R, or all of R
    assert features.n_features == 1 + root + 9 + 1 + 2  # z, root, R_ball, limited hinge, sin/cos


@pytest.mark.parametrize("yaw_invariant", [False, True])
def test_network_coriolis_equals_autograd_on_mixed_joints(tmp_path, yaw_invariant) -> None:
    """The network's explicit c(q, qd) equals Mdot qd - 1/2 grad(qd^T M qd) + EP by autograd
    (with `yaw_invariant`, through the root's rotation of L too)."""
    system = system_of(MIXED, tmp_path)
    torch.manual_seed(0)
    model = DeLaN(
        system.layout, system.actuation, 0.01, Structure(hidden=32, yaw_invariant=yaw_invariant)
    ).double()
    q, qd = random_states(system, 4, seed=2)
    terms = model.terms(q, qd)
    layout, dyn = system.layout, model.dynamics

    def mass_at(qi, d):
        moved = integrate_pos(layout, qi, d, 1.0)
        return model.terms(moved, torch.zeros_like(d)).mass_matrix

    for i in range(q.shape[0]):
        zero = torch.zeros(system.nv)
        dM = torch.autograd.functional.jacobian(lambda d, qi=q[i]: mass_at(qi, d), zero)  # (n,n,n)
        m_dot_qd = (dM @ qd[i]) @ qd[i]
        grad = torch.einsum("i,ijk,j->k", qd[i], dM, qd[i])
        M = terms.mass_matrix[i]
        ep = torch.zeros(system.nv)
        for idx in dyn.rotational_dofs:
            ep[idx] = torch.linalg.cross(qd[i, idx], (M @ qd[i])[idx])
        torch.testing.assert_close(
            terms.coriolis[i], m_dot_qd - 0.5 * grad + ep, rtol=1e-7, atol=1e-9
        )


def test_free_body_energy_conserved_without_gravity_rk4(tmp_path) -> None:
    """A torque-free tumbling body keeps its kinetic energy under RK4 (the model's code path)."""
    system = system_of(FREE_BODY.replace(f'gravity="0 0 -{GRAVITY}"', 'gravity="0 0 0"'), tmp_path)
    field = ExactField(system.layout, free_body_mass_matrix, lambda q: torch.zeros(q.shape[:-1]))
    dynamics = LagrangianDynamics(field, None, system.actuation, rotational_dofs(system.layout))
    q, qd = random_states(system, 4, seed=3)
    zero = torch.zeros_like(qd)
    e0 = dynamics.terms(q, qd).kinetic_energy
    for _ in range(50):  # 0.2 s; RK4's own drift: 1.7e-7
        s = integrate(
            system.layout, lambda a, b: dynamics.forward_dynamics(a, b, zero), q, qd, 4e-3
        )
        q, qd = s.q.detach(), s.qd.detach()
    drift = (dynamics.terms(q, qd).kinetic_energy - e0).abs() / e0
    assert drift.max() < 1e-6


def test_position_arithmetic_in_inference_mode_then_autograd() -> None:
    """The first integrate_pos call of a layout may come from planning (inference mode);
    fitting later differentiates through it."""
    layout = JointLayout(types=(FREE, HINGE), qpos_adr=(0, 7), dof_adr=(0, 6), limited=(False,) * 2)
    q = torch.cat([torch.tensor([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]), torch.zeros(1)])
    with torch.inference_mode():
        integrate_pos(layout, q, torch.ones(7), 0.1)
    qd = torch.ones(7, requires_grad=True)
    integrate_pos(layout, q, qd, 0.1).sum().backward()
    assert qd.grad is not None and torch.isfinite(qd.grad).all()


def test_a_layout_out_of_mujocos_order_is_refused() -> None:
    layout = JointLayout(types=(HINGE, FREE), qpos_adr=(7, 0), dof_adr=(6, 0), limited=(False,) * 2)
    with pytest.raises(ValueError, match="out of MuJoCo's order"):
        integrate_pos(layout, torch.zeros(8), torch.zeros(7), 0.1)


def test_known_armature_adds_to_m_and_matches_mujoco(tmp_path) -> None:
    """MuJoCo adds a joint's armature to M's diagonal; DeLaN's `armature` does the same on
    top of the rigid body's M, and the equations still give MuJoCo's bias forces."""
    armature = 0.05
    xml = FREE_BODY.replace("<freejoint/>", f'<joint type="free" armature="{armature}"/>')
    system = system_of(xml, tmp_path)
    field = ExactField(system.layout, free_body_mass_matrix, free_body_potential)
    dynamics = LagrangianDynamics(
        field, None, system.actuation, rotational_dofs(system.layout),
        armature=torch.tensor(system.mj_model().dof_armature),
    )  # fmt: skip
    assert_equations_are_mujocos(dynamics, system, *random_states(system, 8))
