"""What an arm's MJCF lacks (`mbrl_delan.systems.arms`): springs in the arm that makes the data
(their torques against the analytic springs and MuJoCo's inverse dynamics) and a CAD file's
wrong inertials (reproducible from its seed, the kinematics the arm's), and the fit and
suite options that use them."""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan.bench import run
from mbrl_delan.benchmarks.own_arm import main, spring_stiffness_matrix
from mbrl_delan.benchmarks.records import read_records
from mbrl_delan.conf.checks import ConfigError, compose_config
from mbrl_delan.conf.fitting import FIT_CONFIG_DIR
from mbrl_delan.data.excitation import ExcitationSettings, excitation_arrays, inverse_dynamics
from mbrl_delan.fit_run import _run
from mbrl_delan.runs import load_fit_model
from mbrl_delan.systems.arms import (
    CAD_ERROR,
    SPRINGS,
    arm_model,
    cad_spec,
    shoulder_joint,
    spring_torque,
    torque_limits,
    wrist_pair,
)
from tests.test_excitation import TWO_LINK
from tests.test_own_arm import _bench

QUIET = ExcitationSettings(samples=400, q_noise=0.0, tau_noise=0.0, cutoff_hz=None)


def _middle_half(model: mujoco.MjModel, j: int) -> tuple[float, float]:
    low, high = model.jnt_range[j]
    return (low + high) / 2, min((high - low) / 2, math.pi)


@pytest.mark.parametrize("robot", ["panda", "ur5e"])
def test_the_springs_torques_are_the_analytic_springs(robot: str) -> None:
    """counterbalance: k (q_s - middle) on the shoulder, k = share x limit / half-width;
    coupling: k (q_a + q_b - middle_a - middle_b) on both wrist joints; nothing elsewhere."""
    plain = arm_model(robot)
    limits = torque_limits(plain)
    q = excitation_arrays(robot, "none", QUIET, seed=0)["q"][::20]
    s = shoulder_joint(plain)
    assert s == 1  # the second joint carries the arm against gravity on these arms
    middle, half = _middle_half(plain, s)
    k = SPRINGS.counterbalance * limits[s] / half
    balanced = spring_torque(arm_model(robot, structure="counterbalance"), q)
    expected = np.zeros_like(q)
    expected[:, s] = k * (q[:, s] - middle)
    np.testing.assert_allclose(balanced, expected, atol=1e-9)
    a, b = wrist_pair(plain)
    (ma, ha), (mb, hb) = _middle_half(plain, a), _middle_half(plain, b)
    k = SPRINGS.coupling * min(limits[a], limits[b]) / (ha + hb)
    coupled = spring_torque(arm_model(robot, structure="coupling"), q)
    expected = np.zeros_like(q)
    expected[:, a] = expected[:, b] = k * (q[:, a] + q[:, b] - ma - mb)
    np.testing.assert_allclose(coupled, expected, atol=1e-9)
    stiffness = spring_stiffness_matrix(robot, "coupling", q[:3])
    np.testing.assert_allclose(stiffness[:, [a, b]][..., [a, b]], np.full((3, 2, 2), k), rtol=1e-6)


@pytest.mark.parametrize("structure", ["counterbalance", "coupling"])
def test_data_with_springs_are_mujocos_inverse_dynamics_and_the_springs_are_potential(
    structure: str,
) -> None:
    """mj_inverse of the arm with its springs is the plain arm's plus the springs' torque;
    in the data (noise-free q), the potential part g holds the springs and the parts sum to
    tau."""
    model = arm_model("iiwa14", structure=structure)
    rng = np.random.default_rng(0)
    q, qd, qdd = (rng.uniform(-1, 1, (20, 7)) for _ in range(3))
    springs = spring_torque(model, q)
    assert np.abs(springs).max() > 1.0  # N m: the springs are there
    mj = mujoco.MjData(model)
    plain = inverse_dynamics(arm_model("iiwa14"), q, qd, qdd)
    for i in range(q.shape[0]):
        mj.qpos[:], mj.qvel[:], mj.qacc[:] = q[i], qd[i], qdd[i]
        mujoco.mj_inverse(model, mj)
        np.testing.assert_allclose(mj.qfrc_inverse, plain["tau"][i] + springs[i], atol=1e-9)
    data = excitation_arrays("iiwa14", "none", QUIET, seed=3, structure=structure)
    gravity = inverse_dynamics(arm_model("iiwa14"), data["q"], data["qd"], data["qdd"])
    np.testing.assert_allclose(data["tau_gravity"],
                               gravity["tau_gravity"] + spring_torque(model, data["q"]),
                               atol=1e-9)  # fmt: skip
    parts = data["tau_inertial"] + data["tau_coriolis"] + data["tau_gravity"]
    np.testing.assert_allclose(parts, data["tau"], atol=1e-8)


