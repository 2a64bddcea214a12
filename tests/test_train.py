"""End to end: `python -m mbrl_delan.train` on a tiny budget, resume, config errors (SIGKILL and
resume: tests/test_faults.py)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from tiny import TINY_TRAIN

from mbrl_delan import keys
from mbrl_delan.conf.checks import CONFIG_DIR
from mbrl_delan.training.checkpoint import load_checkpoint
from mbrl_delan.training.loop import Schedule
from mbrl_delan.training.summary import TIMING_KEYS

TINY = TINY_TRAIN
DATA = Path(__file__).parent / "data"  # holds the CMU clip 09_06 (a run)


def train(
    run_dir: Path, *overrides: str, wait: bool = True, wandb_mode: str = "disabled"
) -> subprocess.Popen | subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "mbrl_delan.train", *TINY, f"hydra.run.dir={run_dir}", *overrides]
    env = {**os.environ, "WANDB_MODE": wandb_mode, "WANDB_SILENT": "true", "PYTHONUNBUFFERED": "1"}
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)


def records(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("run") / "full"
    # the env-step budget ends it: 15 random steps, then rounds of 15 until 60 >= 50
    out = train(run_dir, "budget.env_steps=50", "budget.iterations=10")
    assert out.returncode == 0, out.stdout + out.stderr
    return run_dir


@pytest.mark.slow
def test_offline_wandb_run_holds_the_summary_and_figures(tmp_path: Path) -> None:
    """logger=wandb: the run has the name and tags asked for, the summary (fraction_of_oracle
    included) reaches it before it finishes, the charts run against env steps, the returns
    figure is logged and the final checkpoint is a model artifact."""
    pytest.importorskip("wandb")
    run_dir = tmp_path / "wandb_run"
    tags = ("logger.name=tiny-pendulum", "logger.tags=[smoke,ci]")
    out = train(run_dir, "logger=wandb", "budget.iterations=1", *tags, wandb_mode="offline")
    assert out.returncode == 0, out.stdout + out.stderr
    (log_file,) = (run_dir / "wandb").glob("offline-run-*/run-*.wandb")
    summary: dict = {}
    x_axes, runs, artifacts = set(), [], []
    for record in wandb_records(log_file):
        kind = record.WhichOneof("record_type")
        if kind == "summary":
            summary |= {u.key: json.loads(u.value_json) for u in record.summary.update}
        elif kind == "metric":
            x_axes.add((record.metric.glob_name, record.metric.step_metric))
        elif kind == "run":
            runs.append((record.run.display_name, list(record.run.tags), record.run.run_id))
        elif kind == "artifact":
            files = [entry.path for entry in record.artifact.manifest.contents]
            artifacts.append((record.artifact.name, record.artifact.type, files))
    (name, run_tags, run_id) = runs[0]
    assert name == "tiny-pendulum" and run_tags == ["smoke", "ci"], runs
    assert artifacts == [(f"{run_id}-checkpoint", "model", ["checkpoint.pt"])], artifacts
    local = json.loads((run_dir / "summary.json").read_text())
    assert summary["fraction_of_oracle"] == pytest.approx(local["fraction_of_oracle"])
    assert summary["env_steps"] == local["env_steps"]
    assert ("*", "env_steps") in x_axes  # every chart against env steps
    assert list(log_file.parent.glob("files/media/images/returns_*.png"))


def wandb_records(path: Path):
    """The protobuf records of an offline run's ``.wandb`` file: a 7-byte header, then
    LevelDB's log format (32 KiB blocks of chunks, each with a 7-byte header: CRC, length,
    type 1 full, 2 first, 3 middle, 4 last)."""
    from wandb.proto.wandb_internal_pb2 import Record

    data, block, pos, parts = path.read_bytes(), 32768, 7, b""
    assert data[:4] == b":W&B", path
    while pos + 7 <= len(data):
        left = block - pos % block
        length, kind = int.from_bytes(data[pos + 4 : pos + 6], "little"), data[pos + 6]
        if left < 7 or (kind == 0 and length == 0):  # the block's zero padding
            pos += left
            continue
        parts += data[pos + 7 : pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):
            record = Record()
            record.ParseFromString(parts)
            parts = b""
            yield record


def test_tiny_training_run_writes_everything(finished_run: Path) -> None:
    summary = json.loads((finished_run / "summary.json").read_text())
    for key in (
        "env",
        "model",
        "planner",
        "seed",
        "env_steps",
        "wall_time_s",
        "eval_return_mean",
        "eval_return_std",
        "oracle_return_mean",
        "command",  # where it comes from (mbrl_delan.provenance)
        "git_commit",
        "dirty",
        "host",
        "plan_ms_median",  # the run's own planning time beside its figures
        "plan_ms_per_control_step",
        "plan_load_1min",
        "oracle_plan_ms_median",
    ):
        assert key in summary, key
    assert summary["plan_ms_median"] > 0 and summary["oracle_plan_ms_median"] > 0
    assert summary["env"] == "pendulum" and summary["model"] == "delan"
    assert summary["env_steps"] == 4 * 15  # one random episode + three on-policy ones
    recs = records(finished_run)
    assert [r["iteration"] for r in recs] == [1, 2, 3]
    assert all(0.0 <= r["eval_return_mean"] <= 15.0 for r in recs)  # rewards lie in [0, 1]
    assert all(r["model_error_1step"] >= 0.0 for r in recs)
    for name in ("returns.png", "model_error.png", "checkpoint.pt", "config.yaml"):
        assert (finished_run / name).is_file(), name


def test_load_run_gives_the_train_runs_delan_and_evaluate_uses_it(finished_run, tmp_path) -> None:
    """`load_run` of a train run: its world model with the checkpoint's weights; `evaluate`
    scores that DeLaN's inverse dynamics on pendulum data of MuJoCo (tau = B a)."""
    import numpy as np

    from mbrl_delan.data.synthetic import dynamics_dataset
    from mbrl_delan.evaluate import evaluate_run
    from mbrl_delan.runs import load_run
    from mbrl_delan.systems.system import load_system

    run = load_run(finished_run)
    assert run.kind == "train" and run.summary["env"] == "pendulum"
    assert not run.model.training  # loaded for evaluation
    saved = load_checkpoint(finished_run / "checkpoint.pt", weights_only=False)["loop"]["model"]
    for key, value in run.model.state_dict().items():
        torch.testing.assert_close(value, saved[key])
    data = dynamics_dataset(load_system("pendulum"), 64, torch.Generator().manual_seed(0))
    path = tmp_path / "pendulum.npz"
    np.savez(path, **{k: data[k].numpy() for k in ("q", "qd", "qdd", "tau")})
    result = evaluate_run(finished_run, data=path)["splits"]["data"]
    assert result["n"] == 64 and result["r2"] <= 1.0 and result["mse_si"] >= 0.0
    assert "components" in result and result["rollout"] == {}  # no times: no rollouts


