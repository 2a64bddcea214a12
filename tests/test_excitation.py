"""The shipped real arms and their excitation data: trajectories inside the limits, MuJoCo's
inverse dynamics exact (forward(inverse) = identity, the parts sum to tau), friction
dissipative, velocities from measured positions, and the arrays schema."""

from __future__ import annotations

import json
import tempfile
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest

from mbrl_delan import keys
from mbrl_delan.conf.checks import ConfigError, compose_config
from mbrl_delan.conf.fitting import FIT_CONFIG_DIR
from mbrl_delan.data.arrays import read_arrays, save_arrays
from mbrl_delan.data.excitation import (
    ExcitationSettings,
    excitation_arrays,
    fourier_trajectories,
    inverse_dynamics,
    mass_matrix_error,
)
from mbrl_delan.evaluate import evaluate_run
from mbrl_delan.fit_run import _run
from mbrl_delan.systems.arms import (
    ARMS,
    FRICTION,
    arm,
    arm_model,
    coulomb_friction,
    torque_limits,
)

# published totals of the link masses (kg), base and hand included
MASSES = {"panda": 17.422, "iiwa14": 30.61, "ur5e": 20.995, "slim7": 8.6, "light6": 4.6}
DOF = {"panda": 7, "iiwa14": 7, "ur5e": 6, "slim7": 7, "light6": 6}
# slow (10 s periods of 5 harmonics) and noise-free: differences of q are close to qd
QUIET = ExcitationSettings(
    samples=300, period_s=10.0, harmonics=5, q_noise=0.0, tau_noise=0.0, cutoff_hz=None
)


@pytest.mark.parametrize("robot", list(ARMS))
def test_arms_carry_their_published_masses_and_friction_only_when_asked(robot: str) -> None:
    plain, rough = arm_model(robot), arm_model(robot, "frictionloss")
    assert plain.nv == DOF[robot] and plain.nu == DOF[robot]
    assert plain.body_mass.sum() == pytest.approx(MASSES[robot], abs=1e-3)
    assert not plain.dof_damping.any() and not plain.dof_frictionloss.any()
    assert not plain.dof_armature.any()
    limits = torque_limits(plain)
    np.testing.assert_allclose(rough.dof_damping, FRICTION.viscous * limits)
    np.testing.assert_allclose(rough.dof_frictionloss, FRICTION.coulomb * limits)
    np.testing.assert_allclose(rough.dof_armature, FRICTION.armature * limits)
    real = arm_model(robot, "coulomb_viscous")  # Coulomb as f sign(qd), not MuJoCo's
    np.testing.assert_allclose(real.dof_damping, rough.dof_damping)
    assert not real.dof_frictionloss.any()
    np.testing.assert_allclose(coulomb_friction(robot, "coulomb_viscous"), rough.dof_frictionloss)
    assert not coulomb_friction(robot, "frictionloss").any()
    assert arm_model(robot, True).dof_frictionloss.any()  # true: frictionloss (saved runs)
    with pytest.raises(ValueError, match="neither a shipped arm .*panda.*nor an MJCF file"):
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
    assert summary["samples"] == {"train": 2000, "val": 400, "test": 600}  # 15 x 2 s: 10/2/3
    assert summary["splits"]["val"] == "whole training trajectories"
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
    with pytest.raises(ConfigError, match=r"data.robot='ur10' is not valid; .*panda, iiwa14.*"
                                          r"or give an MJCF file"):  # fmt: skip
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
    assert summary["samples"] == {"train": 2600, "val": 400, "test": 600}
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


