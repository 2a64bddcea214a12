"""The white box of an arm: the regressor is MuJoCo's inverse dynamics exactly, least squares
recovers a known arm from noise-free data, identified inertias are physically consistent, and
friction stays at zero on frictionless data."""

from __future__ import annotations

import copy
from dataclasses import replace

import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from mbrl_delan.conf.checks import ConfigError, compose_config
from mbrl_delan.conf.fitting import FIT_CONFIG_DIR
from mbrl_delan.data.excitation import (
    ExcitationSettings,
    excitation_arrays,
    inverse_dynamics,
    mass_matrix_error,
)
from mbrl_delan.fit_run import _run
from mbrl_delan.models.inertial import (
    cholesky_of_pi,
    inertial_parameters,
    moving_bodies,
    physically_consistent,
    pi_from_cholesky,
    pseudo_inertia,
    set_inertial_parameters,
)
from mbrl_delan.models.rigid_body import WhiteBoxInverse, regressor
from mbrl_delan.runs import load_fit_model
from mbrl_delan.systems.arms import arm_model, coulomb_friction

# noise-free; 3 harmonics: the unfiltered differences' O(dt^2) error (qd, qdd) stays below the
# tolerances of the identification's checks
QUIET = ExcitationSettings(samples=3000, harmonics=3, q_noise=0.0, tau_noise=0.0, cutoff_hz=None)


