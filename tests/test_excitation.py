"""The shipped real arms and their excitation data: trajectories inside the limits, MuJoCo's
inverse dynamics exact (forward(inverse) = identity, the parts sum to tau), friction
dissipative, velocities from measured positions, and the arrays schema."""

from __future__ import annotations

import json
from dataclasses import replace

import mujoco
import numpy as np
import pytest

from mbrl_delan import keys
from mbrl_delan.conf.checks import ConfigError, compose_config
from mbrl_delan.conf.fitting import FIT_CONFIG_DIR, _run
from mbrl_delan.data.arrays import read_arrays, save_arrays
from mbrl_delan.data.excitation import (
    ExcitationSettings,
    excitation_arrays,
    fourier_trajectories,
    inverse_dynamics,
    mass_matrix_error,
)
from mbrl_delan.evaluate import evaluate_run
from mbrl_delan.systems.arms import ARMS, FRICTION, arm, arm_model, torque_limits

# published totals of the link masses (kg), base and hand included
MASSES = {"panda": 17.422, "iiwa14": 30.61, "ur5e": 20.995}
DOF = {"panda": 7, "iiwa14": 7, "ur5e": 6}
# slow (10 s periods of 5 harmonics) and noise-free: differences of q are close to qd
QUIET = ExcitationSettings(
    samples=300, period_s=10.0, harmonics=5, q_noise=0.0, tau_noise=0.0, cutoff_hz=None
)


@pytest.mark.parametrize("robot", list(ARMS))
def test_arms_carry_their_published_masses_and_friction_only_when_asked(robot: str) -> None:
    plain, rough = arm_model(robot), arm_model(robot, friction=True)
    assert plain.nv == DOF[robot] and plain.nu == DOF[robot]
    assert plain.body_mass.sum() == pytest.approx(MASSES[robot], abs=1e-3)
    assert not plain.dof_damping.any() and not plain.dof_frictionloss.any()
    assert not plain.dof_armature.any()
    limits = torque_limits(plain)
    np.testing.assert_allclose(rough.dof_damping, FRICTION.viscous * limits)
    np.testing.assert_allclose(rough.dof_frictionloss, FRICTION.coulomb * limits)
    np.testing.assert_allclose(rough.dof_armature, FRICTION.armature * limits)
    with pytest.raises(ValueError, match="not a shipped arm; choose one of: panda"):
        arm("panda7")


@pytest.mark.parametrize("robot", list(ARMS))
def test_fourier_trajectories_stay_inside_the_ranges_and_speed_limits(robot: str) -> None:
    model = arm_model(robot)
    limit = np.array(arm(robot).max_velocity)
    x = fourier_trajectories(model, limit, 4, ExcitationSettings(), np.random.default_rng(0))
    low, high = model.jnt_range[:, 0], model.jnt_range[:, 1]
    assert (x.q >= low).all() and (x.q <= high).all()
    assert (np.abs(x.qd) <= 0.8 * limit + 1e-12).all()
    assert np.isclose(np.abs(x.qd).max(1), 0.8 * limit).any(axis=-1).all()  # a limit reached
    # the derivatives are the series' own: central differences agree to O(dt^2), at most
    # (W dt)^2 / 6 of the derivative for the highest harmonic W = L 2 pi / T
    settings, dt = ExcitationSettings(), x.t[1]
    bound = (settings.harmonics * 2 * np.pi / settings.period_s * dt) ** 2 / 6
    for f, df in ((x.q, x.qd), (x.qd, x.qdd)):
        err = np.gradient(f, dt, axis=1)[:, 1:-1] - df[:, 1:-1]
        assert np.abs(err).max() < bound * np.abs(df).max()