def test_schedule_ends_at_the_round_cap_or_the_env_step_budget() -> None:
    rounds = Schedule(1, 1, iterations=4, eval_every=2, eval_episodes=2, final_eval_episodes=5)
    assert [rounds.evaluations_at(k, env_steps=10**6) for k in (1, 2, 3, 4)] == [0, 2, 0, 5]
    steps = replace(rounds, iterations=100, env_steps=1000)
    assert [steps.is_last(k, 999) for k in (1, 99, 100)] == [False, False, True]
    assert steps.is_last(3, 1000) and steps.evaluations_at(3, 1200) == 5
    assert steps.evaluations_at(2, 999) == 2 and steps.evaluations_at(3, 999) == 0


@pytest.mark.slow
def test_tiny_humanoid_stand_run_with_the_residual_delan(tmp_path: Path) -> None:
    """Humanoid-v5 with contacts through the whole loop: free root (quaternion) states in the
    buffer, DeLaN with its residual force (the env's default) fitted on 3-step rollouts, the
    oracle on MuJoCo."""
    run_dir = tmp_path / "humanoid"
    out = train(run_dir, "env=humanoid_stand", "budget.iterations=1", "fit.rollout_steps=3")
    assert out.returncode == 0, out.stdout + out.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env"] == "humanoid_stand" and summary["env_steps"] == 2 * 15
    config = (run_dir / "config.yaml").read_text()
    assert "residual: true" in config and "rollout_steps: 3" in config
    # the fits trained on 3-step windows of the buffer's episodes (none across episodes)
    assert "windows of 3 steps" in out.stdout + out.stderr
    rec = records(run_dir)[-1]
    assert 0.0 <= rec["eval_return_mean"] <= 15.0 and rec["model_error_1step"] >= 0.0


