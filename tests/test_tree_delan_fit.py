"""Fit's `model=tree_delan`: DeLaN with the arm's known kinematic tree under it. The tree's
M is MuJoCo's (linear in the inertials: the start's share of `mj_fullM`, plus the armature
start where the MJCF gives none), the fitted model
is positive definite, reloads to the same torques, and needs an MJCF."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan import keys
from mbrl_delan.conf.checks import ConfigError, compose_config
from mbrl_delan.conf.fitting import (
    FIT_CONFIG_DIR,
    build_system_model,
    inverse_data,
    validate_fit_config,
)
from mbrl_delan.fit_run import _run
from mbrl_delan.models.inverse import DeLaNInverse
from mbrl_delan.models.tree import TreeDynamics
from mbrl_delan.runs import load_fit_model
from mbrl_delan.systems.arms import arm_model

SMALL = ["data=excitation", "data.robot=ur5e", "data.samples=1000", "model=tree_delan",
         "logger=none", "epochs=2", "model.hidden=16", "threads=1"]  # fmt: skip


def test_the_trees_mass_matrix_is_mujocos_at_the_starts_share() -> None:
    """M_tree(q) = 0.5 mj_fullM(q) + the armature start, 0.01 of the start's M(qpos0)
    diagonal (the MJCF gives none); with armature_start=0, exactly 0.5 mj_fullM(q)."""
    truth = arm_model("ur5e")
    mj = mujoco.MjData(truth)
    mujoco.mj_forward(truth, mj)
    home = np.zeros((6, 6))
    mujoco.mj_fullM(truth, mj, home)
    for share in (0.01, 0.0):
        cfg = compose_config(FIT_CONFIG_DIR, [*SMALL, "model.prior_scale=0.5",
                                              f"model.armature_start={share}"])  # fmt: skip
        data = inverse_data(cfg.data)
        model = build_system_model(cfg, data.system).double()
        assert isinstance(model, DeLaNInverse) and isinstance(model.dynamics, TreeDynamics)
        q = data.splits["train"][keys.Q][::100]
        with torch.no_grad():
            tree = model.dynamics.tree.mass_matrix(q).numpy()
        armature = np.diag(share * 0.5 * np.diag(home))
        for qi, mi in zip(q.numpy(), tree, strict=True):
            mj.qpos[:] = qi
            mujoco.mj_forward(truth, mj)
            full = np.zeros((6, 6))
            mujoco.mj_fullM(truth, mj, full)
            np.testing.assert_allclose(mi, 0.5 * full + armature, rtol=1e-6, atol=1e-9)


def test_a_tree_delan_fit_is_positive_definite_and_reloads(tmp_path) -> None:
    summary, model = _run(compose_config(FIT_CONFIG_DIR, SMALL), tmp_path / "run")
    assert summary["model"] == "tree_delan" and summary["positive_definite_fraction"] == 1.0
    assert 0 < summary["mass_matrix_error"]["test"] < 1
    _, again = load_fit_model(tmp_path / "run")
    q = torch.randn(5, 6, dtype=torch.float64)
    qd, qdd = torch.randn_like(q), torch.randn_like(q)
    with torch.no_grad():
        torch.testing.assert_close(again.predict_torque(q, qd, qdd),
                                   model.predict_torque(q, qd, qdd))  # fmt: skip


def test_tree_delan_without_a_model_file_is_a_config_error(tmp_path) -> None:
    path = tmp_path / "d.npz"
    np.savez(path, q=np.zeros((4, 2)), qd=np.zeros((4, 2)), tau=np.zeros((4, 2)), dt=0.01)
    overrides = ["data=arrays", f"data.path={path}", "data.joints=[hinge,hinge]",
                 "model=tree_delan", "logger=none"]  # fmt: skip
    with pytest.raises(ConfigError, match="model=tree_delan needs the robot's kinematic tree"):
        _run(compose_config(FIT_CONFIG_DIR, overrides), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_the_coulomb_terms_width_is_the_model_groups() -> None:
    """``model.coulomb_velocity`` v: the Coulomb force is F tanh(qd / v) (at qd = v, F
    tanh(1) beside the viscous D qd); v <= 0 is a config error naming the key."""
    cfg = compose_config(FIT_CONFIG_DIR, [*SMALL, "model.coulomb_velocity=0.002"])
    data = inverse_data(cfg.data)
    model = build_system_model(cfg, data.system).double()
    friction = model.dynamics.dissipation
    assert friction.coulomb_velocity == 0.002
    qd = torch.full((1, 6), 0.002, dtype=torch.float64)
    with torch.no_grad():
        coulomb = friction(qd) - friction.viscous * qd
        expected = friction.coulomb_scale * torch.nn.functional.softplus(friction.raw_coulomb)
    torch.testing.assert_close(coulomb[0], expected * math.tanh(1.0))
    bad = compose_config(FIT_CONFIG_DIR, [*SMALL, "model.coulomb_velocity=0"])
    with pytest.raises(ConfigError, match="model.coulomb_velocity=0"):
        validate_fit_config(bad)
