"""The structured contact model: its point Jacobians against MuJoCo's `mj_jac`, and the laws
it promises (no force without contact, a non-negative normal force, friction inside its cone,
no energy gained in a passive drop)."""

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan.config import build_model, compose_train_config
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.models.contact import ContactModel, ContactPoints
from mbrl_delan.systems.external import humanoid_v5_xml
from mbrl_delan.systems.posarith import integrate_pos
from mbrl_delan.systems.system import load_system

BALL_XML = """
<mujoco>
  <option gravity="0 0 -9.81"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body pos="0 0 0.5">
      <freejoint/>
      <geom type="sphere" size="0.1" mass="1"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def humanoid() -> tuple[mujoco.MjModel, ContactModel]:
    model = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    return model, ContactModel.from_mujoco(model).double()


def random_state(model: mujoco.MjModel, n: int, height: float, seed: int) -> tuple:
    """n states near qpos0 with the root at `height` m, random joint angles and velocities."""
    g = torch.Generator().manual_seed(seed)
    q = torch.from_numpy(model.qpos0.copy()).repeat(n, 1)
    q[:, 7:] += 0.5 * (2 * torch.rand(n, model.nq - 7, generator=g, dtype=torch.float64) - 1)
    q[:, 3:7] += 0.2 * torch.randn(n, 4, generator=g, dtype=torch.float64)
    q[:, 3:7] /= q[:, 3:7].norm(dim=-1, keepdim=True)
    q[:, 2] = height
    qd = 2.0 * torch.randn(n, model.nv, generator=g, dtype=torch.float64)
    return q, qd


def test_points_and_jacobians_match_mujoco(humanoid) -> None:
    model, contact = humanoid
    q, _ = random_state(model, 4, 1.0, seed=0)
    position, jacobian = contact.kinematics(q)  # (4, P, 3), (4, P, 3, nv)
    data = mujoco.MjData(model)
    for i in range(q.shape[0]):
        data.qpos[:] = q[i].numpy()
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        for p, body in enumerate(contact.points.body):
            offset = np.asarray(contact.points.offset[p])
            expected = data.xpos[body] + data.xmat[body].reshape(3, 3) @ offset
            np.testing.assert_allclose(position[i, p].numpy(), expected, atol=1e-12)
            jacp = np.zeros((3, model.nv))
            mujoco.mj_jac(model, data, jacp, None, expected, body)
            np.testing.assert_allclose(jacobian[i, p].numpy(), jacp, atol=1e-12)


def test_points_are_the_geoms_that_touch_the_floor(humanoid) -> None:
    model, contact = humanoid
    feet = [
        mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in ("right_foot", "left_foot")
    ]
    assert all(f in contact.points.body for f in feet)
    assert contact.points.floor == 0.0
    mass = model.body_mass.sum()
    assert contact.points.weight == pytest.approx(9.81 * mass, rel=1e-6)


def test_no_force_without_contact(humanoid) -> None:
    model, contact = humanoid
    q, qd = random_state(model, 16, 3.0, seed=1)  # every point at least 1 m above the floor
    assert torch.equal(contact(q, qd), torch.zeros_like(qd))


def test_normal_force_non_negative_and_friction_inside_the_cone(humanoid) -> None:
    model, contact = humanoid
    q, qd = random_state(model, 64, 0.9, seed=2)  # feet, legs and hands through the floor
    state = contact.contact_state(q, qd)
    normal, tangential = state.force[..., 2], state.force[..., :2].norm(dim=-1)
    depth = contact.points.floor + contact.radius - state.position[..., 2]
    assert bool((depth > 0).any()) and bool((depth <= 0).any())
    assert bool((normal >= 0).all())
    assert bool((normal[depth <= 0] == 0).all()) and bool((normal[depth > 0] > 0).any())
    mu = float(contact.law()["friction"].detach())
    assert bool((tangential <= mu * normal * (1 + 1e-12)).all())
    # friction opposes the slip
    slip = (state.force[..., :2] * state.velocity[..., :2]).sum(-1)
    assert bool((slip <= 0).all())


def test_normal_force_grows_with_depth_and_resists_approach(humanoid) -> None:
    _, contact = humanoid
    p = len(contact.points.body)
    radius = contact.radius
    depths = torch.tensor([0.001, 0.005, 0.01, 0.02], dtype=torch.float64)
    position = torch.zeros(4, p, 3, dtype=torch.float64)
    position[..., 2] = radius - depths[:, None]
    still = contact.point_forces(position, torch.zeros_like(position))[..., 2]
    assert bool((still.diff(dim=0) > 0).all())
    moving = torch.zeros_like(position)
    moving[..., 2] = -0.3
    approaching = contact.point_forces(position, moving)[..., 2]
    leaving = contact.point_forces(position, -moving)[..., 2]
    assert bool((approaching > still).all()) and bool((leaving < still).all())


def test_a_passive_drop_gains_no_energy(tmp_path) -> None:
    """A ball dropped with spin and sideways speed onto the floor: its mechanical energy
    (kinetic with MuJoCo's mass matrix, plus m g z) never rises above the start, and the
    bounce and the friction take some of it."""
    path = tmp_path / "ball.xml"
    path.write_text(BALL_XML)
    model = mujoco.MjModel.from_xml_string(BALL_XML)
    system = load_system(path)
    contact = ContactModel.from_mujoco(model).double()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    M = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, M)
    mass_matrix = torch.from_numpy(M)  # constant for one free body
    weight = float(model.body_mass[1]) * 9.81
    gravity = torch.tensor([0, 0, -weight, 0, 0, 0], dtype=torch.float64)

    def energy(q: torch.Tensor, qd: torch.Tensor) -> float:
        return float(0.5 * qd @ mass_matrix @ qd + weight * q[2])

    q = torch.from_numpy(model.qpos0.copy())
    qd = torch.tensor([1.0, 0.0, 0.0, 0.0, 5.0, 0.0], dtype=torch.float64)
    start, dt, touched = energy(q, qd), 2e-4, False
    energies = []
    with torch.no_grad():
        for _ in range(int(0.6 / dt)):  # semi-implicit Euler; the bounce is at 0.29 s
            force = contact(q, qd)
            touched |= bool(force.abs().sum() > 0)
            qd = qd + dt * torch.linalg.solve(mass_matrix, gravity + force)
            q = integrate_pos(system.layout, q, qd, dt)
            energies.append(energy(q, qd))
    assert touched
    assert max(energies) <= start * (1 + 1e-3)
    assert energies[-1] < 0.95 * start


def test_delan_adds_the_contact_force() -> None:
    cfg = compose_train_config(["env=humanoid_stand", "model=delan", "env.model_contacts=true"])
    parts = make_env_parts("humanoid_stand", None, 10)
    model = build_model(cfg.model, parts.system).double()
    assert isinstance(model.contact, ContactModel)
    q, qd = random_state(parts.system.mj_model(), 8, 1.0, seed=3)
    action = torch.rand(8, parts.system.nu, dtype=torch.float64)
    own = model.dynamics.generalized_force(action) + model.contact(q, qd)
    residual = model.tau_scale * model.residual(q, qd, action, model.velocity_limit / 3.0)
    torch.testing.assert_close(model.applied_force(q, qd, action), own + residual)
    assert isinstance(model.contact.points, ContactPoints)


def test_the_contact_law_learns_through_a_delan_step() -> None:
    """A forward step from states through the floor gives the law's constants a finite,
    non-zero gradient (they are fitted with the rest of the model)."""
    cfg = compose_train_config(["env=humanoid_stand", "model=delan", "env.model_contacts=true"])
    parts = make_env_parts("humanoid_stand", None, 10)
    model = build_model(cfg.model, parts.system)
    q, qd = random_state(parts.system.mj_model(), 8, 0.95, seed=4)
    nxt = model.step(q.float(), qd.float(), torch.zeros(8, parts.system.nu))
    assert bool(torch.isfinite(nxt.q).all() and torch.isfinite(nxt.qd).all())
    nxt.qd.square().sum().backward()
    for name, param in model.contact.named_parameters():
        assert param.grad is not None and bool(torch.isfinite(param.grad)), name
        assert float(param.grad.abs()) > 0, name