@pytest.mark.slow
@pytest.mark.heavy
def test_tiny_cmu_track_run_follows_the_clip_in_time(tmp_path: Path) -> None:
    """A time-indexed task through the whole loop: the CMU humanoid (56 actuators, contacts)
    following the test clip, every reward scored against the reference frame of its step; the
    oracle is the env's default, iLQR over `env.oracle_horizon` (5 here)."""
    run_dir = tmp_path / "track"
    clip = ["env.task.clip=09_06", f"env.task.folders=[{DATA}]", "env.task.download=false"]
    short = ("env.episode_len=6", "env.oracle_horizon=5", "budget.iterations=1")
    out = train(run_dir, "env=cmu_track", *clip, *short)
    assert out.returncode == 0, out.stdout + out.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env"] == "cmu_track" and summary["env_steps"] == 2 * 6
    rec = records(run_dir)[-1]
    assert 0.0 < rec["eval_return_mean"] <= 6.0  # rewards lie in (0, 1]
    assert 0.0 < summary["oracle_return_mean"] <= 6.0
    assert "oracle_planner: ilqr" in (run_dir / "config.yaml").read_text()
    assert "oracle: iLQR, horizon 5" in out.stdout + out.stderr


def test_ilqr_oracle_option_builds_the_tracking_ilqr() -> None:
    """budget.oracle_planner=ilqr on cmu_track: the oracle is iLQR with the clip's residuals
    (its episodes are tested in test_ilqr.py)."""
    from mbrl_delan.conf.loop import build_oracle
    from mbrl_delan.envs.registry import make_env_parts
    from mbrl_delan.planners.ilqr import ILQRPlanner
    from mbrl_delan.planners.tracking_residual import TRACKING_ILQR, TrackingResidual

    configs = str(CONFIG_DIR)
    clip = ["env.task.clip='09_06'", f"env.task.folders=[{DATA}]", "env.task.download=false"]
    with initialize_config_dir(config_dir=configs, version_base=None):
        cfg = compose("config", overrides=["env=cmu_track", *clip, "budget.oracle_planner=ilqr"])
    parts = make_env_parts("cmu_track", task_options={"clip": "09_06", "folders": [str(DATA)],
                                                      "download": False})  # fmt: skip
    oracle = build_oracle(cfg, parts.system, parts.task)
    assert isinstance(oracle.planner, ILQRPlanner)
    ilqr = oracle.planner.ilqr
    assert ilqr.settings == TRACKING_ILQR and isinstance(ilqr.cost, TrackingResidual)
    assert ilqr.cost.ref_q.shape == tuple(parts.task.ref_q.shape)
    # cmu_track's oracle plans on MuJoCo at 3 x 10 ms per control step (the env: 15 x 2 ms)
    assert parts.system.frame_skip == 15 and ilqr.frame_skip == 3
    assert ilqr.model.opt.timestep == pytest.approx(0.01)
    oracle.planner.close()


