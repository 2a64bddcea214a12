"""DeLaN on a floating-base humanoid: inverse dynamics learned from MuJoCo, M and g recovered."""

import math
import os
from dataclasses import replace

import pytest
import torch

from mbrl_delan import keys
from mbrl_delan.benchmarks.humanoid_identify import (
    HumanoidIdentifyConfig,
    humanoid_system,
    identify_humanoid,
)
from mbrl_delan.data.synthetic import inverse_dynamics_dataset


def test_inverse_dynamics_data_satisfy_mujoco_equations() -> None:
    """tau = M qdd + qfrc_bias - passive, checked against mj_fullM independently of mj_inverse."""
    import mujoco
    import numpy as np

    system = humanoid_system("humanoid")
    data = inverse_dynamics_dataset(system, 8, torch.Generator().manual_seed(0))
    model = system.mj_model()
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    mj = mujoco.MjData(model)
    mass = np.zeros((model.nv, model.nv))
    for i in range(8):
        mj.qpos[:], mj.qvel[:] = data[keys.Q][i].numpy(), data[keys.QD][i].numpy()
        mujoco.mj_forward(model, mj)
        mujoco.mj_fullM(model, mj, mass)
        tau = mass @ data[keys.QDD][i].numpy() + mj.qfrc_bias - mj.qfrc_passive
        np.testing.assert_allclose(data[keys.TAU][i].numpy(), tau, rtol=1e-6, atol=1e-6)
    quat = data[keys.Q][:, 3:7]
    torch.testing.assert_close(quat.norm(dim=-1), torch.ones(8, dtype=torch.float64))


def test_quick_identification_runs_and_reports_every_metric() -> None:
    cfg = HumanoidIdentifyConfig.quick()
    result = identify_humanoid("humanoid", cfg)
    assert set(result.metrics) == {
        "torque_r2",
        "mass_matrix_rel_error_median",
        "gravity_rel_error_median",
        "damping_rel_error",
    }
    assert all(math.isfinite(v) for v in result.metrics.values())
    M = result.model.terms(*(torch.zeros(4, 24), torch.zeros(4, 23))).mass_matrix
    assert (torch.linalg.eigvalsh(M) > 0).all()


@pytest.mark.slow
@pytest.mark.heavy
def test_humanoid_v5_identified_from_8000_samples() -> None:
    """A quarter of the benchmark's data and 60 epochs, eager (22 s on one core): held-out
    torque R^2 0.935, M and g to 16% and 10% on the 2-core AMD host; asserted with margin.
    The benchmark's own settings reach R^2 >= 0.98 (`test_humanoid_v5_torque_r2_at_least_098`,
    100 s: run it with MBRL_DELAN_ACCEPTANCE=1, or `suite=identify_humanoid`)."""
    base = HumanoidIdentifyConfig(systems=("humanoid",), compile=False)
    cfg = replace(base, n_samples=8000, fit=replace(base.fit, max_epochs=60))
    metrics = identify_humanoid("humanoid", cfg).metrics
    assert metrics["torque_r2"] >= 0.9, metrics
    assert metrics["mass_matrix_rel_error_median"] < 0.25, metrics
    assert metrics["gravity_rel_error_median"] < 0.15, metrics


@pytest.mark.skipif(
    not os.environ.get("MBRL_DELAN_ACCEPTANCE"),
    reason="the benchmark's settings take 100 s: MBRL_DELAN_ACCEPTANCE=1 runs it",
)
def test_humanoid_v5_torque_r2_at_least_098() -> None:
    """R^2 >= 0.98 on held-out states of Humanoid-v5 (contacts, limits off), at the
    benchmark's settings."""
    result = identify_humanoid("humanoid", HumanoidIdentifyConfig(systems=("humanoid",)))
    assert result.metrics["torque_r2"] >= 0.98, result.metrics