def test_the_cad_file_is_reproducible_from_its_seed_and_keeps_the_kinematics() -> None:
    own = arm_model("panda")
    first, again, other = (cad_spec("panda", s).compile() for s in (4, 4, 5))
    np.testing.assert_array_equal(first.body_mass, again.body_mass)
    np.testing.assert_array_equal(first.body_ipos, again.body_ipos)
    assert not np.allclose(first.body_mass, other.body_mass)
    moving = own.body_mass > 0
    ratio = first.body_mass[moving] / own.body_mass[moving]
    assert ((ratio >= CAD_ERROR.scale[0]) & (ratio <= CAD_ERROR.scale[1])).all()
    assert np.abs(ratio - 1).max() > 0.05
    shift = np.linalg.norm(first.body_ipos - own.body_ipos, axis=1)
    assert shift.max() <= CAD_ERROR.com_m + 1e-12 and shift.max() > 0
    for name in ("body_pos", "body_quat", "jnt_axis", "jnt_range", "dof_parentid"):
        np.testing.assert_array_equal(getattr(first, name), getattr(own, name))


def test_a_fit_given_the_cad_file_rebuilds_it_from_its_provenance(tmp_path: Path) -> None:
    overrides = ["data=excitation", "data.robot=ur5e", "data.samples=1200", "model=white_box",
                 "data.model_mjcf=cad", "data.structure=coupling", "logger=none",
                 "threads=1"]  # fmt: skip
    summary, fitted = _run(compose_config(FIT_CONFIG_DIR, overrides), tmp_path / "run")
    assert summary["model_mjcf"] == "cad" and summary["structure"] == "coupling"
    _, loaded = load_fit_model(tmp_path / "run")
    cad = cad_spec("ur5e", 0).compile()  # data.seed 0 draws the CAD file
    np.testing.assert_array_equal(loaded.mujoco_model().body_pos, cad.body_pos)
    np.testing.assert_allclose(loaded.prior.numpy(), fitted.prior.numpy())
    q = torch.zeros(1, 6, dtype=torch.float64)
    np.testing.assert_allclose(loaded.predict_torque(q, q, q), fitted.predict_torque(q, q, q))


def test_a_model_mjcf_of_other_joints_or_no_file_is_a_config_error(tmp_path: Path) -> None:
    base = ["data=excitation", "data.robot=ur5e", "data.samples=600", "model=white_box",
            "logger=none"]  # fmt: skip
    with pytest.raises(ConfigError, match="data.model_mjcf='nope' is not valid"):
        _run(compose_config(FIT_CONFIG_DIR, [*base, "data.model_mjcf=nope"]), tmp_path / "a")
    panda = tmp_path / "panda.xml"
    panda.write_text(cad_spec("panda", 0).to_xml())
    with pytest.raises(ConfigError, match="joints .* are not data.robot=ur5e's"):
        _run(compose_config(FIT_CONFIG_DIR, [*base, f"data.model_mjcf={panda}"]), tmp_path / "b")
    with pytest.raises(ConfigError, match="data.structure"):
        _run(compose_config(FIT_CONFIG_DIR, [*base, "data.structure=gas_spring"]), tmp_path / "c")
    assert not any((tmp_path / d).exists() for d in "abc")