def test_humanoid_walk_oracle_is_ilqr_on_the_cheaper_physics() -> None:
    """humanoid_walk's default oracle: iLQR with the humanoid residuals over the planner's
    horizon, on the env's planning physics (2 x 7.5 ms, Euler)."""
    import mujoco

    from mbrl_delan.conf.checks import compose_train_config
    from mbrl_delan.conf.loop import build_oracle
    from mbrl_delan.envs.registry import make_env_parts
    from mbrl_delan.planners.humanoid_residual import HumanoidResidual
    from mbrl_delan.planners.ilqr import ILQRPlanner

    cfg = compose_train_config(["env=humanoid_walk"])
    assert cfg.budget.oracle_planner == "ilqr"
    parts = make_env_parts("humanoid_walk")
    oracle = build_oracle(cfg, parts.system, parts.task)
    assert isinstance(oracle.planner, ILQRPlanner)
    ilqr = oracle.planner.ilqr
    assert isinstance(ilqr.cost, HumanoidResidual) and ilqr.settings.horizon == 30
    assert ilqr.frame_skip == 2 and ilqr.model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert ilqr.model.opt.timestep == pytest.approx(parts.system.control_dt / 2)
    oracle.planner.close()


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("planner.horizon=-5", "planner.horizon=-5 is not valid; it must be a whole number >= 1"),
        (
            "model.name=transformer",
            "choose one of: delan, tree, tree_delan, delan_ensemble, ensemble",
        ),
        ("env.name=moon", "choose one of: pendulum, cartpole, acrobot, arm_reach"),
        ("device=tpu", "device='tpu'"),
        ("resume=/nonexistent/run", "no config.yaml in that folder"),
        ("fit.rollout_steps=0", "fit.rollout_steps=0"),
        ("model=ensemble fit.rollout_steps=3", "its GaussianEnsemble does not train on windows"),
        ("model.loss=inverse fit.rollout_steps=3", "its DeLaN does not train on windows"),
        ("env=cmu_track env.task.clip='99_99' env.task.download=false", "clip '99_99' not found"),
        ("env=cmu_track env.task.clip=131_03", "clip=13103 is not a clip name; quote it"),
        ("planner.temperature=-1", "planner.temperature=-1.0 is not valid; it must be a finite"),
        ("planner.smoothing=1", "planner.smoothing=1.0 is not valid; it must be a finite number"),
        ("buffer.device=tpu", "buffer.device='tpu' is not valid"),
        ("buffer.device_fraction=0", "buffer.device_fraction=0.0 is not valid"),
        ("model.yaw_invariant=true", "yaw_invariant needs a model whose first joint is a free"),
        ("fit.val_fraction=2", "fit.val_fraction=2.0 is not valid; it must be a finite number"),
        ("budget.oracle_planner=ilqr", "oracle_planner=ilqr needs a motion-tracking or humanoid"),
        ("+fit.learning_rate=0.1", "fit.learning_rate is not a config key"),
        ("fit.max_grad_norm=0", "fit.max_grad_norm=0.0 is not valid; it must be a finite"),
        ("fit.max_batches_per_epoch=0", "fit.max_batches_per_epoch=0 is not valid"),
        ("fit.patience=abc", "fit.patience: Value 'abc' of type 'str' could not be converted"),
        ("seed=abc", "seed: Value 'abc' of type 'str' could not be converted to Integer"),
        ("seed=-3", "seed=-3 is not valid; it must be a whole number >= 0"),
        ("threads=0", "threads=0 is not valid; it must be a whole number >= 1"),
        ("accel.rollout_threads=0", "accel.rollout_threads=0 is not valid; it must be a whole"),
        ("model.lr=nan", "model.lr=nan is not valid; it must be a finite number > 0"),
        ("model.lr=0", "model.lr=0.0 is not valid"),
        ("model.weight_decay=-1", "model.weight_decay=-1.0 is not valid"),
        ("budget.oracle_planner=lqr", "budget.oracle_planner='lqr' is not valid"),
        ("planner=random_shooting", "Could not find 'planner/random_shooting'; choose one of: cem"),
    ],
)
def test_bad_config_value_fails_at_start_naming_it(
    override: str, expected: str, tmp_path: Path, run_main
) -> None:
    """In-process, as the command runs: exit 2, one line naming the value, no traceback, and
    no run dir for a value the checks before the run catch (all but those that need the
    env's parts built or the resumed folder read).
    Each of these once reached deep code (torch's seeding, the optimizer, `FitConfig`) and
    failed there with a raw traceback, or ran with a silent default (threads=0)."""
    from mbrl_delan.train import main

    run_dir = tmp_path / "bad"
    code, text = run_main(main, *TINY, *override.split(), f"hydra.run.dir={run_dir}")
    assert code == 2, text
    assert expected in text and "Traceback" not in text, text
    assert not (run_dir / "checkpoint.pt").exists()
    # these need the built parts (the env's system, the model's capabilities, the run's folder)
    built = ("env=", "resume=", "yaw_invariant", "oracle_planner=ilqr", "rollout_steps=3")
    if not any(word in override for word in built):
        assert not run_dir.exists()


def run_files(run_dir: Path) -> dict[str, bytes]:
    """Every file of the run dir by relative path: the run's own, Hydra's `.hydra/` record of
    its launch and its log."""
    return {str(p.relative_to(run_dir)): p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}


