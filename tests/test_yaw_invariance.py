"""`Structure(yaw_invariant=True)`: turning a free-floating system about the vertical turns its
predicted motion with it, and the equations stay Lagrangian (energy, inverse-forward)."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch
from torch import Tensor

from mbrl_delan.conf.checks import CONFIG_DIR
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.features import rotation_matrix
from mbrl_delan.models.integrators import integrate
from mbrl_delan.models.structure import Structure
from mbrl_delan.systems.external import humanoid_v5_xml
from mbrl_delan.systems.system import load_system
from tests.test_free_joints import (  # noqa: F401  (float64: an autouse fixture)
    MIXED,
    float64,
    random_states,
    system_of,
)


def turn(q: Tensor, qd: Tensor, angle: float) -> tuple[Tensor, Tensor, Tensor]:
    """The state turned by `angle` about the world's vertical (free root first), and Rz."""
    c, s = math.cos(angle), math.sin(angle)
    Rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    w1, v1 = math.cos(angle / 2), torch.tensor([0.0, 0.0, math.sin(angle / 2)])
    w2, v2 = q[..., 3:4], q[..., 4:7]
    quat = torch.cat(
        [
            w1 * w2 - (v2 @ v1).unsqueeze(-1),
            w1 * v2 + w2 * v1 + torch.linalg.cross(v1.expand_as(v2), v2),
        ],
        dim=-1,
    )
    q_turned = torch.cat([q[..., :3] @ Rz.T, quat, q[..., 7:]], dim=-1)
    qd_turned = torch.cat([qd[..., :3] @ Rz.T, qd[..., 3:]], dim=-1)
    return q_turned, qd_turned, Rz


def model_of(system, **kwargs) -> DeLaN:
    torch.manual_seed(0)
    return DeLaN(
        system.layout, system.actuation, 0.01, Structure(hidden=32, yaw_invariant=True, **kwargs)
    ).double()


def test_turn_helper_turns_the_root_rotation(tmp_path) -> None:
    system = system_of(MIXED, tmp_path)
    q, qd = random_states(system, 3, seed=4)
    q_t, _, Rz = turn(q, qd, 0.7)
    torch.testing.assert_close(rotation_matrix(q_t[..., 3:7]), Rz @ rotation_matrix(q[..., 3:7]))


@pytest.mark.parametrize("residual", [False, True])
def test_turned_state_gives_turned_accelerations(tmp_path, residual) -> None:
    system = system_of(MIXED, tmp_path)
    model = model_of(system, residual=residual)
    if residual:  # a fresh residual is zero; give it weights so that it acts
        with torch.no_grad():
            for p in model.residual.parameters():
                p.normal_(0.0, 0.3)
    q, qd = random_states(system, 6, seed=5)
    action = torch.randn(6, system.nu, generator=torch.Generator().manual_seed(6))
    qdd = model.acceleration(q, qd, action)
    plain = DeLaN(system.layout, system.actuation, 0.01, Structure(hidden=32)).double()
    for angle in (0.4, -2.0, math.pi):
        q_t, qd_t, Rz = turn(q, qd, angle)
        expected = torch.cat([qdd[..., :3] @ Rz.T, qdd[..., 3:]], dim=-1)
        torch.testing.assert_close(model.acceleration(q_t, qd_t, action), expected)
        terms, terms_t = model.terms(q, qd), model.terms(q_t, qd_t)
        torch.testing.assert_close(terms_t.potential_energy, terms.potential_energy)
        torch.testing.assert_close(terms_t.kinetic_energy, terms.kinetic_energy)
        # a model that sees the heading does not turn its accelerations along
        qdd_plain = plain.acceleration(q, qd, action)
        turned_plain = torch.cat([qdd_plain[..., :3] @ Rz.T, qdd_plain[..., 3:]], dim=-1)
        assert (plain.acceleration(q_t, qd_t, action) - turned_plain).abs().max() > 1e-3


@pytest.mark.parametrize("structure", ["plain", "translation_invariant", "tree_sparse"])
def test_mass_matrix_is_positive_definite_and_inverse_undoes_forward(tmp_path, structure) -> None:
    """Also with V's exact height term and with the tree-sparse (upper) factor of M_b."""
    system = system_of(MIXED, tmp_path)
    extra = {
        "plain": {},
        "translation_invariant": {"translation_invariant": True},
        "tree_sparse": {"dof_parents": system.mj_model().dof_parentid.tolist()},
    }[structure]
    model = model_of(system, **extra)
    q, qd = random_states(system, 6, seed=7)
    M = model.terms(q, qd).mass_matrix
    torch.testing.assert_close(M, M.transpose(-1, -2))
    assert bool((torch.linalg.eigvalsh(M) > 0).all())
    tau = torch.randn(6, system.nv, generator=torch.Generator().manual_seed(8))
    qdd = model.dynamics.forward_dynamics(q, qd, tau)
    torch.testing.assert_close(model.dynamics.inverse_dynamics(q, qd, qdd), tau)
    q_t, qd_t, Rz = turn(q, qd, 1.1)
    tau_t = torch.cat([tau[..., :3] @ Rz.T, tau[..., 3:]], dim=-1)
    expected = torch.cat([qdd[..., :3] @ Rz.T, qdd[..., 3:]], dim=-1)
    torch.testing.assert_close(model.dynamics.forward_dynamics(q_t, qd_t, tau_t), expected)