def test_forward_of_the_inverse_torques_gives_the_accelerations_back() -> None:
    model = arm_model("panda")
    x = fourier_trajectories(model, np.array(arm("panda").max_velocity), 1, QUIET,
                             np.random.default_rng(1))  # fmt: skip
    q, qd, qdd = x.q[0, ::50], x.qd[0, ::50], x.qdd[0, ::50]
    forces = inverse_dynamics(model, q, qd, qdd)
    parts = sum(forces[k] for k in (keys.TAU_INERTIAL, keys.TAU_CORIOLIS, keys.TAU_GRAVITY))
    np.testing.assert_allclose(parts, forces["tau"], rtol=1e-9, atol=1e-9)
    data = mujoco.MjData(model)
    for i in range(q.shape[0]):
        data.qpos[:], data.qvel[:], data.qfrc_applied[:] = q[i], qd[i], forces["tau"][i]
        mujoco.mj_forward(model, data)
        np.testing.assert_allclose(data.qacc, qdd[i], rtol=1e-7, atol=1e-7)


def test_joint_friction_takes_power_from_the_motors() -> None:
    """With friction the torques exceed the rigid body's by a force along the motion."""
    data = excitation_arrays("iiwa14", True, replace(QUIET, samples=1000), seed=0)
    parts = sum(data[k] for k in (keys.TAU_INERTIAL, keys.TAU_CORIOLIS, keys.TAU_GRAVITY))
    friction = data["tau"] - parts
    np.testing.assert_allclose(data[keys.TAU_FRICTION], friction, atol=1e-9)  # before noise
    moving = np.abs(data["qd"]) > 0.05
    assert (friction[moving] * data["qd"][moving] > 0).mean() > 0.99
    model = arm_model("iiwa14", True)
    assert (np.abs(data["tau"]) <= torque_limits(model)).all()  # what the motors can give
    bound = model.dof_damping * np.abs(data["qd"]) + model.dof_frictionloss
    assert (np.abs(friction) <= 1.01 * bound).all()  # qd here: differences of q (O(dt^2))


def test_measured_velocities_follow_the_true_ones_and_the_file_is_the_arrays_schema(
    tmp_path,
) -> None:
    settings = ExcitationSettings(samples=2000)
    data = excitation_arrays("ur5e", False, settings, seed=3)
    quiet = excitation_arrays("ur5e", False, replace(settings, q_noise=0.0, tau_noise=0.0), 3)
    err = np.sqrt(((data["qd"] - quiet["qd"]) ** 2).mean()) / np.sqrt((quiet["qd"] ** 2).mean())
    assert err < 0.02  # filtered differences of noisy positions
    tau_err = (data["tau"] - quiet["tau"]).std(0) / np.sqrt((quiet["tau"] ** 2).mean(0))
    np.testing.assert_allclose(tau_err, settings.tau_noise, rtol=0.15)
    assert len(np.unique(data["trajectory"])) == 10 and data["q"].shape == (2000, 6)  # 2 s
    back = read_arrays(save_arrays(data, tmp_path / "ur5e.npz"))
    for name in ("q", "qd", "tau", "t", "trajectory", keys.TAU_GRAVITY):
        np.testing.assert_allclose(back[name], data[name])


def test_fit_on_excitation_data_learns_and_evaluates_from_its_provenance(tmp_path) -> None:
    """``fit data=excitation``: the data generated from the config, split by trajectory, the
    DeLaN built on the arm's tree; `evaluate` regenerates the same data and reproduces the
    summary, with the true parts' errors."""
    overrides = ["data=excitation", "data.robot=ur5e", "data.samples=3000", "model=delan",
                 "logger=none", "epochs=3", "model.hidden=16", "threads=1"]  # fmt: skip
    summary, _ = _run(compose_config(FIT_CONFIG_DIR, overrides), tmp_path)
    assert summary["data"] == "excitation" and summary["robot"] == "ur5e"
    assert summary["samples"] == {"train": 2160, "val": 240, "test": 600}  # 15 x 2 s
    first = json.loads((tmp_path / "metrics.jsonl").read_text().splitlines()[0])
    assert summary["final"]["train"]["mse"] < first["train_mse"]
    result = evaluate_run(tmp_path)
    assert result["splits"]["test"]["mse"] == pytest.approx(summary["final"]["test"]["mse"])
    assert summary["mass_matrix_error"]["test"] > 0  # the arm's M known: the error measured
    components = result["splits"]["test"]["components"]
    assert set(components) == {
        keys.TAU_INERTIAL, keys.TAU_CORIOLIS, keys.TAU_GRAVITY, keys.TAU_FRICTION
    }  # fmt: skip
    assert components[keys.TAU_FRICTION]["rel_error"] is None  # the arm has no friction