def test_resume_of_a_finished_run_rewrites_nothing_and_takes_only_safe_overrides(
    finished_run: Path, tmp_path: Path, run_main
) -> None:
    """resume= on a finished run reports its summary and exits 0, its files untouched; an
    override that would change what the run is (model.hidden) is refused naming it, with
    nothing written; a longer budget is taken, saved and run on."""
    from mbrl_delan.train import main

    run_dir = tmp_path / "done"
    shutil.copytree(finished_run, run_dir)
    kept = ("summary.json", "metrics.jsonl", "checkpoint.pt", "config.yaml")
    before = run_files(run_dir)
    code, text = run_main(main, *TINY, f"resume={run_dir}")
    assert code == 0 and "the run is finished" in text, text
    after = run_files(run_dir)
    assert all(after[name] == before[name] for name in kept)

    before = run_files(run_dir)
    code, text = run_main(
        main, *TINY, f"resume={run_dir}", "model.hidden=32", "planner.num_samples=8"
    )
    assert code == 2 and "Traceback" not in text, text
    assert "cannot change" in text and "model.hidden" in text and "planner.num_samples" in text
    assert run_files(run_dir) == before  # no crash.json, no new .hydra record or log lines

    steps = records(run_dir)[-1]["env_steps"]
    out = train(run_dir, f"resume={run_dir}", f"budget.env_steps={steps + 15}")
    assert out.returncode == 0, out.stdout + out.stderr
    assert records(run_dir)[-1]["env_steps"] >= steps + 15
    saved = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert saved["budget"]["env_steps"] == steps + 15 and saved["model"]["hidden"] == 16


def test_resume_of_a_finished_run_saved_without_newer_fields_completes_its_summary(
    finished_run: Path, tmp_path: Path, run_main
) -> None:
    """A finished run whose summary.json predates the zero-control baseline and the median
    episode length gets them on resume= (the baseline evaluated, the median read from its
    last evaluation), every other field as it was."""
    from mbrl_delan.train import main

    run_dir = tmp_path / "older"
    shutil.copytree(finished_run, run_dir)
    full = json.loads((run_dir / "summary.json").read_text())
    newer = ("zero_torque_return_mean", "gap_closed", "eval_steps_median")
    older = {k: v for k, v in full.items() if k not in newer}
    (run_dir / "summary.json").write_text(json.dumps(older))
    code, text = run_main(main, *TINY, f"resume={run_dir}")
    assert code == 0, text
    completed = json.loads((run_dir / "summary.json").read_text())
    assert completed["eval_steps_median"] == records(run_dir)[-1]["eval_steps_median"]
    assert completed["eval_steps_median"] == full["eval_steps_median"]
    r0 = completed["zero_torque_return_mean"]
    gap = (completed["eval_return_mean"] - r0) / (completed["oracle_return_mean"] - r0)
    assert completed["gap_closed"] == pytest.approx(gap)
    assert {k: completed[k] for k in older} == older


def test_an_error_found_while_building_leaves_no_folder_and_the_corrected_run_goes_there(
    tmp_path: Path,
) -> None:
    """A config error found once the run has started (a clip that does not exist) is exit 2
    and one line before the run's config is written, and leaves no folder; the corrected
    command runs in the same folder."""
    run_dir = tmp_path / "run"
    out = train(run_dir, "env=cmu_track", "env.task.clip='99_99'")
    text = out.stdout + out.stderr
    assert out.returncode == 2 and "Traceback" not in text and "99_99" in text, text
    assert not run_dir.exists()
    out = train(run_dir, "budget.iterations=1")
    assert out.returncode == 0, out.stdout + out.stderr
    assert (run_dir / "summary.json").is_file() and not (run_dir / "crash.json").exists()


def test_new_run_in_a_used_run_dir_is_refused_and_leaves_it_as_it_was(
    finished_run: Path, tmp_path: Path
) -> None:
    """Without `resume=`, a run in a folder holding another would overwrite its config,
    checkpoint and metrics: it is refused before it writes anything."""
    run_dir = tmp_path / "used"
    shutil.copytree(finished_run, run_dir)
    before = run_files(run_dir)
    out = train(run_dir, "budget.iterations=1")
    text = out.stdout + out.stderr
    assert out.returncode == 2, text
    assert "already holds a run (config.yaml, checkpoint.pt, metrics.jsonl" in text
    assert f"resume={run_dir}" in text and "Traceback" not in text
    assert run_files(run_dir) == before  # no crash.json, and Hydra's record left as it was
    assert "metrics.jsonl" in before and "checkpoint.pt" in before
    assert ".hydra/overrides.yaml" in before


