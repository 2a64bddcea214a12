"""The white-box model (`training/whitebox.py`) and the fidelity figures (`training/fidelity.py`):
the MJCF's own rollouts at multipliers 1, identification of perturbed parameters against
their true values, worked answers of the fidelity figures, and the loop end to end."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tiny import TINY_TRAIN

from mbrl_delan import keys
from mbrl_delan.conf.checks import compose_train_config, migrate
from mbrl_delan.envs.real import make_real_env
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.objectives.mujoco import ENV_PHYSICS, mujoco_objective_factory
from mbrl_delan.planners.mppi import MPPIPlanner
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.systems.system import load_system
from mbrl_delan.training.fidelity import CandidateRecorder, build_reference, fidelity_metrics
from mbrl_delan.training.loop import run_episode
from mbrl_delan.training.whitebox import (
    IdentifyConfig,
    MjStepper,
    WhiteBoxModel,
    WhiteBoxSpec,
    contact_groups,
)


@pytest.fixture(scope="module")
def humanoid():
    return make_env_parts("humanoid_stand", None, None)


def _random_transitions(system, model, starts, steps, seed) -> TensorDict:
    """Episodes of uniform random controls from `starts` (q (E, nq), qd (E, nv)) under the
    MjModel `model` at the system's own physics, as the loop's buffer holds them."""
    rng = np.random.default_rng(seed)
    low, high = system.ctrl_low.numpy(), system.ctrl_high.numpy()
    ctrl = rng.uniform(low, high, (starts[0].shape[0], steps, system.nu))
    stepper = MjStepper(model, system.frame_skip)
    q, qd = stepper(model, starts[0], starts[1], ctrl)
    stepper.close()
    q_all = np.concatenate([starts[0][:, None], q], 1)
    qd_all = np.concatenate([starts[1][:, None], qd], 1)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x)).reshape(-1, x.shape[-1])  # noqa: E731
    episode = torch.arange(ctrl.shape[0])[:, None].expand(-1, steps).reshape(-1, 1)
    return TensorDict(
        {
            keys.Q: t(q_all[:, :-1]), keys.QD: t(qd_all[:, :-1]), keys.ACTION: t(ctrl),
            keys.NEXT_Q: t(q_all[:, 1:]), keys.NEXT_QD: t(qd_all[:, 1:]), keys.EPISODE: episode,
        },
        batch_size=[episode.shape[0]],
    )  # fmt: skip


def test_whitebox_at_multipliers_one_rolls_out_exactly_as_the_mjcf(humanoid) -> None:
    """The floor contacts as explicit pairs, the inertials made explicit: random controls
    from standing starts, through falls and impacts, give MuJoCo's own states bit for bit;
    and the groups are the feet and hands apart from the body."""
    system = humanoid.system
    white = WhiteBoxSpec(mujoco.MjSpec.from_file(str(system.xml_path)))
    start = humanoid.task.initial_state((6,), torch.Generator().manual_seed(1))
    ctrl = np.random.default_rng(1).uniform(-0.4, 0.4, (6, 40, system.nu))
    original = system.mj_model()
    stepper = MjStepper(original, system.frame_skip)
    q_mjcf, qd_mjcf = stepper(original, start.q.numpy(), start.qd.numpy(), ctrl)
    rebuilt = white.build(np.ones(len(white.multipliers)))
    q_white, qd_white = stepper(rebuilt, start.q.numpy(), start.qd.numpy(), ctrl)
    stepper.close()
    assert q_mjcf[:, -1, 2].min() < 0.5  # they fell: contacts of every kind happened
    np.testing.assert_array_equal(q_white, q_mjcf)
    np.testing.assert_array_equal(qd_white, qd_mjcf)
    assert set(contact_groups(original)) == {
        "body", "right_foot", "left_foot", "right_lower_arm", "left_lower_arm"
    }  # fmt: skip


def test_multipliers_edit_what_they_name(humanoid) -> None:
    """Each multiplier scales its own value in the compiled model and nothing else: a body's
    mass with its inertia, the joints' damping, one contact group's solref and friction."""
    system = humanoid.system
    white = WhiteBoxSpec(mujoco.MjSpec.from_file(str(system.xml_path)))
    base = white.build(np.ones(len(white.multipliers)))
    theta = np.ones(len(white.multipliers))
    names = white.names
    theta[names.index("mass:pelvis")] = 2.0
    theta[names.index("damping:joints")] = 3.0
    theta[names.index("timeconst:left_foot")] = 4.0
    theta[names.index("friction:left_foot")] = 0.5
    edited = white.build(theta)
    pelvis = edited.body("pelvis").id
    np.testing.assert_allclose(edited.body_mass[pelvis], 2 * base.body_mass[pelvis])
    np.testing.assert_allclose(edited.body_inertia[pelvis], 2 * base.body_inertia[pelvis])
    others = np.arange(base.nbody) != pelvis
    np.testing.assert_array_equal(edited.body_mass[others], base.body_mass[others])
    np.testing.assert_allclose(edited.dof_damping, 3 * base.dof_damping)
    left = edited.pair("floor_left_foot").id
    np.testing.assert_allclose(edited.pair_solref[left], [4 * base.pair_solref[left, 0], 1.0])
    np.testing.assert_allclose(edited.pair_friction[left, :2], 0.5 * base.pair_friction[left, :2])
    right = edited.pair("floor_right_foot").id
    np.testing.assert_array_equal(edited.pair_solref[right], base.pair_solref[right])


def test_identify_recovers_perturbed_masses_of_a_small_system() -> None:
    """A two-link arm whose masses (with their inertias), damping and armature are off by up
    to 2x: least squares on 4-step windows of random-control data finds the true values."""
    system = load_system("arm2", frame_skip=2)
    truth = system.mj_model()
    rng = np.random.default_rng(0)
    starts = (rng.uniform(-2, 2, (16, 2)), rng.uniform(-1, 1, (16, 2)))
    data = _random_transitions(system, truth, starts, 12, seed=0)
    model = WhiteBoxModel(system, identify=IdentifyConfig(window=4, windows=64, iterations=30))
    assert model.white.names == ["mass:link1", "mass:link2", "damping:joints"]
    model.set_multipliers(np.array([1.8, 0.6, 2.0]))
    report = model.identify(data, torch.Generator().manual_seed(0))
    np.testing.assert_allclose(model.theta, [1.0, 1.0, 1.0], atol=1e-4)
    assert report.train_loss[-1] < 1e-8 * report.train_loss[0]


def test_identify_finds_a_humanoids_masses_and_contacts_from_falls(humanoid) -> None:
    """From the documented wrong start (contacts 10x softer, friction halved, masses off by up
    to 50%), 3 falling episodes of random controls identify the body's contact and the
    masses of the trunk and legs within 10%."""
    system = humanoid.system
    start = humanoid.task.initial_state((3,), torch.Generator().manual_seed(0))
    data = _random_transitions(system, system.mj_model(), (start.q.numpy(), start.qd.numpy()),
                               40, seed=3)  # fmt: skip
    model = WhiteBoxModel(system, identify=IdentifyConfig(windows=64, iterations=8), nthread=2)
    model.set_multipliers(model.white.documented_start())
    wrong = model.parameters_by_name()
    model.identify(data, torch.Generator().manual_seed(0))
    found = model.parameters_by_name()
    assert wrong["timeconst:body"] == 10.0 and abs(found["timeconst:body"] - 1) < 0.1
    for body in ("torso", "pelvis", "right_thigh", "left_thigh"):
        assert abs(wrong[f"mass:{body}"] - 1) > 0.05 or body == "torso"
        assert abs(found[f"mass:{body}"] - 1) < 0.1, (body, found[f"mass:{body}"])


@pytest.fixture(scope="module")
def reference(humanoid):
    """The fidelity reference of a short MuJoCo-planned episode (a small MPPI)."""
    system, task = humanoid.system, humanoid.task
    factory = mujoco_objective_factory(system, task, nthread=1)
    recorder = CandidateRecorder(factory, every=3)
    planner = MPPIPlanner(horizon=5, action_low=system.ctrl_low, action_high=system.ctrl_high,
                          num_samples=12, iterations=1, temperature=0.05, noise_std=0.3,
                          dtype=torch.float64)  # fmt: skip
    policy = PlannerPolicy(planner, recorder, seed=0)
    env = make_real_env("humanoid_stand", seed=0)
    rollout = run_episode(env, policy, 0, 16)
    env.close()
    recorder.close()
    assert recorder.calls == 16 and len(recorder.starts) == 6  # plans 0, 3, ..., 15
    assert recorder.candidates[0].shape == (12, 5, system.nu)
    return build_reference(rollout, recorder, system, task, horizons=(1, 5), every=3)


def test_fidelity_of_the_env_physics_itself_is_exact(humanoid, reference) -> None:
    """The MJCF stepped as the env steps it: zero velocity and height errors (to the solver's
    warm start, which a step from (q, qd) does not carry) and it ranks the candidates exactly as
    the env's physics (rho 1)."""
    model = WhiteBoxModel(humanoid.system, physics=ENV_PHYSICS)
    metrics = fidelity_metrics(model, model.objective_factory(humanoid.task), reference,
                               humanoid.task)  # fmt: skip
    assert metrics["root_velocity_error_1step"] == 0.0
    assert metrics["head_height_error_1step"] == 0.0
    assert metrics["head_height_error_5step"] < 1e-5  # cm
    assert metrics["candidate_rank_rho"] == pytest.approx(1.0)
    assert reference.q.shape[0] == 2 * 4  # starts 0, 3, 6, 9 and their perturbed copies