TWO_LINK = """<mujoco model="two_link">
  <option timestep="0.002"><flag contact="disable"/></option>
  <worldbody>
    <body name="upper">
      <inertial mass="1.0" pos="0 0 0.15" diaginertia="0.01 0.01 0.001"/>
      <joint name="shoulder" type="hinge" axis="0 1 0" range="-2 2"/>
      <body name="lower" pos="0 0 0.3">
        <inertial mass="0.5" pos="0 0 0.1" diaginertia="0.003 0.003 0.0005"/>
        <joint name="elbow" type="hinge" axis="0 1 0" range="-2.5 2.5"/>
        <body name="slider" pos="0 0 0.2">
          <inertial mass="0.2" pos="0 0 0" diaginertia="1e-4 1e-4 1e-4"/>
          <joint name="extend" type="slide" axis="0 0 1" range="0 0.5"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="shoulder" gear="20" ctrlrange="-1 1"/>
    <motor joint="elbow" gear="8" ctrlrange="-1 1"/>
    <motor joint="extend" gear="30" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""


@pytest.mark.parametrize("design", ["fourier", "sinusoids", "point_to_point"])
def test_every_design_stays_inside_the_limits_with_its_exact_derivatives(design: str) -> None:
    """Sample trajectories of a user's MJCF (hinges and a slide) inside the ranges, speeds
    and motors' torques; qd and qdd the design's own derivatives (central differences of the
    noise-free, unfiltered signals agree to O(dt^2))."""
    settings = ExcitationSettings(samples=2000, design=design, q_noise=0.0, tau_noise=0.0,
                                  cutoff_hz=None, rate_hz=400.0, centres="random")  # fmt: skip
    path = "tests_two_link.xml"
    with pytest.MonkeyPatch.context() as mp, tempfile.TemporaryDirectory() as tmp:
        mp.chdir(tmp)
        Path(path).write_text(TWO_LINK)
        data = excitation_arrays(path, "coulomb_viscous", settings, seed=0)
        model = arm_model(path)
    low, high = model.jnt_range[:, 0], model.jnt_range[:, 1]
    mid, half = (low + high) / 2, (high - low) / 2
    assert (np.abs(data["q"] - mid) <= 0.8 * half + 1e-9).all()
    assert (np.abs(data["qd"]) <= 0.8 * np.array([2.0, 2.0, 0.5]) + 1e-9).all()  # defaults
    assert (np.abs(data["tau"]) <= torque_limits(model)).all()
    assert data["q"].std(0).min() > 0.1 * half.min()  # every joint moves
    dt = 1.0 / settings.rate_hz
    for f, df in (("q", "qd"), ("qd", "qdd")):
        for k in np.unique(data["trajectory"]):
            rows = data["trajectory"] == k
            err = np.gradient(data[f][rows], dt, axis=0)[2:-2] - data[df][rows][2:-2]
            assert np.abs(err).max() < 0.02 * np.abs(data[df]).max(), (f, k)


def test_coulomb_viscous_friction_is_damping_and_sign_of_velocity() -> None:
    data = excitation_arrays("light6", "coulomb_viscous", replace(QUIET, samples=1000), 0)
    model = arm_model("light6", "coulomb_viscous")
    coulomb = coulomb_friction("light6", "coulomb_viscous")
    parts = sum(data[k] for k in (keys.TAU_INERTIAL, keys.TAU_CORIOLIS, keys.TAU_GRAVITY))
    # qd here: differences of q (O(dt^2)), the law's own qd to within 1e-3 of its range
    law = model.dof_damping * data["qd"] + coulomb * np.sign(data["qd"])
    moving = np.abs(data["qd"]) > 0.05
    np.testing.assert_allclose((data["tau"] - parts)[moving], law[moving], atol=2e-3)
    np.testing.assert_allclose(data[keys.TAU_FRICTION], data["tau"] - parts, atol=1e-9)


def test_fit_on_a_users_mjcf_tests_on_another_design(tmp_path, monkeypatch) -> None:
    """``fit data=excitation data.robot=<MJCF path>``: an arm the package does not ship, its
    test trajectories of another design, whole trajectories validating; an MJCF with a ball
    joint, a missing file and a bad design are one-line config errors."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "arm.xml").write_text(TWO_LINK)
    overrides = ["data=excitation", "data.robot=arm.xml", "data.samples=2000",
                 "data.test_design=point_to_point", "model=white_box", "logger=none",
                 "threads=1"]  # fmt: skip
    summary, _ = _run(compose_config(FIT_CONFIG_DIR, overrides), tmp_path / "run")
    # the small arm's measured accelerations (1e-4 rad of noise on q, differentiated twice)
    # hold the test R^2 of its own true dynamics at 0.979
    assert summary["robot"] == "arm.xml" and summary["test_r2"] > 0.95
    assert summary["splits"]["test"] == "trajectories of their own (design point_to_point, seed 1)"
    assert summary["mass_matrix_error"]["test"] < 0.02
    assert set(summary["final"]["test"]["trajectories"]) == {"test:0", "test:1"}
    (tmp_path / "ball.xml").write_text(TWO_LINK.replace('type="hinge" axis="0 1 0" range="-2 2"',
                                                        'type="ball"'))  # fmt: skip
    for bad, message in [
        ("data.robot=ball.xml", "joint shoulder is a ball joint"),
        ("data.robot=none.xml", "data.robot='none.xml': no such MJCF file"),
        ("data.design=chirp", "data.design='chirp' is not valid"),
        ("data.friction=stribeck", "data.friction='stribeck' is not valid"),
    ]:
        with pytest.raises(ConfigError, match=message):
            _run(compose_config(FIT_CONFIG_DIR, [*overrides, bad]), tmp_path / "bad")
        assert not (tmp_path / "bad").exists()
