"""Suite realtime (the benchmark contract of planning time per control step) and the
oracle's planning physics (`PlanPhysics`)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from mbrl_delan.bench import build_options
from mbrl_delan.benchmarks import BenchSettings, TimingConfig
from mbrl_delan.benchmarks.profile import PARTS, frame_part, profile_parts
from mbrl_delan.benchmarks.realtime import (
    PLANNER_FIELDS,
    RealtimeConfig,
    _fields,
    busy_processes,
    case_config,
    model_case,
)
from mbrl_delan.conf.checks import CONFIGS, ConfigError, compose_train_config
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.objectives.mujoco import MujocoObjectiveFactory, PlanPhysics


def test_quick_suite_writes_the_contract(tmp_path: Path) -> None:
    out = tmp_path / "realtime.jsonl"
    cmd = [sys.executable, "-m", "mbrl_delan.bench", "suite=realtime", "quick=true", "threads=1"]
    cmd += ["tasks=[pendulum]", "models=[mujoco,ensemble]", "load=1", "profile=true", f"out={out}"]
    cmd += [f"hydra.run.dir={tmp_path / 'run'}"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    records = [r for r in lines if r["metric"] == "plan_ms_per_control_step"]
    assert [r["dynamics"] for r in records] == ["mujoco", "ensemble"]
    shares = {r["part"]: r for r in lines if r["metric"] == "step_share"}
    assert set(shares) == set(PARTS)  # the learned model's profile; the oracle has none
    assert sum(r["value"] for r in shares.values()) == pytest.approx(1.0)
    assert shares["network"]["value"] > 0 and shares["kinematics"]["value"] == 0
    assert all(r["dynamics"] == "ensemble" for r in shares.values())
    for r in records:
        assert r["suite"] == "realtime" and r["metric"] == "plan_ms_per_control_step"
        assert r["task"] == "pendulum" and r["threads"] == 1 and r["planner"] == "mppi"
        assert r["load"] == 1 and r["load_cpu_s"] > 0 and r["load_1min"] >= 0
        assert set(PLANNER_FIELDS) <= set(r)
        assert math.isfinite(r["value"]) and r["value"] > 0
    oracle = records[0]
    assert oracle["steps_survived"] == 5 and oracle["episode_len"] == 5  # the quick episode


def test_the_load_generator_keeps_its_processes_busy_inside_its_block() -> None:
    """`load=N`'s generator: N processes that use about a core each while the block runs,
    none left running after it."""
    import time

    start = time.perf_counter()
    with busy_processes(2) as load:
        time.sleep(1.5)
    wall = time.perf_counter() - start
    assert load.processes == 2 and load.cpu_s > 0.3  # busy, even on a shared host (idle: 3 s)
    assert load.cpu_s <= 2 * wall + 0.1  # their own CPU time only
    with busy_processes(0) as none:
        subprocess.run([sys.executable, "-c", "sum(range(10**6))"], check=True)  # a child
    assert none.cpu_s == 0  # another child's CPU time is not the load's


def test_a_profiled_operator_counts_for_the_innermost_function_a_rule_names() -> None:
    assert frame_part("/x/mbrl_delan/models/contact.py(440): _solve") == "solve"
    assert frame_part("mbrl_delan/models/contact.py(289): kinematics") == "contact"
    assert frame_part("mbrl_delan/models/tree.py(335): kinematics") == "kinematics"
    assert frame_part("mbrl_delan/models/tree.py(350): mass_matrix") == "mass_matrix"
    assert frame_part("mbrl_delan/systems/posarith.py(98): quat_mul") is None  # a helper
    assert frame_part("mbrl_delan/systems/forward_kinematics.py(268): turn") is None
    assert frame_part("torch/nn/modules/linear.py(120): forward") is None


def test_the_profiled_parts_split_an_integrator_step() -> None:
    """Operators under the integrator count for it, those under its caller (no package
    function) for `other`; the shares sum to one."""
    from mbrl_delan.models.integrators import semi_implicit_euler

    layout = make_env_parts("pendulum", None, None).system.layout
    q, qd = torch.zeros(256, 1), torch.ones(256, 1)

    def call() -> None:
        accel = -torch.sin(q) * 9.81  # the caller's operators
        semi_implicit_euler(layout, lambda q_, qd_: accel * qd_.cos(), q, qd, 0.01)

    call()
    shares = profile_parts(call)
    assert set(shares) == set(PARTS) and sum(shares.values()) == pytest.approx(1.0)
    assert shares["integrator"] > 0 and shares["other"] > 0
    assert sum(v for k, v in shares.items() if k not in ("integrator", "other")) == 0


def test_an_ilqr_oracle_case_is_recorded_as_ilqr() -> None:
    walk = case_config("humanoid_walk", "mujoco", ())  # its default oracle
    fields = _fields(walk, "humanoid_walk", "mujoco", 0.015)
    assert fields["planner"] == "ilqr" and fields["horizon"] == 30
    assert fields["num_samples"] is None and fields["knots"] is None
    stand = _fields(case_config("humanoid_stand", "mujoco", ()), "humanoid_stand", "mujoco", 0.015)
    assert stand["planner"] == "mppi" and stand["num_samples"] == 32 and stand["knots"] == 4


def test_a_case_records_its_integrator_steps() -> None:
    """Records tell apart settings that differ only in the physics steps per control step."""
    one = ("env.oracle_substeps=1", "model.substeps=1")
    two = ("env.oracle_substeps=2", "model.substeps=2")
    for dynamics in ("mujoco", "tree"):
        fine = _fields(case_config("humanoid_stand", dynamics, two), "humanoid_stand",
                       dynamics, 0.015)  # fmt: skip
        cheap = _fields(case_config("humanoid_stand", dynamics, one), "humanoid_stand",
                        dynamics, 0.015)  # fmt: skip
        assert (fine["substeps"], cheap["substeps"]) == (2, 1)


def test_the_delan_case_plans_with_the_loops_policy() -> None:
    """The DeLaN case (eager here: compiling takes 5-40 s) times the loop's own policy."""
    cfg = case_config("pendulum", "delan", ("accel.compile=false", "planner.num_samples=16"))
    assert cfg.model.name == "delan" and cfg.planner.num_samples == 16
    assert case_config("pendulum", "delan", ()).accel.compile  # the suite's default: compiled
    opts = BenchSettings(torch.device("cpu"), TimingConfig(repeats=1, min_time_s=0.01, warmup=1))
    ms, timing, compiled = model_case(cfg, "pendulum", opts, seed=0)
    assert math.isfinite(ms) and ms > 0 and timing["repeats"] == 1
    assert compiled is None  # eager: nothing compiled, no compile_s