def test_an_unknown_robot_is_a_config_error_naming_the_choices(tmp_path) -> None:
    cfg = compose_config(FIT_CONFIG_DIR, ["data=excitation", "data.robot=ur10", "logger=none"])
    with pytest.raises(ConfigError, match=r"data.robot='ur10' is not valid; .*panda, iiwa14"):
        _run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_trajectories_past_a_motors_limit_are_shrunk_within_it() -> None:
    """One-second periods drive the Panda's shoulder past 87 N m before shrinking."""
    fast = replace(QUIET, samples=1000, period_s=1.0)
    model = arm_model("panda")
    limit = np.array(arm("panda").max_velocity)
    raw = fourier_trajectories(model, limit, 10, fast, np.random.default_rng(0))
    flat = raw.q.reshape(-1, 7), raw.qd.reshape(-1, 7), raw.qdd.reshape(-1, 7)
    assert (np.abs(inverse_dynamics(model, *flat)["tau"]) > torque_limits(model)).any()
    data = excitation_arrays("panda", False, fast, seed=0)
    assert (np.abs(data["tau"]) <= torque_limits(model)).all()


def test_excitation_test_seed_draws_the_test_trajectories_apart(tmp_path) -> None:
    overrides = ["data=excitation", "data.robot=ur5e", "data.samples=3000",
                 "data.test_seed=7", "model=mlp", "logger=none", "epochs=1",
                 "model.hidden=16", "threads=1"]  # fmt: skip
    summary, _ = _run(compose_config(FIT_CONFIG_DIR, overrides), tmp_path / "run")
    assert summary["samples"] == {"train": 2700, "val": 300, "test": 600}
    assert set(summary["final"]["test"]["trajectories"]) == {"test:0", "test:1", "test:2"}
    same = compose_config(FIT_CONFIG_DIR, [*overrides, "data.test_seed=0"])
    with pytest.raises(ConfigError, match="data.test_seed=0: the training data's own seed"):
        _run(same, tmp_path / "again")


def test_mass_matrix_error_is_zero_for_the_arms_own_and_relative() -> None:
    q = excitation_arrays("panda", True, replace(QUIET, samples=1000), seed=2)["q"][::100]
    model = arm_model("panda", True)
    data = mujoco.MjData(model)
    own = np.zeros((q.shape[0], 7, 7))
    for i, qi in enumerate(q):
        data.qpos[:] = qi
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, own[i])
    assert mass_matrix_error("panda", True, q, own) < 1e-12
    assert mass_matrix_error("panda", True, q, 1.1 * own) == pytest.approx(0.1)
    assert mass_matrix_error("panda", False, q, own) > 0  # the friction arm's armature


def test_measured_accelerations_hold_up_at_the_trajectories_ends() -> None:
    """The filters see the periodic motion on either side: qdd at a trajectory's first and
    last samples is as close to the true one (M^-1 of the inertial part) as inside."""
    data = excitation_arrays("panda", False, replace(ExcitationSettings(), samples=1000,
                             q_noise=0.0, tau_noise=0.0), seed=0)  # fmt: skip
    model = arm_model("panda")
    mj = mujoco.MjData(model)
    true = np.zeros_like(data["qdd"])
    mass = np.zeros((7, 7))
    for i, qi in enumerate(data["q"]):
        mj.qpos[:] = qi
        mujoco.mj_forward(model, mj)
        mujoco.mj_fullM(model, mj, mass)
        true[i] = np.linalg.solve(mass, data[keys.TAU_INERTIAL][i])
    error = np.abs(data["qdd"] - true).max(1)
    starts = np.flatnonzero(np.diff(data["trajectory"], prepend=-1))
    ends = np.r_[starts[1:] - 1, len(error) - 1]
    inside = np.ones(len(error), dtype=bool)
    inside[np.r_[starts, ends]] = False
    assert error[starts].max() < 2 * error[inside].max()
    assert error[ends].max() < 2 * error[inside].max()
    assert error.max() < 0.05 * np.abs(true).max()