def test_collecting_with_two_envs_gives_one_episode_per_env_each_round(
    tmp_path: Path, run_main
) -> None:
    """`budget.collect_envs=2`: the warm-up and each round collect two whole episodes (of 15
    steps), numbered in the buffer, and the round's metrics are their means."""
    from mbrl_delan.train import main

    run_dir = tmp_path / "two_envs"
    code, text = run_main(
        main, *TINY, "budget.iterations=2", "budget.collect_envs=2", f"hydra.run.dir={run_dir}"
    )
    assert code == 0, text
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["episodes"] == 6 and summary["env_steps"] == 6 * 15
    assert [r["env_steps"] for r in records(run_dir)] == [60, 90]
    state = load_checkpoint(run_dir / "checkpoint.pt", weights_only=False)
    episode = state["loop"]["buffer"]["filled"][keys.EPISODE].reshape(-1)
    assert torch.equal(torch.bincount(episode), torch.full((6,), 15))


def test_paired_figures_count_falls_and_compare_where_both_stood() -> None:
    """`MBRLLoop.paired_figures`: episodes shorter than the episode length fell; the
    standing-return ratio is over the episodes where neither fell."""
    from mbrl_delan.training.loop import Evaluation, MBRLLoop

    loop = MBRLLoop.__new__(MBRLLoop)  # only the oracle's record and the episode length
    loop.episode_len = 100
    loop.oracle_returns, loop.oracle_steps = [90.0, 80.0, 20.0, 95.0], [100, 100, 30, 100]
    model = Evaluation(returns=[45.0, 10.0, 50.0, 95.0], steps=[100, 12, 100, 100])
    figures = loop.paired_figures(model)
    assert figures["paired_episodes"] == 4
    assert figures["falls"] == 1 and figures["oracle_falls"] == 1 and figures["both_stood"] == 2
    assert figures["standing_return_ratio"] == pytest.approx((45.0 + 95.0) / (90.0 + 95.0))
    assert figures["oracle_episode_steps"] == [100, 100, 30, 100]


def test_planning_figures_of_worked_replans() -> None:
    """`Evaluation.planning_figures`: replans of 10, 30 and 20 ms serving 6 control steps (a
    plan every two steps): the median replan 20 ms, 60 ms over 6 steps 10 ms per step; a
    policy that never planned gives none."""
    from mbrl_delan.training.loop import Evaluation

    ev = Evaluation(plan_seconds=[0.010, 0.030, 0.020], planned_steps=6)
    figures = ev.planning_figures("oracle_")
    assert figures["oracle_plan_ms_median"] == pytest.approx(20.0)
    assert figures["oracle_plan_ms_per_control_step"] == pytest.approx(10.0)
    assert figures["oracle_plan_load_1min"] >= 0.0
    assert Evaluation(returns=[1.0], steps=[10]).planning_figures() == {}