def test_realtime_options() -> None:
    def options(*overrides: str):
        with initialize_config_dir(config_dir=str(CONFIGS / "bench"), version_base=None):
            return build_options(compose("config", overrides=["suite=realtime", *overrides]))[0]

    default = RealtimeConfig.from_options(options())
    assert default.tasks == ("humanoid_stand", "humanoid_walk", "pendulum")
    assert default.dynamics == ("mujoco", "delan", "tree", "tree_delan", "ensemble")
    assert default.oracle_steps is None
    some = RealtimeConfig.from_options(options("models=[delan]", "tasks=[humanoid_walk]"))
    assert some.dynamics == ("delan",) and some.tasks == ("humanoid_walk",)
    assert RealtimeConfig.from_options(options("tasks=[cartpole]")).tasks == ("cartpole",)
    with pytest.raises(ConfigError, match="tasks: 'no_such_env' is not a registered env"):
        options("tasks=[no_such_env]")
    with pytest.raises(ConfigError, match="models"):
        options("models=[humanoid_delan]")


def test_humanoid_oracle_plans_on_a_cheaper_mujoco() -> None:
    cfg = compose_train_config(["env=humanoid_stand"])
    assert (cfg.env.oracle_substeps, cfg.env.oracle_integrator) == (1, "euler")
    system = make_env_parts("humanoid_stand").system
    model, substeps = PlanPhysics(2, "euler").model(system)
    assert substeps == 2 and model.opt.timestep == pytest.approx(system.control_dt / 2)
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    own, skip = PlanPhysics().model(system)
    assert skip == system.frame_skip and own.opt.timestep == pytest.approx(system.timestep)
    assert own.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4  # the MJCF's
    with pytest.raises(ValueError, match="integrator"):
        PlanPhysics(integrator="verlet")
    with pytest.raises(ValueError, match="substeps"):
        PlanPhysics(substeps=0)
    with pytest.raises(ConfigError, match="oracle_integrator"):
        compose_train_config(["env=humanoid_stand", "env.oracle_integrator=verlet"])


def test_the_plan_physics_is_the_env_physics_when_unset() -> None:
    """Default `PlanPhysics`: the oracle's rollout equals the env's own MuJoCo steps."""
    parts = make_env_parts("pendulum")
    factory = MujocoObjectiveFactory(parts.system, parts.task, nthread=1)
    same = MujocoObjectiveFactory(
        parts.system, parts.task, nthread=1, physics=PlanPhysics(parts.system.frame_skip)
    )
    finer = MujocoObjectiveFactory(
        parts.system, parts.task, nthread=1, physics=PlanPhysics(4 * parts.system.frame_skip)
    )
    start = factory.initial_state(torch.tensor([0.3]), torch.tensor([0.0]))
    actions = torch.linspace(-1, 1, 10, dtype=torch.float64).reshape(1, 10, 1)
    a, b, c = (f.rollout(start, actions).states.q for f in (factory, same, finer))
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.equal(a, c) and float((a - c).abs().max()) < 1e-2  # the same motion, finer
    for f in (factory, same, finer):
        f.close()
    np.testing.assert_array_equal(a.shape, (1, 10, 1))
