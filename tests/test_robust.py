"""Suite robust (falls of the oracle over whole episodes, the push test) and the planning
cost option `env.plan_cost`."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mbrl_delan.benchmarks.robust import Push, run_robust_episode, setting_points
from mbrl_delan.benchmarks.robust import main as robust_figure
from mbrl_delan.conf.checks import ConfigError, compose_train_config
from mbrl_delan.conf.loop import build_oracle, build_policy, build_world_model, planning_task
from mbrl_delan.envs.real import MujocoTaskEnv
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.tasks.balance import BalanceCost


def test_quick_suite_writes_the_contract(tmp_path: Path) -> None:
    out = tmp_path / "robust.jsonl"
    cmd = [sys.executable, "-m", "mbrl_delan.bench", "suite=robust", "quick=true", "threads=1"]
    cmd += ["overrides=['env.plan_cost=balance','planner.num_samples=4','planner.horizon=4']"]
    cmd += [f"out={out}", f"hydra.run.dir={tmp_path / 'run'}"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["metric"] for r in records] == ["falls", "plan_ms_per_control_step", "return_mean"]
    for r in records:
        assert r["suite"] == "robust" and r["task"] == "humanoid_stand"
        assert r["dynamics"] == "mujoco" and r["planner"] == "mppi" and r["seed"] == 0
        assert r["plan_cost"] == "balance" and r["episodes"] == 1 and r["num_samples"] == 4
        (episode,) = r["per_episode"]
        assert episode["fall_step"] is None and episode["start"] == 1000  # 5 steps: no fall
    assert records[0]["value"] == 0 and records[1]["value"] > 0
    assert records[2]["value"] == pytest.approx(records[0]["per_episode"][0]["return"], abs=1e-3)


def test_a_push_changes_the_whole_bodys_velocity_at_its_step() -> None:
    """A policy that holds still: before the push the root drifts at most by the reset's
    noise; after a 1 m/s push along x its x velocity is about 1 m/s."""

    class Still:
        def reset(self) -> None:
            pass

        def act(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
            return torch.zeros(17)

    env = MujocoTaskEnv("humanoid_stand", episode_len=3)
    episode = run_robust_episode(Still(), env, start=0, steps=3, push=Push(1.0, 2))
    assert episode.steps == 3 and episode.fall_step is None
    assert 0.8 < float(env.get_state().qd[0]) < 1.1
    calm = MujocoTaskEnv("humanoid_stand", episode_len=3)
    run_robust_episode(Still(), calm, start=0, steps=3)
    assert abs(float(calm.get_state().qd[0])) < 0.1


def test_plan_cost_balance_plans_the_balance_cost_and_only_on_humanoids() -> None:
    parts = make_env_parts("humanoid_stand")
    cfg = compose_train_config(["env=humanoid_stand", "env.plan_cost=balance",
                                "planner.num_samples=4", "planner.horizon=4"])  # fmt: skip
    assert isinstance(planning_task(cfg, parts.system, parts.task), BalanceCost)
    oracle = build_oracle(cfg, parts.physics, parts.task)
    assert isinstance(oracle.objective_factory.task, BalanceCost)
    oracle.objective_factory.close()
    model = build_world_model(cfg, parts.system, torch.device("cpu"), torch.float32)
    policy = build_policy(cfg, parts.system, parts.task, model, torch.Generator())
    assert isinstance(policy.objective_factory.task, BalanceCost)  # the world model's too
    start = parts.task.initial_state((), torch.Generator().manual_seed(0))
    action = policy.act(start.q.float(), start.qd.float())  # a plan in the (untrained) DeLaN
    assert action.shape == (17,) and torch.isfinite(action).all()
    assert torch.isfinite(policy.last_result.best_return)
    default = compose_train_config(["env=humanoid_stand"])  # the env's planner: balance
    assert isinstance(planning_task(default, parts.system, parts.task), BalanceCost)
    assert (default.planner.num_samples, default.planner.iterations) == (32, 1)
    assert (default.planner.temperature, default.env.oracle_substeps) == (1.0, 1)
    reward = compose_train_config(["env=humanoid_stand", "plan=humanoid_reward"])
    assert planning_task(reward, parts.system, parts.task) is parts.task
    assert (reward.planner.num_samples, reward.planner.iterations) == (64, 2)
    assert (reward.planner.temperature, reward.env.oracle_substeps) == (0.05, 2)
    assert compose_train_config(["env=humanoid_walk"]).planner.iterations == 2
    pendulum = make_env_parts("pendulum")
    cfg = compose_train_config(["env=pendulum", "env.plan_cost=balance"])
    with pytest.raises(ConfigError, match="plan_cost=balance needs a humanoid env"):
        planning_task(cfg, pendulum.system, pendulum.task)
    with pytest.raises(ConfigError, match="plan_cost"):
        compose_train_config(["env=humanoid_stand", "env.plan_cost=lean"])


def test_plan_speed_sets_the_walks_target_and_is_refused_to_stand() -> None:
    walk = make_env_parts("humanoid_walk")
    cfg = compose_train_config(["env=humanoid_walk", "env.plan_cost=balance",
                                "env.plan_speed=1.25"])  # fmt: skip
    task = planning_task(cfg, walk.system, walk.task)
    assert task.constants.values["target_velocity"].tolist() == [1.25, 0.0]
    stand = make_env_parts("humanoid_stand")
    cfg = compose_train_config(["env=humanoid_stand", "env.plan_cost=balance",
                                "env.plan_speed=1.0"])  # fmt: skip
    with pytest.raises(ConfigError, match="planning speed"):
        planning_task(cfg, stand.system, stand.task)
    with pytest.raises(ConfigError, match="plan_speed"):
        compose_train_config(["env=humanoid_walk", "env.plan_speed=-1"])


def test_plan_humanoid_walk_balance_makes_the_oracle_mppi_on_the_balance_cost() -> None:
    """`plan=humanoid_walk_balance`: the walk's oracle becomes MPPI 128 x 1 over 40 steps on
    one MuJoCo step per control step (not iLQR), scoring the balance cost at 1.05 m/s."""
    walk = make_env_parts("humanoid_walk")
    cfg = compose_train_config(["env=humanoid_walk", "plan=humanoid_walk_balance"])
    oracle = build_oracle(cfg, walk.system, walk.task)
    planner = oracle.planner
    assert (planner.num_samples, planner.iterations, planner.horizon) == (128, 1, 40)
    assert cfg.budget.oracle_planner == "same" and cfg.env.oracle_substeps == 1
    task = planning_task(cfg, walk.system, walk.task)
    assert isinstance(task, BalanceCost)
    assert task.constants.values["target_velocity"].tolist() == [1.05, 0.0]


def test_the_figure_counts_falls_per_setting(tmp_path: Path) -> None:
    def record(metric: str, value: float, seed: int, **extra) -> dict:
        base = dict(suite="robust", case=f"humanoid_stand-mujoco-s{seed}", metric=metric,
                    value=value, unit="", device="cpu", plan_cost="balance", planner="mppi",
                    num_samples=32, iterations=1, horizon=20, episodes=10, seed=seed,
                    push=None, oracle_substeps=2)  # fmt: skip
        return base | extra

    records = [record("falls", 1, 0), record("plan_ms_per_control_step", 20.0, 0),
               record("falls", 0, 1), record("plan_ms_per_control_step", 30.0, 1),
               record("falls", 3, 0, plan_cost="reward", num_samples=64, iterations=2),
               record("falls", 2, 0, oracle_substeps=1),
               record("return_mean", 900.0, 0)]  # fmt: skip
    points = setting_points(records)
    balance = points["balance: mppi N 32 x 1, H 20, 2 physics steps"]
    assert (balance.falls, balance.episodes, balance.ms) == (1, 20, 25.0)
    assert points["reward: mppi N 64 x 2, H 20, 2 physics steps"].falls == 3
    assert points["balance: mppi N 32 x 1, H 20, 1 physics step"].falls == 2  # apart
    # timed apart: that setting's ms from those records alone, its falls still the runs'
    timing = [record("plan_ms_per_control_step", 12.0, 0, episodes=2),
              record("falls", 5, 0, episodes=2)]  # fmt: skip
    apart = setting_points(records, timing)["balance: mppi N 32 x 1, H 20, 2 physics steps"]
    assert (apart.falls, apart.episodes, apart.ms) == (1, 20, 12.0)
    path = tmp_path / "robust.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in records))
    assert robust_figure([str(path), "--out", str(tmp_path / "falls.png")]) == 0
    (tmp_path / "timing.jsonl").write_text("\n".join(json.dumps(r) for r in timing))
    timed = [
        str(path),
        "--out",
        str(tmp_path / "timed.png"),
        "--timing",
        str(tmp_path / "timing.jsonl"),
    ]
    assert robust_figure(timed) == 0
    assert (tmp_path / "falls.png").stat().st_size > 0
    assert robust_figure([str(tmp_path / "missing.jsonl"), "--out", str(tmp_path / "x.png")]) == 2


def test_the_table_gives_each_settings_fall_rate_with_its_wilson_interval(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """0 falls in 100 episodes: the Wilson 95% interval is 0 to z^2 / (n + z^2) = 3.7%;
    the speed is the episodes' mean over the records (weighted by their episodes)."""
    base = dict(suite="robust", unit="", device="cpu", plan_cost="balance", planner="mppi",
                num_samples=32, iterations=1, horizon=30, episodes=50, push=None,
                oracle_substeps=1)  # fmt: skip
    records = [base | dict(metric="falls", value=0, seed=s, speed_mean=speed)
               for s, speed in ((0, 0.8), (1, 1.0))] + [
               base | dict(metric="plan_ms_per_control_step", value=20.0, seed=0)]  # fmt: skip
    path = tmp_path / "robust.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in records))
    assert robust_figure([str(path)]) == 0
    row = capsys.readouterr().out.splitlines()[-1]
    z2 = 1.959964**2
    assert row == (f"| balance: mppi N 32 x 1, H 30, 1 physics step | 100 | 0 | "
                   f"0.0% (0.0% to {z2 / (100 + z2):.1%}) | 0.90 | 20.0 |")  # fmt: skip


REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("records", ["robust_stand_100.jsonl", "robust_walk_100.jsonl"])
def test_the_oracles_fall_rates_in_the_docs_are_their_records(
    records: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """The table docs/humanoid_results.md shows for each oracle's 100 episodes is what the
    documented command prints from the kept records, and they hold 100 episodes."""
    path = REPO / "docs" / "records" / records
    assert robust_figure([str(path)]) == 0
    table = capsys.readouterr().out.strip()
    assert table in (REPO / "docs" / "humanoid_results.md").read_text()
    assert table.splitlines()[-1].split(" | ")[1] == "100"
