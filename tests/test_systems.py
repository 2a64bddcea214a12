"""Systems: torch position arithmetic against MuJoCo, actuation matrices, loading errors."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan.systems.external import humanoid_cmu_xml, humanoid_v5_xml
from mbrl_delan.systems.posarith import differentiate_pos, integrate_pos
from mbrl_delan.systems.system import JointLayout, actuation_matrix, asset_path, load_system
from mbrl_delan.tasks.acrobot import ACROBOT_GEAR
from mbrl_delan.tasks.arm_reach import ARM2_GEARS, ARM3_GEARS
from mbrl_delan.tasks.cartpole import CART_GEAR
from mbrl_delan.tasks.pendulum import PENDULUM_GEAR

# free root, ball, hinge and slide joints in one tree (qpos layout: 7 + 4 + 1 + 4 + 1 = 17)
MIXED_XML = """
<mujoco>
  <option><flag contact="disable" gravity="disable"/></option>
  <worldbody>
    <body name="root">
      <freejoint/>
      <inertial pos="0 0 0" mass="1" diaginertia="0.1 0.2 0.3"/>
      <body name="b1" pos="0 0 -0.3">
        <joint type="ball"/>
        <inertial pos="0 0 -0.1" mass="0.5" diaginertia="0.01 0.02 0.03"/>
        <body name="b2" pos="0 0 -0.2">
          <joint type="hinge" axis="0 1 0"/>
          <inertial pos="0 0 -0.1" mass="0.3" diaginertia="0.01 0.01 0.01"/>
          <body name="b3" pos="0 0 -0.2">
            <joint type="ball"/>
            <inertial pos="0 0 -0.1" mass="0.2" diaginertia="0.01 0.01 0.01"/>
            <body name="b4" pos="0 0 -0.2">
              <joint type="slide" axis="1 0 0"/>
              <inertial pos="0 0 0" mass="0.1" diaginertia="0.01 0.01 0.01"/>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def mixed() -> tuple[mujoco.MjModel, JointLayout]:
    model = mujoco.MjModel.from_xml_string(MIXED_XML)
    layout = JointLayout(
        types=tuple(int(t) for t in model.jnt_type),
        qpos_adr=tuple(int(a) for a in model.jnt_qposadr),
        dof_adr=tuple(int(a) for a in model.jnt_dofadr),
        limited=tuple(bool(x) for x in model.jnt_limited),
    )
    return model, layout