def test_fidelity_sees_the_floor_go(humanoid, reference) -> None:
    """Without contacts the body sinks: a head-height error of centimetres after 5 steps."""
    spec = mujoco.MjSpec.from_file(str(humanoid.system.xml_path))
    spec.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    model = WhiteBoxModel(humanoid.system, spec, physics=ENV_PHYSICS)
    metrics = fidelity_metrics(model, model.objective_factory(humanoid.task), reference,
                               humanoid.task)  # fmt: skip
    assert metrics["head_height_error_5step"] > 1.0  # cm


@pytest.mark.slow
def test_tiny_whitebox_loop_identifies_and_resumes(tmp_path: Path) -> None:
    """model=white_box through the loop on the pendulum: identified at every refit (no
    optimizer), planned on MuJoCo, its multipliers in the checkpoint; a resume with a larger
    budget continues from them."""
    run_dir = tmp_path / "whitebox"
    tiny = [o for o in TINY_TRAIN if not o.startswith("model.")]
    cmd = [sys.executable, "-m", "mbrl_delan.train", *tiny, "model=white_box",
           "model.iterations=3", "model.windows=16", f"hydra.run.dir={run_dir}"]  # fmt: skip
    env = {**os.environ, "WANDB_MODE": "disabled"}
    out = subprocess.run([*cmd, "budget.iterations=1"], capture_output=True, text=True, env=env,
                         timeout=600)  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    first = torch.load(run_dir / "checkpoint.pt", weights_only=False)["loop"]["model"]
    assert first["_extra_state"]["identifications"] == 2  # the warm-up and round 1
    resumed = subprocess.run(
        [sys.executable, "-m", "mbrl_delan.train", f"resume={run_dir}", "budget.iterations=2"],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    state = torch.load(run_dir / "checkpoint.pt", weights_only=False)["loop"]["model"]
    assert state["_extra_state"]["identifications"] == 3
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["model"] == "white_box" and summary["iterations"] == 2


def test_the_former_name_whitebox_runs_as_white_box_with_a_notice(caplog) -> None:
    """model=whitebox (the name before train and fit shared one) is model=white_box with every
    setting the same and one notice; a run saved under the former name reads as white_box."""
    with caplog.at_level(logging.WARNING, logger="mbrl_delan.conf.checks"):
        former = compose_train_config(["model=whitebox"])
    assert [r.getMessage() for r in caplog.records] == [
        "model=whitebox is now model=white_box: read as that"
    ]
    current = compose_train_config(["model=white_box"])
    assert OmegaConf.to_container(former.model) == OmegaConf.to_container(current.model)
    saved = OmegaConf.create({"model": {"name": "whitebox", "window": 4}})
    assert migrate(saved).model.name == "white_box" and saved.model.name == "whitebox"


@pytest.mark.parametrize(("case", "factor"), [("mass_x1.25", 1.25), ("gear_x0.65", 0.65)])
def test_fidelity_cases_scale_what_they_name(humanoid, case: str, factor: float) -> None:
    """The suite's scaled cases: every body's mass and inertia, or every actuator's gear, times
    the factor, and nothing else."""
    from mbrl_delan.benchmarks.fidelity import TASK, perturbed_model
    from mbrl_delan.conf.checks import compose_train_config

    cfg = compose_train_config([f"env={TASK}"])
    true = humanoid.system.mj_model()
    model, _ = perturbed_model(cfg, humanoid, case, 0, 1).mj_model()
    mass, gear = (factor, 1.0) if case.startswith("mass") else (1.0, factor)
    np.testing.assert_allclose(model.body_mass, mass * true.body_mass, rtol=1e-12)
    np.testing.assert_allclose(model.body_inertia, mass * true.body_inertia, rtol=1e-12)
    np.testing.assert_allclose(model.actuator_gear, gear * true.actuator_gear, rtol=1e-12)
    np.testing.assert_allclose(model.dof_damping, true.dof_damping, rtol=1e-12)