def _states(model: mujoco.MjModel, n: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    low, high = model.jnt_range[:, 0], model.jnt_range[:, 1]
    q = low + (high - low) * rng.uniform(0.1, 0.9, size=(n, model.nv))
    return q, rng.normal(size=(n, model.nv)), rng.normal(size=(n, model.nv))


def _parameters(model: mujoco.MjModel) -> np.ndarray:
    inertials = [inertial_parameters(model, b) for b in moving_bodies(model)]
    return np.concatenate([*inertials, model.dof_damping, model.dof_frictionloss,
                           model.dof_armature])  # fmt: skip


def test_a_bodys_parameters_go_into_mujoco_and_back() -> None:
    model = arm_model("ur5e")
    other = copy.copy(model)
    for body in moving_bodies(model):
        pi = inertial_parameters(model, body)
        set_inertial_parameters(other, body, 1.3 * pi)  # a heavier, consistent body
        np.testing.assert_allclose(inertial_parameters(other, body), 1.3 * pi, atol=1e-12)
        np.testing.assert_allclose(pi_from_cholesky(cholesky_of_pi(pi)), pi, rtol=1e-7, atol=1e-12)


def test_the_regressor_times_the_parameters_is_mujocos_inverse_dynamics() -> None:
    """tau = Y p at another arm's inertials than the one Y is taken about (exact: tau is
    linear in them), friction and armature included away from zero velocity."""
    truth = arm_model("panda", friction=True)
    start = copy.copy(truth)
    bodies = moving_bodies(truth)
    for body in bodies:
        set_inertial_parameters(start, body, 0.5 * inertial_parameters(truth, body))
    q, qd, qdd = _states(truth, 40, seed=0)
    qd = qd + np.sign(qd)  # |qd| > 1: MuJoCo's frictionloss at its bound
    tau = inverse_dynamics(truth, q, qd, qdd)["tau"]
    Y = regressor(start, bodies, q, qd, qdd, "frictionloss")
    np.testing.assert_allclose(Y @ _parameters(truth), tau, rtol=1e-7, atol=1e-7)


def test_cholesky_parameters_are_always_physically_consistent() -> None:
    rng = np.random.default_rng(0)
    for theta in rng.normal(scale=2.0, size=(200, 10)):
        pi = pi_from_cholesky(theta)
        assert physically_consistent(pi)
        inertia = np.array([[pi[4], pi[7], pi[8]], [pi[7], pi[5], pi[9]], [pi[8], pi[9], pi[6]]])
        com = pi[1:4] / pi[0]
        about_com = np.linalg.eigvalsh(
            inertia - pi[0] * (com @ com * np.eye(3) - np.outer(com, com))
        )
        a, b, c = about_com
        assert pi[0] > 0 and a > 0 and a + b >= c * (1 - 1e-9)  # triangle inequality
    bad = np.array([1.0, 0, 0, 0, -1.0, 1.0, 1.0, 0, 0, 0])  # a negative inertia
    assert not physically_consistent(bad)
    projected = pi_from_cholesky(cholesky_of_pi(bad))
    assert physically_consistent(projected)
    assert np.linalg.eigvalsh(pseudo_inertia(projected))[0] > 0


@pytest.mark.parametrize(
    ("friction", "law"),
    [("none", "coulomb_viscous"), ("frictionloss", "frictionloss"),
     ("coulomb_viscous", "coulomb_viscous")],
)  # fmt: skip
def test_least_squares_recovers_a_known_arm_from_noise_free_data(friction: str, law: str) -> None:
    """From the documented wrong start (inertials x 0.5, no friction), with the friction law
    the data were made by: the identified arm's torques on other trajectories, its M,
    friction and armature are the true arm's (the base parameters: a chain's link masses are
    not each identifiable) and its bodies physically consistent; on the frictionless arm the
    friction stays at zero."""
    data = excitation_arrays("panda", friction, QUIET, seed=0)
    td = TensorDict({k: torch.as_tensor(data[k]) for k in ("q", "qd", "qdd", "tau")},
                    batch_size=[data["q"].shape[0]])  # fmt: skip
    model = WhiteBoxInverse(arm_model("panda"), friction_law=law)
    model.fit_normalization(td)
    model.identify(td)
    assert model.consistent()
    held = excitation_arrays("panda", friction, replace(QUIET, samples=400), seed=1)
    pred = model.predict_torque(*(torch.as_tensor(held[k]) for k in ("q", "qd", "qdd")))
    assert np.abs(pred.numpy() - held["tau"]).max() < 5e-3 * np.abs(held["tau"]).max()
    mass = model.mass_matrix(torch.as_tensor(held["q"][::20])).numpy()
    assert mass_matrix_error("panda", friction, held["q"][::20], mass) < 0.005
    truth, rough = arm_model("panda", friction), arm_model("panda", "frictionloss")
    found = {"dof_damping": model.viscous, "dof_armature": model.armature,
             "dof_frictionloss": model.coulomb}  # fmt: skip
    coulomb = coulomb_friction("panda", friction) + truth.dof_frictionloss  # one of them is 0
    for name, share in (("dof_damping", 0.05), ("dof_frictionloss", 0.05), ("dof_armature", 0.1)):
        true = coulomb if name == "dof_frictionloss" else getattr(truth, name)
        error = np.abs(found[name].numpy() - true)[1:]  # joint 1's armature:
        assert (error <= share * getattr(rough, name)[1:]).all(), name  # link 1's inertia too


@pytest.mark.parametrize("law", ["coulomb_viscous", "frictionloss"])
def test_the_white_boxs_forward_dynamics_inverts_its_inverse_dynamics(law: str) -> None:
    """acceleration(q, qd, predict_torque(q, qd, qdd)) = qdd under either friction law,
    with friction, armature and other inertials than the MJCF's."""
    model = WhiteBoxInverse(arm_model("ur5e"), prior_scale=0.7, friction_law=law)
    model.viscous.fill_(0.5)
    model.coulomb.fill_(2.0)
    model.armature.fill_(0.05)
    q, qd, qdd = (torch.as_tensor(x) for x in _states(arm_model("ur5e"), 30, seed=4))
    tau = model.predict_torque(q, qd, qdd)
    torch.testing.assert_close(model.acceleration(q, qd, tau), qdd, rtol=1e-7, atol=1e-7)


def test_the_white_box_fitted_with_the_wrong_friction_law_misses_the_torques() -> None:
    """On Coulomb + viscous data (f sign(qd)), MuJoCo's soft frictionloss law leaves a test
    error many times the right law's."""
    data = excitation_arrays("ur5e", "coulomb_viscous", QUIET, seed=0)
    held = excitation_arrays("ur5e", "coulomb_viscous", replace(QUIET, samples=400), seed=1)
    td = TensorDict({k: torch.as_tensor(data[k]) for k in ("q", "qd", "qdd", "tau")},
                    batch_size=[data["q"].shape[0]])  # fmt: skip
    errors = {}
    for law in ("coulomb_viscous", "frictionloss"):
        model = WhiteBoxInverse(arm_model("ur5e"), friction_law=law)
        model.fit_normalization(td)
        model.identify(td)
        pred = model.predict_torque(*(torch.as_tensor(held[k]) for k in ("q", "qd", "qdd")))
        errors[law] = float(((pred.numpy() - held["tau"]) ** 2).mean())
    assert errors["frictionloss"] > 10 * errors["coulomb_viscous"]


def test_white_box_fit_identifies_an_arm_and_reloads(tmp_path) -> None:
    overrides = ["data=excitation", "data.robot=ur5e", "data.samples=1000", "model=white_box",
                 "logger=none", "threads=1"]  # fmt: skip
    summary, _ = _run(compose_config(FIT_CONFIG_DIR, overrides), tmp_path / "run")
    assert summary["test_r2"] > 0.999 and summary["mass_matrix_error"]["test"] < 0.01
    assert summary["identified"]["physically_consistent"]
    assert max(summary["identified"]["coulomb"]) < 0.05  # the arm has none
    cfg, model = load_fit_model(tmp_path / "run")
    assert isinstance(model, WhiteBoxInverse)
    masses = list(summary["identified"]["mass"].values())
    np.testing.assert_allclose(model.mujoco_model().body_mass[model.bodies], masses)


def test_white_box_without_a_model_file_is_a_config_error(tmp_path) -> None:
    path = tmp_path / "d.npz"
    np.savez(path, q=np.zeros((4, 2)), qd=np.zeros((4, 2)), tau=np.zeros((4, 2)), dt=0.01)
    overrides = ["data=arrays", f"data.path={path}", "data.joints=[hinge,hinge]",
                 "model=white_box", "logger=none"]  # fmt: skip
    with pytest.raises(ConfigError, match="model=white_box needs the robot's kinematic tree"):
        _run(compose_config(FIT_CONFIG_DIR, overrides), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_delan_friction_stays_near_zero_on_a_frictionless_arm(tmp_path) -> None:
    """The fit defaults start DeLaN's friction at zero: a short fit on frictionless data
    leaves its friction torque far below 1% of the torques' RMS (the old start, 0.69 of the
    unit, is a tenth of them)."""
    overrides = ["data=excitation", "data.robot=ur5e", "data.samples=1000", "model=delan",
                 "logger=none", "epochs=3", "model.hidden=16", "threads=1"]  # fmt: skip
    for name, extra in (("zero", []), ("old", ["friction_init=null"])):
        _run(compose_config(FIT_CONFIG_DIR, [*overrides, *extra]), tmp_path / name)
    data = excitation_arrays("ur5e", False, replace(QUIET, samples=400), seed=5)
    q, qd = (torch.as_tensor(data[k]) for k in ("q", "qd"))
    share = {}
    for name in ("zero", "old"):
        _, model = load_fit_model(tmp_path / name)
        with torch.no_grad():
            friction = model.dynamics.terms(q, qd).dissipation
        share[name] = float(friction.pow(2).mean().sqrt() / np.sqrt((data["tau"] ** 2).mean()))
    assert share["zero"] < 0.001 < 0.01 < share["old"]