def energy_drift(model: DeLaN, system, dt: float, duration: float = 0.2) -> float:
    """Largest relative change of M's kinetic plus V's energy over `duration`, no torque."""
    q, qd = random_states(system, 4, seed=9)
    zero = torch.zeros_like(qd)

    def energy(q: Tensor, qd: Tensor) -> Tensor:
        terms = model.terms(q, qd)
        return terms.kinetic_energy + terms.potential_energy

    e0 = energy(q, qd)
    with torch.no_grad():
        for _ in range(round(duration / dt)):
            step = integrate(
                system.layout, lambda a, b: model.dynamics.forward_dynamics(a, b, zero), q, qd, dt
            )
            q, qd = step.q, step.qd
    return float(((energy(q, qd) - e0).abs() / e0.abs().clamp_min(1.0)).max())


def test_energy_conserved_without_torque_and_friction(tmp_path) -> None:
    """The drift is RK4's own: it falls about 16-fold when the step halves (a model that
    did not conserve energy would keep a drift of the order of its error in the force)."""
    system = system_of(MIXED, tmp_path)
    model = model_of(system, dissipation=False)
    coarse, fine = energy_drift(model, system, 2e-3), energy_drift(model, system, 1e-3)
    assert fine < 1e-3 and fine < coarse / 10  # measured: 5.8e-3 and 3.5e-4
    friction = model_of(system)  # with friction the energy falls: the test can tell
    assert energy_drift(friction, system, 2e-3) > 100 * fine


def test_mujoco_humanoid_mass_matrix_has_this_form() -> None:
    """MuJoCo's M of Humanoid-v5 is S M_b S^T with M_b the same at every root pose: the
    class of `yaw_invariant` models holds the true one."""
    model = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    q = model.qpos0.copy()
    q[7:] += rng.uniform(-0.3, 0.3, model.nq - 7)
    body_frame = []
    for _ in range(3):
        quat = rng.normal(size=4)
        q[:3], q[3:7] = rng.normal(size=3), quat / np.linalg.norm(quat)
        data.qpos[:] = q
        mujoco.mj_forward(model, data)
        M = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, M)
        S = np.eye(model.nv)
        S[:3, :3] = rotation_matrix(torch.from_numpy(q[3:7])).numpy()
        body_frame.append(S.T @ M @ S)
    scale = np.abs(body_frame[0]).max()
    for other in body_frame[1:]:
        assert np.abs(other - body_frame[0]).max() < 1e-12 * scale
    # and a plain turn changes M in world coordinates, so the rotation S is needed
    assert np.abs(M - body_frame[0]).max() > 1e-2 * scale


def test_needs_a_free_root_first() -> None:
    system = load_system("acrobot")
    with pytest.raises(ValueError, match="free root"):
        DeLaN(system.layout, system.actuation, 0.01, Structure(yaw_invariant=True))


@pytest.mark.parametrize("name", ["delan", "delan_ensemble"])
def test_config_builds_yaw_invariant_humanoid_models_that_step_turned(name) -> None:
    """`model.yaw_invariant=true` reaches every DeLaN (the ensemble's members too), and a
    control step of Humanoid-v5 from a turned state lands on the turned next state."""

    from hydra import compose, initialize_config_dir

    from mbrl_delan.conf.builders import build_model
    from mbrl_delan.envs.registry import make_env_parts

    configs = str(CONFIG_DIR)
    overrides = ["env=humanoid_stand", f"model={name}", "model.yaw_invariant=true"]
    with initialize_config_dir(config_dir=configs, version_base=None):
        cfg = compose("config", overrides=overrides)
    system = make_env_parts("humanoid_stand").system
    torch.manual_seed(0)
    model = build_model(cfg.model, system).double()
    members = [model] if name == "delan" else [model.member(i) for i in range(2)]
    assert all(m.structure.yaw_invariant and m.residual is not None for m in members)
    q, qd = random_states(system, 3, seed=10)
    action = 0.3 * torch.randn(3, system.nu, generator=torch.Generator().manual_seed(11))
    with torch.no_grad():
        for p in model.parameters():  # fresh heads are zero: give every part weights
            p.add_(0.05 * torch.randn_like(p))
        step = model.step(q, qd, action, generator=torch.Generator().manual_seed(1))
        q_t, qd_t, Rz = turn(q, qd, 2.3)
        turned = model.step(q_t, qd_t, action, generator=torch.Generator().manual_seed(1))
    expected_q, expected_qd, _ = turn(step.q, step.qd, 2.3)
    torch.testing.assert_close(turned.q, expected_q)
    torch.testing.assert_close(turned.qd, expected_qd)
