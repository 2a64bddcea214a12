"""Suite `humanoid`: Humanoid-v5 data from a PD hold, world models fitted, rollout errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from mbrl_delan import keys
from mbrl_delan.bench import build_options
from mbrl_delan.benchmarks.figures import describe_curves, error_curves
from mbrl_delan.benchmarks.figures import main as figures_main
from mbrl_delan.benchmarks.humanoid import (
    HumanoidBenchConfig,
    PDHoldPolicy,
    collect_episodes,
    first_transitions,
    model_config,
    oracle_cases,
    oracle_config,
    rollout_error,
    split_run_episodes,
    suite_config,
    tracking_errors,
)
from mbrl_delan.conf.builders import build_model
from mbrl_delan.conf.checks import CONFIGS, ConfigError
from mbrl_delan.envs.registry import make_env_parts
from tests.test_tracking import RUN_CLIP


@pytest.fixture(scope="module")
def humanoid():
    return make_env_parts("humanoid_stand")


def test_quick_suite_writes_every_model_and_horizon(tmp_path: Path) -> None:
    out = tmp_path / "humanoid.jsonl"
    cmd = [sys.executable, "-m", "mbrl_delan.bench", "suite=humanoid", "quick=true", "threads=1"]
    cmd += [f"out={out}", f"hydra.run.dir={tmp_path / 'run'}", "seed=2"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    records = [json.loads(line) for line in out.read_text().splitlines()]
    errors = [r for r in records if r["metric"] == "rollout_error"]
    cases = {"delan-n120", "delan_contact-n120", "delan_ensemble-n120", "ensemble-n120"}
    assert {r["case"] for r in errors} == cases
    assert sorted({r["horizon"] for r in errors}) == [1, 5]
    assert all(r["value"] is not None and math.isfinite(r["value"]) for r in errors)
    assert sum(r["metric"] == "fit_s" for r in records) == 4
    assert {r["seed"] for r in records} == {2}  # the data's, the fits' and the oracle's
    # the DeLaN models fit 2-step rollouts (the quick K), the MLP ensemble single transitions
    steps = {r["case"]: r["rollout_steps"] for r in records if "rollout_steps" in r}
    assert steps == {
        "delan-n120": 2, "delan_contact-n120": 2, "delan_ensemble-n120": 2, "ensemble-n120": 1
    }  # fmt: skip
    # the quick oracle: one 3-step MPPI episode on humanoid_stand, before the models
    oracle = [r for r in records if r["case"] == "oracle-humanoid_stand"]
    assert [r["metric"] for r in oracle] == ["oracle_return", "oracle_step_s"]
    assert records[:2] == oracle
    ret = oracle[0]
    assert ret["steps"] == ret["episode_len"] == 3 and ret["fell"] is False
    assert ret["mean_reward"] == pytest.approx(ret["value"] / 3)
    assert 0.0 < ret["mean_reward"] <= 1.0  # the stand reward is a product of factors in [0, 1]


def test_pd_hold_policy_worked_example(humanoid) -> None:
    """No noise: at the held pose and at rest the control is 0; a hinge 0.1 rad off gets
    -kp 0.1 / gear on its actuator (clipped to the control range)."""
    system = humanoid.system
    policy = PDHoldPolicy(system, kp=10.0, kd=1.0, noise=0.0, seed=0)
    qpos = system.mj_model().qpos0.copy()
    policy.reset(qpos)
    qvel = np.zeros(system.nv)
    assert np.allclose(policy(qpos, qvel), 0.0)
    moved = qpos.copy()
    moved[policy.qpos[0]] += 0.1
    ctrl = policy(moved, qvel)
    low, high = float(system.ctrl_low[0]), float(system.ctrl_high[0])
    expected = np.clip(-10.0 * 0.1 / policy.gear[0], low, high)
    assert ctrl[0] == pytest.approx(float(expected))
    assert np.allclose(ctrl[1:], 0.0)


def test_episodes_are_contiguous_mujoco_transitions(humanoid) -> None:
    cfg = HumanoidBenchConfig.quick()
    episodes = collect_episodes(humanoid.system, humanoid.task, 50, cfg, seed=3)
    assert sum(e.shape[0] for e in episodes) == 50
    for ep in episodes:  # each step starts where the last one ended
        torch.testing.assert_close(ep[keys.Q][1:], ep[keys.NEXT_Q][:-1])
        torch.testing.assert_close(ep[keys.QD][1:], ep[keys.NEXT_QD][:-1])
    again = collect_episodes(humanoid.system, humanoid.task, 50, cfg, seed=3)
    other = collect_episodes(humanoid.system, humanoid.task, 50, cfg, seed=4)
    torch.testing.assert_close(episodes[0][keys.ACTION], again[0][keys.ACTION])
    assert not torch.allclose(episodes[0][keys.ACTION], other[0][keys.ACTION])  # the seed's data


def test_rollout_error_skips_episodes_shorter_than_the_horizon(humanoid) -> None:
    cfg = HumanoidBenchConfig.quick()
    episodes = collect_episodes(humanoid.system, humanoid.task, 20, cfg, seed=4)
    model = build_model(model_config("ensemble", cfg), humanoid.system)
    model.fit_normalization(torch.cat(episodes).to(torch.float32))
    assert rollout_error(model, humanoid.system, episodes, horizon=10_000) is None
    assert rollout_error(model, humanoid.system, episodes, horizon=1) > 0


def test_untrained_humanoid_delan_has_a_finite_first_gradient(humanoid) -> None:
    """With the humanoid env's inertia scaling (its units from the data alone: no known root)
    the first forward loss of an untrained DeLaN is O(10) with a moderate gradient; without it
    the untrained M is far from the body's units and its accelerations hit the velocity clamp:
    a loss over 10x and a gradient over 5x (217 and 1,593 against 10.4 and 233)."""
    cfg = HumanoidBenchConfig.quick()
    data = torch.cat(collect_episodes(humanoid.system, humanoid.task, 120, cfg, 0))
    first = {}
    for scaling in (True, False):
        settings = model_config("delan", HumanoidBenchConfig())
        settings.inertia_scaling = scaling
        settings.known_root = False
        torch.manual_seed(0)
        model = build_model(settings, humanoid.system)
        model.fit_normalization(data.to(torch.float32))
        out = model.loss(data[:64].to(torch.float32))
        out.loss.backward()
        grads = torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])
        assert bool(torch.isfinite(grads).all())
        first[scaling] = (float(out.loss.detach()), float(grads.norm()))
    assert first[True][0] < 1e2
    assert first[False][0] > 10 * first[True][0] and first[False][1] > 5 * first[True][1]


def test_loop_delan_with_the_free_tree_structure(humanoid) -> None:
    """model.tree_sparse and model.translation_invariant reach the loop's DeLaN: on
    Humanoid-v5 its M is zero between the two legs, and a step moves the state finitely."""
    settings = model_config("delan", HumanoidBenchConfig())
    settings.tree_sparse, settings.translation_invariant = True, True
    torch.manual_seed(0)
    model = build_model(settings, humanoid.system).double()
    cfg = HumanoidBenchConfig.quick()
    data = torch.cat(collect_episodes(humanoid.system, humanoid.task, 60, cfg, 0))
    model.fit_normalization(data)
    parents = humanoid.system.mj_model().dof_parentid
    chain = lambda d: {d} | (chain(parents[d]) if parents[d] >= 0 else set())  # noqa: E731
    legs = [d for d in range(humanoid.system.nv) if d >= 6]
    apart = [(i, j) for i in legs for j in legs if i not in chain(j) and j not in chain(i)]
    assert apart  # two branches exist
    M = model.terms(data[keys.Q][:4], data[keys.QD][:4]).mass_matrix.detach()
    rows, cols = zip(*apart, strict=True)
    assert float(M[:, list(rows), list(cols)].abs().max()) == 0.0
    step = model.step(data[keys.Q][:4], data[keys.QD][:4], data[keys.ACTION][:4])
    assert torch.isfinite(step.q).all() and torch.isfinite(step.qd).all()


def test_models_and_rollout_steps_options() -> None:
    with initialize_config_dir(config_dir=str(CONFIGS / "bench"), version_base=None):
        cfg = compose("config", overrides=["suite=humanoid", "models=[delan]", "rollout_steps=3"])
        bad_model = compose("config", overrides=["suite=humanoid", "models=[pendulum_delan]"])
        bad_steps = compose("config", overrides=["suite=humanoid", "rollout_steps=0"])
    chosen = suite_config(build_options(cfg)[0])
    assert chosen.models == ("delan",) and chosen.rollout_steps == 3
    assert chosen.sizes == (10_000, 50_000)
    with pytest.raises(ConfigError, match="models"):
        build_options(bad_model)  # a planner-suite case is not a humanoid-suite model
    with pytest.raises(ConfigError, match="rollout_steps"):
        build_options(bad_steps)


def test_the_suite_builds_the_loops_model_and_oracle_planner() -> None:
    """The models and the oracle's MPPI are the loop's, composed from configs/ for the env."""
    cfg = HumanoidBenchConfig()
    delan = model_config("delan", cfg)
    assert delan.residual and delan.inertia_scaling and delan.integrator == "euler"
    assert not delan.contacts
    contact = model_config("delan_contact", cfg)  # the same DeLaN with the contact model
    assert contact.name == "delan" and contact.contacts and contact.residual
    alone = model_config("delan_contact_only", cfg)  # on demand: contacts without residual
    assert alone.contacts and not alone.residual
    quick = model_config("ensemble", HumanoidBenchConfig.quick())
    assert (quick.hidden, quick.layers, quick.ensemble_size) == (8, 1, 2)
    for env in cfg.oracle_tasks:
        planner = oracle_config(env, cfg).planner
        # standing and walking plan over 4 cubic knots, standing the balance cost
        expected = {"humanoid_stand": (32, 30, 1, 4, "cubic", 1.0),
                    "cmu_track": (256, 15, 2, None, "linear", 0.05)}.get(
                        env, (64, 30, 2, 4, "cubic", 0.05))  # fmt: skip
        assert (
            planner.num_samples, planner.horizon, planner.iterations, planner.knots,
            planner.interpolation, planner.temperature,
        ) == expected  # fmt: skip
        assert (planner.noise_std, planner.smoothing) == (0.3, 0.0)


def test_oracle_options() -> None:
    def options(*overrides: str, suite: str = "humanoid"):
        with initialize_config_dir(config_dir=str(CONFIGS / "bench"), version_base=None):
            return build_options(compose("config", overrides=[f"suite={suite}", *overrides]))[0]

    default = suite_config(options())
    assert default.oracle_tasks == ("humanoid_stand", "humanoid_walk", "cmu_track")
    assert default.oracle_steps is None  # the task's own episode length
    only = suite_config(options("models=[]", "oracle_tasks=[humanoid_walk]", "oracle_steps=50"))
    assert only.models == () and only.oracle_tasks == ("humanoid_walk",)
    assert only.oracle_steps == 50
    assert suite_config(options("horizons=[1,2,30]")).horizons == (1, 2, 30)
    assert default.horizons == (1, 10, 30)
    assert suite_config(options("oracle_tasks=[]")).oracle_tasks == ()
    with pytest.raises(ConfigError, match="oracle_tasks"):
        options("oracle_tasks=[cartpole]")
    with pytest.raises(ConfigError, match="oracle_steps"):
        options("oracle_steps=0")
    assert default.oracle_method == "mppi"
    ilqr = suite_config(options("oracle_tasks=[cmu_track]", "oracle_planner=ilqr"))
    assert ilqr.oracle_method == "ilqr" and ilqr.oracle_tasks == ("cmu_track",)
    assert oracle_config("cmu_track", ilqr).env.oracle_substeps == 3  # the env's oracle physics
    clips = options("oracle_tasks=[cmu_track,humanoid_stand]", "clips=['02_01','09_06']")
    assert list(oracle_cases(suite_config(clips))) == [
        ("cmu_track", {"clip": "02_01"}), ("cmu_track", {"clip": "09_06"}), ("humanoid_stand", None)
    ]  # fmt: skip
    assert list(oracle_cases(ilqr)) == [("cmu_track", None)]  # the env's own clip
    with pytest.raises(ConfigError, match="oracle_planner=ilqr needs .* humanoid_stand"):
        options("oracle_planner=ilqr")  # all three tasks; standing has no residuals
    with pytest.raises(ConfigError, match="oracle_planner"):
        options("oracle_planner=lqr")
    overrides = "oracle_overrides=['planner.knots=4','planner.horizon=23']"
    spline = suite_config(options("oracle_planner=predictive", overrides))
    planner = oracle_config("humanoid_stand", spline).planner
    assert planner.name == "predictive" and (planner.knots, planner.horizon) == (4, 23)
    assert planner.interpolation == "cubic" and planner.num_samples == 10
    with pytest.raises(ConfigError, match="oracle_overrides"):
        options("oracle_overrides=['knots=4']")
    assert default.seed == 0 and suite_config(options("seed=3")).seed == 3
    with pytest.raises(ConfigError, match="seed"):
        options("seed=-1")
    with pytest.raises(ConfigError, match="models"):
        options("models=[]", suite="planner")  # only suite humanoid runs without models


def test_error_vs_horizon_figure(tmp_path: Path) -> None:
    records = [
        {"case": "delan-n100", "metric": "rollout_error", "horizon": 10, "value": 0.5,
         "rollout_steps": 5},
        {"case": "delan-n100", "metric": "rollout_error", "horizon": 1, "value": 0.2,
         "rollout_steps": 5},
        {"case": "ensemble-n100", "metric": "rollout_error", "horizon": 1, "value": 0.1},
        {"case": "ensemble-n100", "metric": "rollout_error", "horizon": 30, "value": None},
        {"case": "ensemble-n100", "metric": "fit_s", "value": 3.0},
    ]  # fmt: skip
    curves = error_curves(records)
    assert curves == {
        "delan-n100 (K=5)": [(1, [0.2]), (10, [0.5])],  # sorted by horizon
        "ensemble-n100": [(1, [0.1])],  # the skipped figure (None) left out
    }
    other_seed = {**records[1], "value": 0.4, "seed": 1}  # delan at h 1 again
    two = error_curves([*records, other_seed])["delan-n100 (K=5)"]
    assert two == [(1, [0.2, 0.4]), (10, [0.5])]
    assert describe_curves({"d": two})[0] == "d h=1: mean 0.3 (min 0.2, max 0.4, n 2)"
    data = tmp_path / "h.jsonl"
    data.write_text("\n".join(json.dumps(r) for r in [*records, other_seed]))  # with a band
    out = tmp_path / "fig" / "error.png"
    assert figures_main([str(data), "--out", str(out)]) == 0
    assert out.read_bytes()[:4] == b"\x89PNG"
    empty = tmp_path / "empty.jsonl"
    empty.write_text(json.dumps(records[-1]) + "\n")
    assert figures_main([str(empty), "--out", str(tmp_path / "none.png")]) == 2
    assert figures_main([str(tmp_path / "missing.jsonl"), "--out", str(out)]) == 2
    broken = tmp_path / "broken.jsonl"
    broken.write_text('{"case": "x", "metric": "rollout_error", "value": 1.0}\n')
    assert figures_main([str(broken), "--out", str(out)]) == 2


def test_tracking_errors_average_the_episodes_distances() -> None:
    """An episode that reaches each reference state but one, there 0.3 m off along y (the
    whole body): root error 0.3 / T on average and 0.3 at most; end effectors 0."""
    from tensordict import TensorDict

    task = make_env_parts("cmu_track", task_options=RUN_CLIP).task
    T = 6
    q = task.ref_q[1 : T + 1].clone()  # step t's action reaches ref_{t+1}
    q[2, 1] += 0.3
    rollout = TensorDict({keys.NEXT_Q: q.float()}, batch_size=[T])
    errors = tracking_errors(task, rollout)
    assert errors["root_error_m"] == pytest.approx(0.3 / T, abs=1e-6)
    assert errors["root_error_max_m"] == pytest.approx(0.3, abs=1e-6)
    assert errors["end_effector_error_m"] == pytest.approx(0.0, abs=1e-5)
    assert errors["end_effector_error_max_m"] == pytest.approx(0.0, abs=1e-5)


def test_data_run_gives_a_runs_buffered_episodes_in_order(tmp_path: Path) -> None:
    """`data_run`: the episodes of a run's checkpointed buffer (one that wrapped: the oldest
    transitions overwritten), oldest first, the last ones the test set."""
    from omegaconf import OmegaConf

    from mbrl_delan.data.buffer import add_transitions, buffer_state, make_replay_buffer
    from mbrl_delan.training.checkpoint import save_checkpoint

    parts = make_env_parts("humanoid_stand")
    cfg = HumanoidBenchConfig(episode_len=12)
    episodes = collect_episodes(parts.system, parts.task, 60, cfg, seed=3)  # 5 x 12
    total = sum(e.shape[0] for e in episodes)
    buffer = make_replay_buffer(total - 4)  # the first episode's first 4 steps overwritten
    for i, episode in enumerate(episodes):
        add_transitions(buffer, episode.to(torch.float32).set("episode", torch.full((12, 1), i)))
    save_checkpoint(tmp_path / "checkpoint.pt", {"loop": {"buffer": buffer_state(buffer)}})
    OmegaConf.save({"env": {"name": "humanoid_stand"}}, tmp_path / "config.yaml")

    train, test = split_run_episodes(str(tmp_path), "humanoid_stand", test_transitions=20)
    assert [e.shape[0] for e in train] == [8, 12, 12] and [e.shape[0] for e in test] == [12, 12]
    for got, want in zip(train[1:] + test, episodes[1:], strict=True):
        torch.testing.assert_close(got[keys.NEXT_Q], want[keys.NEXT_Q].to(torch.float32).double())
    torch.testing.assert_close(train[0][keys.Q], episodes[0][keys.Q][4:].float().double())
    assert first_transitions(train, 30, "run").shape == (30,)
    with pytest.raises(ConfigError, match="more than the 32 training transitions"):
        first_transitions(train, 33, "run")
    with pytest.raises(ConfigError, match="a run of env=humanoid_stand, not humanoid_walk"):
        split_run_episodes(str(tmp_path), "humanoid_walk", 20)
    with pytest.raises(ConfigError, match="no checkpoint.pt"):
        split_run_episodes(str(tmp_path / "missing"), "humanoid_stand", 20)


def test_a_diverged_fit_is_recorded_and_the_suite_goes_on(monkeypatch) -> None:
    import mbrl_delan.benchmarks.humanoid as suite
    from mbrl_delan.benchmarks import BenchSettings
    from mbrl_delan.training.fit import FitReport, TrainingDivergedError

    fit = suite.fit_world_model

    def diverging(name, *args, **kwargs):
        if name == "delan":
            raise TrainingDivergedError(1, "grad_norm", math.inf, FitReport(), "")
        return fit(name, *args, **kwargs)

    monkeypatch.setattr(suite, "fit_world_model", diverging)
    cfg = replace(HumanoidBenchConfig.quick(), models=("delan", "ensemble"), oracle_tasks=())
    opts = BenchSettings(device=torch.device("cpu"))
    records = list(suite.run_humanoid(cfg, opts))
    delan = [r for r in records if r.case.startswith("delan-")]
    assert len(delan) == 1 and delan[0].value is None
    assert "fit diverged" in delan[0].extra["note"] and "grad_norm" in delan[0].extra["note"]
    ensemble = [r for r in records if r.case.startswith("ensemble-")]
    assert {r.metric for r in ensemble} == {"fit_s", "rollout_error"}
