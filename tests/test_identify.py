"""System identification from MuJoCo data: the dataset, the metrics and the `identify` suite."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from torch.nn import functional as F

from mbrl_delan import keys
from mbrl_delan.benchmarks import SUITE_NAMES, get_suite
from mbrl_delan.benchmarks.identify import (
    METRICS,
    SYSTEMS,
    IdentifyConfig,
    gravity_errors,
    identify_system,
    make_model,
    mujoco_energy_drift,
    passive_energy_drift,
    relative_errors,
    run_identify,
    run_identify_suite,
    suite_config,
    torque_r2,
)
from mbrl_delan.benchmarks.records import BASE_FIELDS, RecordWriter, read_records
from mbrl_delan.conf.bench_schema import IdentifySuiteConfig
from mbrl_delan.data.synthetic import dynamics_dataset, reference_terms
from mbrl_delan.systems.system import load_system


def _data(name: str, n: int, seed: int = 0):
    system = load_system(name)
    return system, dynamics_dataset(system, n, torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("name", ["acrobot", "arm3"])
def test_dataset_is_mujocos_forward_dynamics(name: str) -> None:
    """tau = B a equals M qdd + qfrc_bias - qfrc_passive (mj_inverse) at every sample."""
    system, data = _data(name, 8)
    assert data[keys.QDD].dtype == torch.float64 and data.batch_size == torch.Size([8])
    low, high = system.ctrl_low, system.ctrl_high
    assert ((data[keys.ACTION] >= low) & (data[keys.ACTION] <= high)).all()
    torch.testing.assert_close(data[keys.TAU], data[keys.ACTION] @ system.actuation.T)
    model = system.mj_model()
    mj = mujoco.MjData(model)
    for i in range(8):
        mj.qpos[:], mj.qvel[:] = data[keys.Q][i].numpy(), data[keys.QD][i].numpy()
        mj.qacc[:] = data[keys.QDD][i].numpy()
        mujoco.mj_inverse(model, mj)
        np.testing.assert_allclose(mj.qfrc_inverse, data[keys.TAU][i].numpy(), atol=1e-9)
    assert data[keys.QD].abs().max() > 1.0  # states are spread, not all at rest


def test_dataset_next_state_is_one_mujoco_step_and_seeded() -> None:
    system, data = _data("arm2", 4, seed=3)
    _, again = _data("arm2", 4, seed=3)
    torch.testing.assert_close(data.to_dict(), again.to_dict())
    model = system.mj_model()
    mj = mujoco.MjData(model)
    mj.qpos[:], mj.qvel[:] = data[keys.Q][1].numpy(), data[keys.QD][1].numpy()
    mj.ctrl[:] = data[keys.ACTION][1].numpy()
    mujoco.mj_step(model, mj)
    np.testing.assert_allclose(data[keys.NEXT_QD][1].numpy(), mj.qvel, atol=1e-12)


def test_reference_terms_of_the_pendulum_are_textbook() -> None:
    """Bob 1 kg at 1 m plus I_yy = 0.01: M = 1.01, g = m g l sin q."""
    q = torch.linspace(-3.0, 3.0, 7, dtype=torch.float64).unsqueeze(-1)
    ref = reference_terms(load_system("pendulum"), q)
    torch.testing.assert_close(ref.mass_matrix, torch.full((7, 1, 1), 1.01, dtype=torch.float64))
    torch.testing.assert_close(ref.gravity, 9.81 * torch.sin(q))


def test_metric_helpers() -> None:
    ref = torch.tensor([[3.0, 4.0], [1e-6, 0.0], [0.0, 2.0]])
    learned = ref + torch.tensor([[0.5, 0.0], [1.0, 0.0], [0.0, 0.2]])
    torch.testing.assert_close(relative_errors(learned, ref)[[0, 2]], torch.tensor([0.1, 0.1]))
    torch.testing.assert_close(gravity_errors(learned, ref), torch.tensor([0.1, 0.1]))  # skips ~0
    target = torch.tensor([[1.0, 0.0], [3.0, 0.0]])
    assert torque_r2(target, target) == 1.0
    assert torque_r2(torch.tensor([[2.0, 0.0], [2.0, 0.0]]), target) == pytest.approx(0.0)


def test_unactuated_dof_gets_the_stage_scale_not_the_floor() -> None:
    """The acrobot's shoulder (tau = 0) is scaled like the elbow times the stage's factor."""
    system, data = _data("acrobot", 64)
    cfg = IdentifyConfig.quick(unactuated_scales=(10.0, 1.0))
    model = make_model(system, cfg)
    elbow = data[keys.TAU][:, 1].std()
    for stage, factor in ((0, 10.0), (1, 1.0), (5, 1.0)):
        model.unactuated_torque_scale = cfg.unactuated_scale(stage)
        model.fit_normalization(data)
        torch.testing.assert_close(model.tau_scale, torch.stack([factor * elbow, elbow]))


def test_untrained_model_conserves_its_own_energy() -> None:
    """Without dissipation the Lagrangian structure conserves T + V whatever the weights."""
    system, data = _data("arm2", 8)
    model = make_model(system, IdentifyConfig.quick())
    drift = passive_energy_drift(model, data[keys.Q], data[keys.QD], data[keys.Q], 200, 0.005)
    assert drift.shape == (8,) and (drift < 1e-6).all()
    reference = mujoco_energy_drift(system, data[keys.Q], data[keys.QD], data[keys.Q], 200, 0.005)
    assert reference.shape == (8,) and (reference < 1e-3).all()  # MuJoCo's model, same RK4


def test_quick_suite_writes_every_metric(tmp_path: Path) -> None:
    out = tmp_path / "identify.jsonl"
    writer = RecordWriter(out)
    for record in run_identify(IdentifyConfig.quick()):
        writer.write(record)
    records = read_records(out)
    assert {(r["case"], r["metric"]) for r in records} == {(s, m) for s in SYSTEMS for m in METRICS}
    for r in records:
        assert set(BASE_FIELDS) <= set(r) and r["suite"] == "identify", r
        assert math.isfinite(r["value"]) and r["n_samples"] == 64 and r["epochs"] >= 1, r
        assert len(r["damping_learned"]) == r["dof"] == len(r["damping_mjcf"])


def test_suite_is_registered_and_reads_its_options() -> None:
    assert "identify" in SUITE_NAMES and get_suite("identify") is run_identify_suite
    base = IdentifySuiteConfig()
    cfg = suite_config(replace(base, n_samples=100), quick=True)
    assert cfg.n_samples == 100 and cfg.max_epochs == IdentifyConfig.quick().max_epochs
    assert suite_config(replace(base, max_epochs=7)) == replace(IdentifyConfig(), max_epochs=7)
    assert suite_config(base) == IdentifyConfig()


def test_short_pendulum_fit_finds_the_mass_and_the_damping_direction() -> None:
    """A weak but real check: 300 samples, about a second of training."""
    cfg = IdentifyConfig(
        n_samples=300,
        n_test=100,
        max_epochs=45,
        batch_size=32,
        stages=1,
        patience=45,
        energy_steps=50,
        systems=("pendulum",),
    )
    initial = F.softplus(make_model(load_system("pendulum"), cfg).dynamics.dissipation.raw_viscous)
    fit, metrics = identify_system("pendulum", cfg)
    assert metrics.mass_matrix_rel_error_median < 0.2
    assert metrics.gravity_rel_error_median < 0.2
    assert metrics.torque_r2 > 0.9
    learned, true = metrics.details["damping_learned"][0], metrics.details["damping_mjcf"][0]
    assert initial.item() < learned < true  # started below the MJCF value and moved up
    assert fit.model.dynamics.dissipation.raw_coulomb is None  # no Coulomb term in this fit