def random_q(model: mujoco.MjModel, rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, nq) positions with random, not normalised quaternions of either sign."""
    q = rng.normal(size=(n, model.nq))
    for j in range(model.njnt):
        free = model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
        if free or model.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            start = model.jnt_qposadr[j] + (3 if free else 0)
            quat = q[:, start : start + 4]
            q[:, start : start + 4] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
            q[:, start : start + 4] *= rng.uniform(0.5, 2.0, size=(n, 1))
    return q


def mj_integrate(model: mujoco.MjModel, q: np.ndarray, v: np.ndarray, dt: float) -> np.ndarray:
    out = np.array(q, dtype=np.float64)
    for row, vel in zip(out, v, strict=True):
        mujoco.mj_integratePos(model, row, vel, dt)
    return out


def mj_difference(model: mujoco.MjModel, q1: np.ndarray, q2: np.ndarray, dt: float) -> np.ndarray:
    out = np.zeros((q1.shape[0], model.nv))
    for row, a, b in zip(out, q1, q2, strict=True):
        mujoco.mj_differentiatePos(model, row, dt, a, b)
    return out


def as_grid(x: np.ndarray) -> torch.Tensor:
    """(64, n) -> (8, 8, n): two leading batch dims."""
    return torch.from_numpy(x).view(8, 8, -1)


@pytest.mark.parametrize("scale", [1e-3, 1.0, 3.0])
def test_integrate_pos_matches_mujoco(mixed: tuple, scale: float) -> None:
    model, layout = mixed
    rng = np.random.default_rng(0)
    q = random_q(model, rng, 64)
    v = scale * rng.normal(size=(64, model.nv))
    v[:4] = 0.0  # zero rotation: identity quaternion path
    dt = 0.37
    expected = mj_integrate(model, q, v, dt)
    got = integrate_pos(layout, as_grid(q), as_grid(v), dt)
    assert got.shape == (8, 8, model.nq)
    np.testing.assert_allclose(got.reshape(64, -1).numpy(), expected, atol=1e-10, rtol=0)


@pytest.mark.parametrize("scale", [1e-6, 0.1, 10.0])
def test_differentiate_pos_matches_mujoco(mixed: tuple, scale: float) -> None:
    model, layout = mixed
    rng = np.random.default_rng(1)
    q1 = random_q(model, rng, 64)
    # q2 near q1 (small scale) up to unrelated orientations (large scale, angles near pi)
    q2 = mj_integrate(model, q1, scale * rng.normal(size=(64, model.nv)), 1.0)
    q2[:8] = random_q(model, rng, 8)
    q2[8:12] = q1[8:12]  # identical positions: zero velocity
    q2[12:16] = -q1[12:16]  # negated quaternions are the same orientation
    dt = 0.05
    expected = mj_difference(model, q1, q2, dt)
    got = differentiate_pos(layout, as_grid(q1), as_grid(q2), dt)
    assert got.shape == (8, 8, model.nv)
    np.testing.assert_allclose(got.reshape(64, -1).numpy(), expected, atol=1e-10, rtol=0)


def test_round_trip(mixed: tuple) -> None:
    model, layout = mixed
    rng = np.random.default_rng(2)
    q = torch.from_numpy(random_q(model, rng, 256))
    v = torch.from_numpy(rng.normal(size=(256, model.nv)))  # rotations below pi for dt = 0.3
    dt = torch.full((256, 1), 0.3, dtype=torch.float64)  # a tensor dt broadcasts too
    back = differentiate_pos(layout, q, integrate_pos(layout, q, v, dt), dt)
    torch.testing.assert_close(back, v, atol=1e-10, rtol=0)


def test_gradients_finite_at_zero_velocity(mixed: tuple) -> None:
    model, layout = mixed
    q = torch.from_numpy(random_q(model, np.random.default_rng(3), 4)).requires_grad_(True)
    v = torch.zeros(4, model.nv, dtype=torch.float64, requires_grad=True)
    q2 = integrate_pos(layout, q, v, 0.1)
    diff = differentiate_pos(layout, q, q2, 0.1)
    diff.sum().backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(v.grad).all()
    # d(differentiate(q, integrate(q, v)))/dv = I: the summed gradient is 1 per dof
    torch.testing.assert_close(v.grad, torch.ones_like(v), atol=1e-10, rtol=0)


def test_scalar_layouts_match_mujoco() -> None:
    model = mujoco.MjModel.from_xml_path(str(asset_path("cartpole")))
    system = load_system("cartpole")
    rng = np.random.default_rng(4)
    q, v = rng.normal(size=(16, 2)), rng.normal(size=(16, 2))
    got = integrate_pos(system.layout, torch.from_numpy(q), torch.from_numpy(v), 0.2)
    np.testing.assert_allclose(got.numpy(), mj_integrate(model, q, v, 0.2), atol=1e-12)
    back = differentiate_pos(system.layout, torch.from_numpy(q), got, 0.2)
    np.testing.assert_allclose(back.numpy(), v, atol=1e-12)


EXPECTED_B = {
    "pendulum": [[PENDULUM_GEAR]],
    "cartpole": [[CART_GEAR], [0.0]],  # only the cart is actuated
    "acrobot": [[0.0], [ACROBOT_GEAR]],  # only the elbow is actuated
    "arm2": np.diag(ARM2_GEARS),
    "arm3": np.diag(ARM3_GEARS),
}


@pytest.mark.parametrize("name", sorted(EXPECTED_B))
def test_actuation_matrix_is_gear_placement(name: str) -> None:
    system = load_system(name)
    np.testing.assert_allclose(system.actuation.numpy(), np.asarray(EXPECTED_B[name]), atol=1e-12)
    # and the same read generically from the model's transmissions
    model = system.mj_model()
    placed = np.zeros((model.nv, model.nu))
    for i in range(model.nu):
        placed[model.jnt_dofadr[model.actuator_trnid[i, 0]], i] = model.actuator_gear[i, 0]
    np.testing.assert_allclose(actuation_matrix(model), placed, atol=1e-12)


@pytest.mark.parametrize("name", ["humanoid_v5", "humanoid_cmu", "panda", "ur5e"])
def test_actuation_matrix_gives_mujocos_actuator_force(name: str) -> None:
    """B ctrl is MuJoCo's qfrc_actuator for controls anywhere in the range, also where the
    range is narrower than 1 (Humanoid-v5's +-0.4, where ctrl = 1 is clamped)."""
    if name == "humanoid_cmu":
        pytest.importorskip("dm_control")
    xml = {"humanoid_v5": humanoid_v5_xml, "humanoid_cmu": humanoid_cmu_xml}.get(name)
    system = load_system(name if xml is None else xml())
    model = system.mj_model()
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    for _ in range(3):
        data.ctrl[:] = rng.uniform(*model.actuator_ctrlrange.T)
        mujoco.mj_forward(model, data)
        tau = system.actuation.numpy() @ data.ctrl
        np.testing.assert_allclose(tau, data.qfrc_actuator, atol=1e-9)


@pytest.mark.parametrize("name", sorted(EXPECTED_B))
def test_assets_follow_conventions(name: str) -> None:
    system = load_system(name, frame_skip=2)
    model = system.mj_model()
    expected_timestep = 0.02 if name == "cartpole" else 0.025
    assert model.opt.timestep == expected_timestep
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert (system.damping > 0).all() and not any(system.layout.limited)
    assert torch.equal(system.ctrl_low, -torch.ones(system.nu))
    assert torch.equal(system.ctrl_high, torch.ones(system.nu))
    assert system.control_dt == pytest.approx(2 * expected_timestep)


def test_load_system_errors(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="no_such_system"):
        load_system("no_such_system")
    with pytest.raises(FileNotFoundError, match="missing.xml"):
        load_system(tmp_path / "missing.xml")
    with pytest.raises(ValueError, match="frame_skip"):
        load_system("pendulum", frame_skip=0)


def mujoco_dynamics(name: str, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's M(q) (nv, nv) and qfrc_bias (nv,) = c(q, qd) + g(q) at one state."""
    model = load_system(name).mj_model()
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = q, qd
    mujoco.mj_forward(model, data)
    mass = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass)
    return mass, data.qfrc_bias.copy()


def test_closed_form_pendulum_matches_mujoco() -> None:
    from closed_form import pendulum_gravity, pendulum_mass_matrix

    for q in np.random.default_rng(5).uniform(-4, 4, size=(10, 1)):
        mass, bias = mujoco_dynamics("pendulum", q, np.zeros(1))
        qt = torch.from_numpy(q)
        np.testing.assert_allclose(pendulum_mass_matrix(qt).numpy(), mass, atol=1e-10)
        np.testing.assert_allclose(pendulum_gravity(qt).numpy(), bias, atol=1e-10)


def test_closed_form_arm2_matches_mujoco() -> None:
    from closed_form import arm2_coriolis, arm2_gravity, arm2_mass_matrix

    rng = np.random.default_rng(6)
    for q, qd in zip(rng.uniform(-4, 4, size=(10, 2)), rng.normal(0, 3, size=(10, 2)), strict=True):
        qt, qdt = torch.from_numpy(q), torch.from_numpy(qd)
        mass, gravity = mujoco_dynamics("arm2", q, np.zeros(2))
        np.testing.assert_allclose(arm2_mass_matrix(qt).numpy(), mass, atol=1e-10)
        np.testing.assert_allclose(arm2_gravity(qt).numpy(), gravity, atol=1e-10)
        _, bias = mujoco_dynamics("arm2", q, qd)
        np.testing.assert_allclose(arm2_coriolis(qt, qdt).numpy(), bias - gravity, atol=1e-10)
    # batched over leading dims
    q = torch.from_numpy(rng.normal(size=(3, 4, 2)))
    assert arm2_mass_matrix(q).shape == (3, 4, 2, 2) and arm2_gravity(q).shape == (3, 4, 2)
    assert arm2_coriolis(q, q).shape == (3, 4, 2)
