"""The kinematic tree with learned inertias (`models/tree.py`): MuJoCo's M, bias and passive
forces at the MJCF's numbers, the free-floating identity g = |g| M[:, z] and physical
consistency at any parameters, the residual Lagrangian starting at the tree, and a fit that
moves a wrong start towards MuJoCo's rigid body."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan.conf.builders import build_model
from mbrl_delan.conf.checks import compose_train_config
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.models.delan import Stepping, TreePrior
from mbrl_delan.models.tree import RigidBodyTree, TreeStart, documented_start, geometric_start
from mbrl_delan.systems.external import humanoid_v5_exo_xml, humanoid_v5_xml
from mbrl_delan.systems.system import asset_path

MODELS = {"humanoid_v5": humanoid_v5_xml, "panda": lambda: asset_path("panda")}


def random_states(model: mujoco.MjModel, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n configurations moved from qpos0 by N(0, 0.5) in velocity space (the root shifted by
    up to 5 m where it is free) and velocities N(0, 1). -> q (n, nq), qd (n, nv)"""
    rng = np.random.default_rng(seed)
    q = np.tile(model.qpos0, (n, 1))
    for i in range(n):
        mujoco.mj_integratePos(model, q[i], rng.normal(size=model.nv) * 0.5, 1.0)
        if model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE:
            q[i, :3] += rng.uniform(-5, 5, 3)
    return q, rng.normal(size=(n, model.nv))


def mujoco_terms(model: mujoco.MjModel, q: np.ndarray, qd: np.ndarray) -> dict[str, np.ndarray]:
    data = mujoco.MjData(model)
    out: dict[str, list[np.ndarray]] = {"M": [], "bias": [], "passive": []}
    for qpos, qvel in zip(q, qd, strict=True):
        data.qpos[:], data.qvel[:] = qpos, qvel
        mujoco.mj_forward(model, data)
        full = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, full)
        out["M"].append(full)
        out["bias"].append(data.qfrc_bias.copy())
        out["passive"].append(data.qfrc_passive.copy())
    return {k: np.stack(v) for k, v in out.items()}


@pytest.mark.parametrize("name", sorted(MODELS))
def test_tree_at_the_mjcfs_numbers_is_mujocos_rigid_body(name: str) -> None:
    """M = mj_fullM (armature included), c + g = qfrc_bias, k (q - q_s) + b qd = -qfrc_passive,
    to 1e-8 relative, at random configurations and velocities."""
    model = mujoco.MjModel.from_xml_path(str(MODELS[name]()))
    tree = RigidBodyTree.from_mujoco(model)
    q, qd = random_states(model, 8, seed=0)
    truth = mujoco_terms(model, q, qd)
    q_t, qd_t = torch.from_numpy(q), torch.from_numpy(qd)
    with torch.no_grad():
        kin = tree.kinematics(q_t)
        mass = tree.mass_matrix(q_t, kin).numpy()
        bias = tree.bias(qd_t, kin).numpy()
        passive = tree.passive(q_t, qd_t).numpy()
    for got, want in ((mass, truth["M"]), (bias, truth["bias"]), (passive, -truth["passive"])):
        np.testing.assert_allclose(got, want, atol=1e-8 * max(np.abs(want).max(), 1.0))