def test_the_suite_records_structure_and_model_mjcf_and_the_white_box_misses_springs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "own_arm.jsonl"
    run(_bench(["quick=true", "models=[white_box]", "friction=[coulomb_viscous]",
                "samples=[2000]", "structures=[none,coupling]", "model_mjcf=cad",
                f"out={out}"]))  # fmt: skip
    records = read_records(out)
    r2 = {(r["structure"], r["metric"]): r["value"] for r in records}
    assert {r["model_mjcf"] for r in records} == {"cad"}
    assert {r["case"] for r in records} == {
        "panda_white_box_coulomb_viscous_2000_fourier_cad",
        "panda_white_box_coulomb_viscous_coupling_2000_fourier_cad",
    }
    assert r2[("none", "test_torque_r2")] > 0.99  # the CAD file's inertials identified
    assert r2[("coupling", "test_torque_r2")] < r2[("coupling", "truth_torque_r2")] - 0.003
    assert r2[("coupling", "truth_torque_r2")] > 0.99  # the arm's own, springs included
    assert 0.05 < r2[("coupling", "spring_torque_share")] < 2  # small about the middles
    stiffness = {r["arm_spring_stiffness"] for r in records if r["structure"] == "coupling"}
    assert len(stiffness) == 1 and stiffness.pop() > 0
    assert main([str(out), "--table"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].startswith("| MJCF lacks | arm | white_box R²") and len(table) == 4
    coupled = r2[("coupling", "test_torque_r2")]
    assert table[3].startswith(f"| coupling | panda | {coupled:.4f} | - |")  # one model: "-"


def test_tree_delan_reports_its_residuals_stiffness(tmp_path: Path) -> None:
    out = tmp_path / "own_arm.jsonl"
    run(_bench(["quick=true", "models=[tree_delan]", "samples=[600]",
                "structures=[counterbalance]", f"out={out}"]))  # fmt: skip
    metrics = {r["metric"]: r["value"] for r in read_records(out)}
    error = metrics["spring_stiffness_error"]
    assert math.isfinite(error) and error >= 0
    assert math.isfinite(metrics["spring_stiffness"])


@pytest.mark.parametrize("model", ["white_box", "tree_delan"])
def test_identified_xml_reloads_in_mujoco_with_the_fits_rigid_body(
    tmp_path: Path, model: str
) -> None:
    """The fit's identified.xml, loaded by MuJoCo, gives the fitted M(q) and gravity torque
    (the white box's identified MJCF; the tree's learned inertials) at random poses, and
    the summary lists each body's numbers beside the file's."""
    overrides = ["data=excitation", "data.robot=ur5e", "data.samples=1200", f"model={model}",
                 "data.model_mjcf=cad", "data.friction=coulomb_viscous", "logger=none",
                 "threads=1", "epochs=3"]  # fmt: skip
    summary, fitted = _run(compose_config(FIT_CONFIG_DIR, overrides), tmp_path / "run")
    xml = mujoco.MjModel.from_xml_path(str(tmp_path / "run" / "identified.xml"))
    cad = cad_spec("ur5e", 0).compile()
    rng = np.random.default_rng(1)
    q = rng.uniform(-2, 2, (5, 6))
    data = mujoco.MjData(xml)
    mass, gravity = np.zeros((5, 6, 6)), np.zeros((5, 6))
    for i, qi in enumerate(q):
        data.qpos[:] = qi
        mujoco.mj_forward(xml, data)
        mujoco.mj_fullM(xml, data, mass[i])
        gravity[i] = data.qfrc_bias - data.qfrc_passive
    qt = torch.as_tensor(q)
    if model == "white_box":
        expected_mass, expected_gravity = _mujoco_rigid_body(fitted.mujoco_model(), q)
    else:
        tree = fitted.dynamics.tree
        with torch.no_grad():
            expected_mass = tree.mass_matrix(qt).numpy()  # armature included
            expected_gravity = tree.gravity(qt).numpy()
    # the file's numbers in MuJoCo's XML precision (6 significant digits)
    np.testing.assert_allclose(mass, expected_mass, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(gravity, expected_gravity, rtol=1e-4, atol=1e-5)
    bodies = summary["identified"]["bodies"]
    assert len(bodies) == len(cad.body_mass) - 2  # the moving bodies: not the world or base
    for name, numbers in bodies.items():
        assert numbers["mass_file"] == pytest.approx(cad.body(name).mass[0])
    joints = summary["identified"]["joints"]
    assert joints["damping"]["file"] == [0.0] * 6 and len(joints["damping"]["identified"]) == 6
    if model == "tree_delan":
        assert len(summary["identified"]["residual_torque_share"]) == 6


def _mujoco_rigid_body(model: mujoco.MjModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    data = mujoco.MjData(model)
    mass, gravity = np.zeros((len(q), model.nv, model.nv)), np.zeros((len(q), model.nv))
    for i, qi in enumerate(q):
        data.qpos[:] = qi
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, mass[i])
        gravity[i] = data.qfrc_bias - data.qfrc_passive
    return mass, gravity


def test_friction_none_sets_a_files_own_damping_and_frictionloss_to_zero(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "rough.xml"
    path.write_text(TWO_LINK.replace('range="-2 2"/>', 'range="-2 2" damping="3" '
                                     'frictionloss="1" armature="0.1"/>'))  # fmt: skip
    with caplog.at_level("INFO"):
        plain = arm_model(str(path), "none")
    assert not plain.dof_damping.any() and not plain.dof_frictionloss.any()
    assert not plain.dof_armature.any()
    assert "sets the file's damping, frictionloss, armature to zero" in caplog.text