@pytest.mark.slow
def test_tiny_tree_run_pairs_its_final_evaluation_and_keeps_its_weights(tmp_path: Path) -> None:
    """model=tree on humanoid_stand with a paired final evaluation: the oracle plans the same
    starts with the same planner seeds (as many episodes), each episode's return and steps
    are recorded, the summary holds the paired figures, and the final weights
    (`world_model.pt`) alone rebuild the model (a record folder, without the checkpoint).
    Another model's run takes its oracle (`budget.oracle_from`)."""
    import shutil

    from mbrl_delan.rescore import rescore
    from mbrl_delan.runs import load_run

    run_dir = tmp_path / "tree"
    out = train(run_dir, "env=humanoid_stand", "model=tree", "budget.iterations=1",
                "budget.final_eval_episodes=2", "budget.paired=true")  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["paired_episodes"] == 2
    assert 0 <= summary["falls"] <= 2 and 0 <= summary["oracle_falls"] <= 2
    last = records(run_dir)[-1]
    assert len(last["eval_episode_returns"]) == 2 and len(last["oracle_episode_returns"]) == 2
    assert sum(last["eval_episode_returns"]) == pytest.approx(2 * last["eval_return_mean"])
    assert all(1 <= s <= 15 for s in last["eval_episode_steps"] + last["oracle_episode_steps"])
    record = tmp_path / "record"
    record.mkdir()
    for name in ("config.yaml", "summary.json", "world_model.pt", "metrics.jsonl"):
        shutil.copy(run_dir / name, record / name)
    saved = load_run(run_dir).model.state_dict()
    for key, value in load_run(record).model.state_dict().items():
        torch.testing.assert_close(value, saved[key])
    # the record re-scored (its config as a record saved before `model.learn_springs` was
    # added): the same episodes, step for step; the MJCF's rigid body under the fit plans
    # the same starts
    from omegaconf import OmegaConf

    older = OmegaConf.load(record / "config.yaml")
    del older.model["learn_springs"]
    OmegaConf.save(older, record / "config.yaml")
    again = rescore(record)
    assert again["steps"] == last["eval_episode_steps"] == again["recorded_steps"]
    assert again["returns"] == pytest.approx(last["eval_episode_returns"], rel=1e-6)
    assert again["falls"] == summary["falls"] and again["paired_episodes"] == 2
    exact = rescore(record, episodes=1, body="mjcf")
    assert exact["paired_episodes"] == 1 and exact["body"] == "mjcf"
    wider = rescore(record, episodes=1, samples=again["num_samples"] + 8)
    assert wider["paired_episodes"] == 1 and wider["num_samples"] == again["num_samples"] + 8
    # a second model takes this run's oracle and zero-torque episodes: the same figures, no
    # oracle episode planned again; a run of another seed is refused naming the key
    other = tmp_path / "tree_delan"
    out = train(other, "env=humanoid_stand", "model=tree_delan", "budget.iterations=1",
                "budget.final_eval_episodes=2", "budget.paired=true",
                f"budget.oracle_from={run_dir}")  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    assert "evaluating the oracle" not in out.stdout + out.stderr
    theirs = json.loads((other / "summary.json").read_text())
    for key in ("oracle_return_mean", "oracle_falls", "zero_torque_return_mean"):
        assert theirs[key] == summary[key], key
    assert records(other)[-1]["oracle_episode_steps"] == last["oracle_episode_steps"]
    assert summary["oracle_source"] == "this run" and theirs["oracle_source"] == str(run_dir)
    # the oracle's episodes on their own (oracle.json, oracle_reference.pt) serve as well,
    # from a folder that holds nothing else (a record under docs/records/oracles)
    from omegaconf import OmegaConf

    from mbrl_delan.runs import ORACLE_FILE, ORACLE_REFERENCE_FILE, oracle_of_run

    kept = json.loads((run_dir / ORACLE_FILE).read_text())
    assert kept["steps"] == last["oracle_episode_steps"] and kept["config"]["seed"] == 0
    assert kept["falls"] == summary["oracle_falls"] and kept["git_commit"] == summary["git_commit"]
    oracles = tmp_path / "oracles"
    oracles.mkdir()
    for name in (ORACLE_FILE, ORACLE_REFERENCE_FILE):
        if (run_dir / name).is_file():
            shutil.copy(run_dir / name, oracles / name)
    alone = oracle_of_run(oracles, OmegaConf.load(other / "config.yaml"))
    assert alone.returns == kept["returns"] and alone.zero_returns == kept["zero_returns"]
    # a run saved before a key was added (here without env.plan_speed) and before its oracle
    # was kept on its own is read migrated, from its checkpoint
    (run_dir / ORACLE_FILE).unlink()
    older = OmegaConf.load(run_dir / "config.yaml")
    del older.env["plan_speed"]
    older.env.mppi_samples, older.env.model_substeps = 999, 7  # other groups' defaults only
    OmegaConf.save(older, run_dir / "config.yaml")
    taken = oracle_of_run(run_dir, OmegaConf.load(other / "config.yaml"))
    assert taken.steps == last["oracle_episode_steps"]
    refused = train(tmp_path / "seed1", "env=humanoid_stand", "model=tree", "seed=1",
                    "budget.iterations=1", "budget.final_eval_episodes=2",
                    "budget.paired=true", f"budget.oracle_from={oracles}")  # fmt: skip
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert "its seed is 0, this run's 1" in refused.stdout + refused.stderr