def scrambled(tree: RigidBodyTree, seed: int, size: float = 1.0) -> RigidBodyTree:
    """The tree with every raw parameter moved by N(0, size)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in tree.parameters():
            p.add_(size * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return tree


def test_gravity_is_weight_times_the_vertical_column_of_m_at_any_parameters() -> None:
    """For a free root under uniform gravity g(q) = |g| M(q)[:, z] (MuJoCo: to round-off); the
    tree keeps it by construction, whatever its inertias."""
    model = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    tree = scrambled(RigidBodyTree.from_mujoco(model), seed=1)
    q, _ = random_states(model, 8, seed=2)
    q_t = torch.from_numpy(q)
    with torch.no_grad():
        kin = tree.kinematics(q_t)
        mass, gravity = tree.mass_matrix(q_t, kin), tree.gravity(q_t, kin)
    true_mass = float(TreeStart.of_model(model).inertial[:, 0].sum())
    assert abs(float(tree.total_mass().detach()) - true_mass) > 1.0  # the parameters moved
    torch.testing.assert_close(gravity, 9.81 * mass[..., :, 2], rtol=1e-10, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_any_raw_parameters_give_a_physically_consistent_body(seed: int) -> None:
    """Positive mass, and principal inertias about the centre of mass that are positive and
    satisfy the triangle inequality I_a + I_b >= I_c, for raw parameters anywhere."""
    model = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    tree = scrambled(RigidBodyTree.from_mujoco(model), seed, size=3.0)
    with torch.no_grad():
        parts = tree.inertial()
    mass, h = parts["mass"], parts["first_moment"]
    assert bool((mass > 0).all())
    com = h / mass[:, None]
    shift = mass[:, None, None] * (
        (com * com).sum(-1)[:, None, None] * torch.eye(3, dtype=com.dtype)
        - com[:, :, None] * com[:, None, :]
    )
    principal = torch.linalg.eigvalsh(parts["inertia"] - shift)  # (B, 3) ascending
    scale = principal[:, 2:]
    assert bool((principal > -1e-9 * scale).all())
    assert bool((principal[:, 0] + principal[:, 1] >= principal[:, 2] - 1e-9 * scale[:, 0]).all())


def test_geometric_start_of_humanoid_v5_is_its_mjcf_and_the_documented_one_is_not() -> None:
    """Humanoid-v5's MJCF takes its inertias from its geoms at 1,000 kg/m^3: the geometric
    start is its truth; the documented start moves every body's mass by up to 50%."""
    spec = mujoco.MjSpec.from_file(str(humanoid_v5_xml()))
    truth = TreeStart.of_model(spec.compile())
    np.testing.assert_allclose(geometric_start(spec).inertial, truth.inertial, atol=1e-10)
    scaled = geometric_start(spec, total_mass=2 * truth.inertial[:, 0].sum())
    np.testing.assert_allclose(scaled.inertial, 2 * truth.inertial, rtol=1e-12)
    wrong = documented_start(spec).inertial[:, 0] / truth.inertial[:, 0]
    assert 0.5 <= wrong.min() < 0.8 and 1.2 < wrong.max() <= 1.5