def test_rescore_env_springs_are_the_exoskeletons_and_the_quadratic_goes() -> None:
    """`springs=env` on humanoid_stand_exo: the swapped tree's springs pull as MuJoCo's
    `qfrc_spring` in the exoskeleton's MJCF at a bent pose, the residual's quadratic
    potential is gone, and a model without a tree is refused naming the option."""
    import mujoco

    from mbrl_delan.conf.loop import build_world_model, env_parts
    from mbrl_delan.rescore import env_springs

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        cfg = compose("config", overrides=["env=humanoid_stand_exo", "model=tree_delan",
                                           "model.spring_potential=true"])  # fmt: skip
        mlp = compose("config", overrides=["env=humanoid_stand_exo", "model=ensemble"])
    parts = env_parts(cfg)
    model = build_world_model(cfg, parts.system, torch.device("cpu"), torch.float64)
    with torch.no_grad():  # a learned quadratic to remove
        model.dynamics.residual.field.spring_stiffness.fill_(0.3)
    model.load_state_dict(env_springs(cfg, model.state_dict()))
    physics = parts.physics.mj_model()
    data = mujoco.MjData(physics)
    data.qpos[:] = physics.qpos0
    data.qpos[7:] += torch.linspace(-0.6, 0.4, physics.nq - 7, dtype=torch.float64).numpy()
    mujoco.mj_forward(physics, data)
    q = torch.tensor(data.qpos)
    torch.testing.assert_close(model.dynamics.tree.spring(q), -torch.tensor(data.qfrc_spring))
    assert data.qfrc_spring[6:].any()  # the exoskeleton's springs pull at this pose
    assert not model.dynamics.residual.field.spring_force(q).any()
    with pytest.raises(ValueError, match="springs=env needs a tree model"):
        env_springs(mlp, {})


def test_rescore_names_what_a_folder_lacks_in_one_line(tmp_path: Path, capsys, caplog) -> None:
    """`python -m mbrl_delan.rescore` on a folder without a paired final evaluation, or with
    a bad option, exits 2 naming the file or the option, without a traceback."""
    from mbrl_delan.rescore import main

    (tmp_path / "metrics.jsonl").write_text(json.dumps({"iteration": 1, "env_steps": 15}) + "\n")
    assert main([str(tmp_path)]) == 2
    assert "holds no paired final evaluation" in caplog.text
    with pytest.raises(SystemExit) as stop:
        main([str(tmp_path), "body"])
    assert stop.value.code == 2
    assert "the options are episodes=, body=, springs=, samples=, out=" in capsys.readouterr().err
    caplog.clear()
    assert main([str(tmp_path), "samples=0"]) == 2
    assert "samples=0: a whole number above 0" in caplog.text


def test_a_loop_built_from_python_takes_its_threads_and_seed(tmp_path: Path) -> None:
    """`build_loop` sets torch's threads and seed as the command line does: a loop built from
    Python with `threads=1` runs on one thread, and twice from the same seed it repeats its
    rounds exactly (its model's weights too)."""
    from mbrl_delan.conf.checks import compose_train_config
    from mbrl_delan.conf.loop import build_loop, schedule_of
    from mbrl_delan.training.loop import LoopHooks

    cfg = compose_train_config([*TINY_TRAIN, "threads=1", "budget.iterations=2"])
    before = torch.get_num_threads()
    results = []
    try:
        for attempt in range(2):
            torch.set_num_threads(2)
            torch.manual_seed(1000 + attempt)  # the caller's own seed does not leak in
            loop, oracle = build_loop(cfg, tmp_path / str(attempt))
            assert torch.get_num_threads() == 1
            rounds: list[dict] = []
            loop.run(schedule_of(cfg), oracle, LoopHooks(log_round=rounds.append))
            drop = TIMING_KEYS
            results.append(([{k: v for k, v in r.items() if k not in drop} for r in rounds],
                            loop.model.state_dict()))  # fmt: skip
    finally:
        torch.set_num_threads(before)
    (first, first_state), (second, second_state) = results
    assert first == second and len(first) == 2
    assert all(torch.equal(first_state[k], second_state[k]) for k in first_state)


def test_the_oracle_phase_reports_each_episode_once_checkpointed(tmp_path: Path) -> None:
    """`LoopHooks.oracle_episode` (the oracle phase's progress bar) gets (done, total) after
    each of the oracle's episodes, each after its checkpoint."""
    from mbrl_delan.conf.checks import compose_train_config
    from mbrl_delan.conf.loop import build_loop, schedule_of
    from mbrl_delan.training.loop import LoopHooks

    cfg = compose_train_config([*TINY_TRAIN, "budget.iterations=1", "budget.oracle_episodes=3"])
    loop, oracle = build_loop(cfg, tmp_path)
    events: list[object] = []
    hooks = LoopHooks(
        checkpoint=lambda: events.append("checkpoint"),
        oracle_episode=lambda done, total: events.append((done, total)),
    )
    loop.run(schedule_of(cfg), oracle, hooks)
    reports = [e for e in events if e != "checkpoint"]
    assert reports == [(1, 3), (2, 3), (3, 3)]
    assert all(events[events.index(r) - 1] == "checkpoint" for r in reports)