def test_residual_lagrangian_at_its_start_is_the_tree() -> None:
    """model=tree_delan before any fit: M within 1e-5 of the tree's own, the same gravity
    (its potential and friction start at zero, M's residual at start_level^2 of its unit)."""
    parts = make_env_parts("humanoid_stand")
    tree_cfg = compose_train_config(["env=humanoid_stand", "model=tree"]).model
    both_cfg = compose_train_config(["env=humanoid_stand", "model=tree_delan"]).model
    torch.manual_seed(0)
    tree, both = build_model(tree_cfg, parts.system), build_model(both_cfg, parts.system)
    q, _ = random_states(parts.system.mj_model(), 4, seed=3)
    q_t = torch.from_numpy(q).float()
    alone, beside = tree.rigid_body(q_t), both.rigid_body(q_t)
    torch.testing.assert_close(beside.mass_matrix, alone.mass_matrix, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(beside.potential_force, alone.potential_force, rtol=1e-5, atol=1e-3)


def test_a_fit_from_the_geometric_start_moves_m_towards_mujocos() -> None:
    """The Panda's geometric start (its capsules at 1,000 kg/m^3: 7.7 kg against 16.8) fitted
    on 2,000 samples of exact inverse dynamics (MuJoCo's forward dynamics at random states and
    controls) brings M to within a tenth of its start's error from `mj_fullM` on other
    states."""
    from tensordict import TensorDict

    from mbrl_delan import keys
    from mbrl_delan.models.delan import DeLaN
    from mbrl_delan.models.inertial import rigid_body_at
    from mbrl_delan.systems.system import load_system
    from mbrl_delan.training.fit import FitConfig, fit_model

    system = load_system("panda")
    model = system.mj_model()
    data, rng = mujoco.MjData(model), np.random.default_rng(0)
    rows = []
    for _ in range(2064):
        data.qpos[:] = rng.uniform(*model.jnt_range.T)
        data.qvel[:] = rng.normal(size=model.nv)
        data.ctrl[:] = rng.uniform(-1, 1, model.nu)
        mujoco.mj_forward(model, data)
        rows.append((data.qpos.copy(), data.qvel.copy(), data.ctrl.copy(), data.qacc.copy()))
    q, qd, action, qdd = (torch.tensor(np.stack(c)) for c in zip(*rows, strict=True))
    samples = TensorDict({keys.Q: q, keys.QD: qd, keys.ACTION: action, keys.QDD: qdd}, [len(q)])
    spec = mujoco.MjSpec.from_file(str(system.xml_path))
    tree = RigidBodyTree.from_mujoco(model, geometric_start(spec))
    delan = DeLaN(system.layout, system.actuation, system.control_dt,
                  stepping=Stepping(loss="inverse"), tree=TreePrior(tree))  # fmt: skip
    test_q = q[-64:]
    truth, _ = rigid_body_at(model, test_q.numpy())

    def error() -> float:
        mass = delan.rigid_body(test_q).mass_matrix.numpy()
        return float(np.median(np.linalg.norm(mass - truth, axis=(1, 2))
                               / np.linalg.norm(truth, axis=(1, 2))))  # fmt: skip

    before = error()
    torch.manual_seed(0)
    optimizer = torch.optim.Adam(delan.parameters(), lr=0.03)
    settings = FitConfig(batch_size=256, max_epochs=60, patience=None, max_batches_per_epoch=8)
    fit_model(delan, optimizer, samples[:-64], settings, torch.Generator().manual_seed(1))
    after = error()
    assert before > 0.3 and after < 0.1 * before, (before, after)  # measured: 0.465 -> 0.005


def test_residual_penalty_adds_the_residuals_share_of_the_torque_to_the_loss() -> None:
    """model=tree_delan with `residual_penalty`: the loss grows by the penalty times the
    residual's inverse-dynamics torque per unit of torque scale, squared and averaged, at the
    batch's finite-difference accelerations; the plain tree refuses a penalty."""
    from tensordict import TensorDict

    from mbrl_delan import keys
    from mbrl_delan.conf.builders import build_model as build
    from mbrl_delan.conf.checks import ConfigError

    parts = make_env_parts("humanoid_stand")
    overrides = ["env=humanoid_stand", "model=tree_delan", "model.start_level=0.3"]
    models = {}
    for penalty in (0.0, 2.5):
        cfg = compose_train_config([*overrides, f"model.residual_penalty={penalty}"]).model
        torch.manual_seed(0)
        models[penalty] = build(cfg, parts.system)
    plain, penalised = models[0.0], models[2.5]
    q, qd = random_states(parts.system.mj_model(), 8, seed=4)
    q_t, qd_t = torch.from_numpy(q).float(), torch.from_numpy(qd).float()
    action = torch.rand(8, parts.system.nu) * 0.8 - 0.4
    next_qd = qd_t + 0.01 * torch.randn(8, qd_t.shape[-1])
    batch = TensorDict({keys.Q: q_t, keys.QD: qd_t, keys.ACTION: action,
                        keys.NEXT_Q: q_t, keys.NEXT_QD: next_qd}, [8])  # fmt: skip
    qdd = (next_qd - qd_t) / penalised.control_dt
    share = penalised.dynamics.residual.inverse_dynamics(q_t, qd_t, qdd) / penalised.tau_scale
    expected = share.pow(2).mean().detach()
    assert float(expected) > 1e-6  # a residual of start_level 0.3 is not negligible
    out, base = penalised.loss(batch), plain.loss(batch)
    assert out.metrics["residual_mse"] == pytest.approx(float(expected), rel=1e-5)
    assert float(out.loss) == pytest.approx(float(base.loss) + 2.5 * float(expected), rel=1e-5)
    with pytest.raises(ConfigError, match="residual_penalty"):
        tree_cfg = compose_train_config(["env=humanoid_stand", "model=tree",
                                         "model.residual_penalty=1.0"]).model  # fmt: skip
        build(tree_cfg, parts.system)


def test_learned_springs_start_at_the_mjcfs_and_fit_the_exoskeletons() -> None:
    """With `learn_springs` the tree's springs start at Humanoid-v5's (a zero spring at the
    floor share of the largest) and, fitted by gradient to MuJoCo's spring forces of the
    exoskeleton's MJCF, reach its stiffness and rest angles at every sprung hinge."""
    plain = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    exo = mujoco.MjModel.from_xml_path(str(humanoid_v5_exo_xml()))
    tree = RigidBodyTree.from_mujoco(plain, learn_springs=True)
    fixed = RigidBodyTree.from_mujoco(plain)
    sprung = fixed.stiffness > 0
    assert tree.spring_ref.requires_grad and tree.raw_stiffness.requires_grad
    np.testing.assert_allclose(tree.spring_stiffness().detach()[sprung], fixed.stiffness[sprung])
    q, _ = random_states(plain, 64, seed=1)
    data = mujoco.MjData(exo)
    target = []
    for qpos in q:
        data.qpos[:] = qpos
        mujoco.mj_forward(exo, data)
        target.append(-data.qfrc_spring.copy())  # the tree's k (q - q_s) resists
    target_t, q_t = torch.from_numpy(np.stack(target)), torch.from_numpy(q)
    springs = [tree.raw_stiffness, tree.spring_ref]
    optimiser = torch.optim.LBFGS(springs, lr=1.0, max_iter=500, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        optimiser.zero_grad()
        loss = (tree.spring(q_t) - target_t).pow(2).mean()
        loss.backward()
        return loss

    optimiser.step(closure)
    truth = torch.tensor([exo.jnt_stiffness[exo.dof_jntid[v]] for v in range(exo.nv)])
    rest = torch.tensor([exo.qpos_spring[exo.jnt_qposadr[exo.dof_jntid[v]]]
                         for v in range(exo.nv)])  # fmt: skip
    hinges = truth > 0
    assert int(hinges.sum()) > int(sprung.sum())  # the right knee too, which the MJCF leaves free
    learned = tree.spring_stiffness().detach()
    np.testing.assert_allclose(learned[hinges], truth[hinges], rtol=1e-4)
    np.testing.assert_allclose(tree.spring_ref.detach()[hinges], rest[hinges], atol=1e-4)


def test_the_residuals_spring_potential_adds_to_the_trees_springs_on_the_hinges() -> None:
    """model=tree_delan model.spring_potential=true on the humanoid: at its start the model is
    the tree (K and b at zero); a K set on the hinges shows in `joint_stiffness` as the tree's
    springs plus K's diagonal, and the free root gets none."""
    parts = make_env_parts("humanoid_stand_exo")
    cfg = compose_train_config(["env=humanoid_stand_exo", "model=tree_delan",
                                "model.spring_potential=true"]).model  # fmt: skip
    torch.manual_seed(0)
    model = build_model(cfg, parts.system).double()
    field = model.dynamics.residual.field
    hinges = field.spring_v.tolist()
    assert hinges == list(range(6, parts.system.mj_model().nv))  # not the free root's six
    q, _ = random_states(parts.system.mj_model(), 8, seed=2)
    q_t = torch.from_numpy(q)
    before = model.dynamics.joint_stiffness(q_t)
    torch.testing.assert_close(before, model.dynamics.tree.spring_stiffness().double())
    diagonal = torch.linspace(1.0, 2.0, len(hinges), dtype=torch.float64)
    with torch.no_grad():
        field.spring_stiffness.copy_(torch.diag(diagonal))
    added = model.dynamics.joint_stiffness(q_t) - before
    torch.testing.assert_close(added[hinges], diagonal * field.energy_scale, rtol=1e-5, atol=1e-6)
    assert added[:6].abs().max() < 1e-9


def test_the_residual_penalty_leaves_out_the_quadratic_springs() -> None:
    """model=tree_delan with the spring potential and the penalty: the penalty's
    `residual_mse` is the same whatever the springs K and b are (they are physics no rigid
    body holds), while the model's inverse dynamics changes by their force exactly;
    `spring_force` is the quadratic's gradient (autograd)."""
    parts = make_env_parts("humanoid_stand_exo")
    cfg = compose_train_config(["env=humanoid_stand_exo", "model=tree_delan",
                                "model.spring_potential=true", "model.residual_penalty=1.0",
                                "model.loss=both"]).model  # fmt: skip
    torch.manual_seed(0)
    model = build_model(cfg, parts.system).double()
    field = model.dynamics.residual.field
    q, qd = (torch.from_numpy(x) for x in random_states(parts.system.mj_model(), 8, seed=3))
    qdd = torch.randn(q.shape[0], parts.system.nv, dtype=torch.float64)
    action = torch.zeros(q.shape[0], parts.system.nu, dtype=torch.float64)

    def terms() -> dict[str, float]:
        out = model.transition_losses(q, qd, action, qdd, None, None, forward=False)
        return {k: float(v) for k, v in out.items()}

    before, tau_before = terms(), model.dynamics.inverse_dynamics(q, qd, qdd).detach()
    with torch.no_grad():
        field.spring_stiffness.normal_()
        field.spring_offset.normal_()
    after, tau_after = terms(), model.dynamics.inverse_dynamics(q, qd, qdd).detach()
    assert after["residual_mse"] == pytest.approx(before["residual_mse"], rel=1e-9)
    springs = field.spring_force(q).detach()
    assert springs.abs().max() > 1.0
    torch.testing.assert_close(tau_after - tau_before, springs, rtol=1e-6, atol=1e-6)
    x = q.clone().requires_grad_(True)
    potential = field._spring_potential(x)[0].sum()
    (grad,) = torch.autograd.grad(potential, x)
    expected = torch.zeros_like(qd).index_add(-1, field.spring_v, grad[:, field.spring_q])
    torch.testing.assert_close(field.spring_force(q), expected)
