"""Suite `robust`: does the oracle's planner stand whole episodes, and how fast does it plan.

For each task in `tasks` (default `humanoid_stand`) and each planner seed in `seeds` (default
0, 1, 2), the loop's oracle (`train.build_oracle` on the config ``python -m mbrl_delan.train
env=<task>`` composes, with the suite's `overrides`, e.g. ``env.plan_cost=balance``) runs
`starts` episodes (default 10) of `oracle_steps` control steps (default the task's 1,000) on the
real env, episode i from the reset seed ``1000 (seed + 1) + i`` (distinct starts for every seed
and episode). Per episode it keeps the fall step (the control step at which the task
terminated, None if it stood to the end), the return and the planning ms per control step
(the policy's calls only).

The push test (`push` m/s, at control step `push_step`): the whole body's velocity is changed
by `push` m/s along +x at that step (the free root's linear velocity; an impulse of `push`
times the total mass at the centre of mass, 42.1 N s per m/s on Humanoid-v5); the planner
sees the pushed state at its next call.

Records, per task and seed, with fields `task`, `dynamics` (`mujoco`), `planner`,
`num_samples`, `iterations`, `horizon`, `knots`, `episodes`, `plan_cost`, `plan_speed` (the
balance cost's target speed, null: the task's), `seed`, `push`,
`push_step`, `speed_mean` (the episodes' mean of `speed`) and `per_episode` (each episode's
`start`, `fall_step`, `return`, `plan_ms_per_control_step` and `speed`: the root's x
displacement over the episode's duration, m/s):

- `falls`: the episodes that terminated (count);
- `plan_ms_per_control_step`: the mean over all control steps of all its episodes (ms);
- `return_mean`: the mean episode return.

`python -m mbrl_delan.benchmarks.robust FILE [FILE ...] [--out PNG] [--timing FILE ...]`
prints a Markdown table (`fall_table`: per setting the episodes, falls, the fall rate with its
95% Wilson interval, mean speed and planning ms) and with `--out` draws
the share of episodes that fell against the planning ms per control step, one point per
setting (`setting_label`: the plan cost, the planner's samples, iterations and horizon and
the oracle's physics steps per control step; pushed runs apart) over all its seeds; a setting
in the `--timing` records (runs timed apart, e.g. with the host idle) takes its ms from them.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from matplotlib.ticker import NullFormatter
from omegaconf import DictConfig

from mbrl_delan.benchmarks import BenchSettings, host_fields
from mbrl_delan.benchmarks.figures import read_record_files
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import RobustSuiteConfig
from mbrl_delan.conf.checks import compose_train_config
from mbrl_delan.envs.real import MujocoTaskEnv
from mbrl_delan.figure_style import page_figure, save_figure
from mbrl_delan.intervals import wilson_interval
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.stops import stop_line
from mbrl_delan.systems.system import State

log = logging.getLogger(__name__)

SUITE = "robust"
METRIC_MS = "plan_ms_per_control_step"
TASKS = ("humanoid_stand",)
SEEDS = (0, 1, 2)
STARTS = 10  # episodes per seed
QUICK = {"starts": 1, "steps": 5, "seeds": (0,)}
START_SEED = 1000  # episode i of planner seed s starts from the reset seed 1000 (s + 1) + i


@dataclass(frozen=True)
class Push:
    """A change of the whole body's velocity by `speed` m/s along +x at control step `step`."""

    speed: float
    step: int


@dataclass
class Episode:
    """One robustness episode: where it started, when it fell (None: it stood), its return
    and its planning ms per control step."""

    start: int
    steps: int  # control steps run
    fall_step: int | None
    episode_return: float
    plan_ms: float
    speed: float  # the root's mean velocity along +x over the episode (m/s)

    def to_dict(self) -> dict[str, Any]:
        return {"start": self.start, "fall_step": self.fall_step,
                "return": round(self.episode_return, 3),
                "plan_ms_per_control_step": round(self.plan_ms, 2),
                "speed": round(self.speed, 3)}  # fmt: skip


def _push(env: MujocoTaskEnv, push: Push) -> None:
    """Add `push.speed` to the free root's x velocity (every body moves with it)."""
    state = env.get_state()
    qd = state.qd.clone()
    qd[0] += push.speed
    env.set_state(State(q=state.q, qd=qd))


def run_robust_episode(
    policy: PlannerPolicy, env: MujocoTaskEnv, start: int, steps: int, push: Push | None = None
) -> Episode:
    """One episode of at most `steps` control steps from the reset seed `start`."""
    env.reset(seed=start)
    policy.reset()
    x0 = float(env.get_state().q[0])
    total, seconds = 0.0, 0.0

    def episode(run: int, fall_step: int | None) -> Episode:
        speed = (float(env.get_state().q[0]) - x0) / (run * env.env_parts.system.control_dt)
        return Episode(start, run, fall_step, total, 1e3 * seconds / run, speed)

    for t in range(steps):
        if push is not None and t == push.step:
            _push(env, push)
        state = env.get_state()
        began = time.perf_counter()
        action = policy.act(state.q.float(), state.qd.float())
        seconds += time.perf_counter() - began
        _, reward, terminated, _, _ = env.step(action.detach().cpu().numpy())
        total += reward
        if terminated:
            return episode(t + 1, t + 1)
    return episode(steps, None)


@dataclass(frozen=True)
class RobustConfig:
    """What the suite runs (module docstring)."""

    tasks: tuple[str, ...] = TASKS
    seeds: tuple[int, ...] = SEEDS
    starts: int = STARTS
    steps: int | None = None  # control steps per episode (None: the task's)
    overrides: tuple[str, ...] = ()
    push: Push | None = None

    @classmethod
    def from_options(cls, options: RobustSuiteConfig, quick: bool = False) -> RobustConfig:
        """The options' choices; None keeps the default (or the quick size under `quick`)."""
        sizes = QUICK if quick else {}
        push = None if options.push is None else Push(options.push, options.push_step)
        return cls(
            tasks=tuple(options.tasks or TASKS),
            seeds=tuple(options.seeds or sizes.get("seeds", SEEDS)),
            starts=options.starts or sizes.get("starts", STARTS),
            steps=options.oracle_steps or sizes.get("steps"),
            overrides=tuple(options.overrides),
            push=push,
        )


def _fields(cfg: DictConfig, task: str, rc: RobustConfig, seed: int) -> dict[str, Any]:
    planner = cfg.planner
    return dict(
        task=task, dynamics="mujoco", planner=planner.name,
        num_samples=planner.get("num_samples"), iterations=planner.get("iterations"),
        horizon=planner.horizon, knots=planner.get("knots"), plan_cost=cfg.env.plan_cost,
        plan_speed=cfg.env.get("plan_speed"),
        oracle_substeps=cfg.env.oracle_substeps, episodes=rc.starts, seed=seed,
        push=None if rc.push is None else rc.push.speed,
        push_step=None if rc.push is None else rc.push.step, overrides=list(rc.overrides),
    )  # fmt: skip


def seed_episodes(task: str, seed: int, rc: RobustConfig) -> tuple[DictConfig, list[Episode]]:
    """The oracle of planner seed `seed` on `task`: its `starts` episodes."""
    from mbrl_delan.conf.loop import build_oracle

    cfg = compose_train_config([f"env={task}", f"seed={seed}", *rc.overrides])
    env = MujocoTaskEnv(task, episode_len=rc.steps)
    policy = build_oracle(cfg, env.env_parts.physics, env.env_parts.task)
    steps = env.episode_len
    episodes = []
    try:
        for i in range(rc.starts):
            episode = run_robust_episode(policy, env, START_SEED * (seed + 1) + i, steps, rc.push)
            log.info("robust: %s seed %d start %d: %s", task, seed, i, episode.to_dict())
            episodes.append(episode)
    finally:
        env.close()
        policy.objective_factory.close()
    return cfg, episodes


def run_robust_suite(options: RobustSuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    rc = RobustConfig.from_options(options, bench.quick)
    host = host_fields(torch.device("cpu"))
    for task in rc.tasks:
        for seed in rc.seeds:
            cfg, episodes = seed_episodes(task, seed, rc)
            fields = _fields(cfg, task, rc, seed) | host
            fields["per_episode"] = [e.to_dict() for e in episodes]
            fields["speed_mean"] = round(float(np.mean([e.speed for e in episodes])), 3)
            falls = sum(e.fall_step is not None for e in episodes)
            steps = np.array([e.steps for e in episodes])
            plan_ms = float(np.dot([e.plan_ms for e in episodes], steps) / steps.sum())
            mean_return = float(np.mean([e.episode_return for e in episodes]))
            case = f"{task}-mujoco-s{seed}"
            yield BenchRecord(SUITE, case, "falls", falls, "episodes", "cpu", fields)
            yield BenchRecord(SUITE, case, METRIC_MS, plan_ms, "ms", "cpu",
                              fields)  # fmt: skip
            yield BenchRecord(SUITE, case, "return_mean", mean_return, "return", "cpu", fields)


def setting_label(record: dict[str, Any]) -> str:
    """A robust record's setting: plan cost, planner, samples x iterations, horizon, the
    oracle's physics steps per control step, push."""
    steps = record["oracle_substeps"]
    label = (f"{record['plan_cost']}: {record['planner']} N {record['num_samples']} x "
             f"{record['iterations']}, H {record['horizon']}, "
             f"{steps} physics step{'' if steps == 1 else 's'}")  # fmt: skip
    return label if record.get("push") is None else f"{label}, push {record['push']} m/s"


@dataclass
class SettingPoint:
    """One setting over all its seeds: falls of episodes and the mean planning ms."""

    falls: int = 0
    episodes: int = 0
    speed_sum: float = 0.0  # sum of the records' speed_mean x their episodes (m/s)
    ms_sum: float = 0.0  # sum of the timed records' ms x their episodes
    ms_episodes: int = 0  # the episodes those records timed

    @property
    def ms(self) -> float:
        return self.ms_sum / max(self.ms_episodes, 1)

    @property
    def speed(self) -> float:
        """The episodes' mean forward speed (m/s)."""
        return self.speed_sum / max(self.episodes, 1)


def setting_points(
    records: list[dict[str, Any]], timing: list[dict[str, Any]] | None = None
) -> dict[str, SettingPoint]:
    """Setting label -> its point, from the `falls` and `plan_ms_per_control_step` records of
    suite robust (other records left out). A setting that `timing` (robust records of runs
    timed apart, e.g. with the host idle) has takes its ms from those records alone."""
    points: dict[str, SettingPoint] = defaultdict(SettingPoint)
    for r in _robust(records, "falls"):
        point = points[setting_label(r)]
        point.falls += int(r["value"])
        point.episodes += int(r["episodes"])
        point.speed_sum += float(r.get("speed_mean") or 0.0) * int(r["episodes"])
    own, apart = _by_setting(_robust(records, METRIC_MS)), _by_setting(_robust(timing, METRIC_MS))
    for label, point in points.items():
        for r in apart.get(label) or own.get(label, []):
            point.ms_sum += float(r["value"]) * int(r["episodes"])
            point.ms_episodes += int(r["episodes"])
    return dict(points)


def _robust(records: list[dict[str, Any]] | None, metric: str) -> list[dict[str, Any]]:
    """The records of suite robust with `metric` and a value."""
    return [r for r in records or [] if r.get("suite") == SUITE and r.get("metric") == metric
            and r.get("value") is not None]  # fmt: skip


def _by_setting(records: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    grouped: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        grouped[setting_label(r)].append(r)
    return grouped


def plot_falls(points: dict[str, SettingPoint], path: Path, title: str,
               control_ms: float | None = None) -> Path:  # fmt: skip
    """Falls (% of episodes) against planning ms per control step, one labelled point per
    setting; a dashed line at the control period `control_ms`."""
    fig, axes = page_figure(4.6)
    ax = axes[0, 0]
    for label, p in sorted(points.items(), key=lambda item: item[1].ms):
        share = 100.0 * p.falls / max(p.episodes, 1)
        marker = "x" if "push" in label else "o"  # pushed runs: shorter episodes, a push
        ax.plot(p.ms, share, marker=marker, markersize=9, linestyle="none",
                label=f"{label} ({p.falls}/{p.episodes})")  # fmt: skip
    if control_ms is not None:
        ax.axvline(control_ms, color="grey", linestyle="--", label="control period")
    ax.set_xscale("log")
    ticks = [t for t in (10, 15, 20, 30, 50, 100, 200, 500, 1000)
             if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]  # fmt: skip
    ax.set_xticks(ticks, [str(t) for t in ticks])
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("planning ms per control step (2 cores)")
    ax.set_ylabel("episodes that fell (%)")
    ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(title)
    fig.legend(loc="outside lower center", ncols=1, frameon=False)
    return save_figure(fig, path)


def fall_table(points: dict[str, SettingPoint]) -> str:
    """A Markdown table, one row per setting: its episodes, falls, fall rate with the 95%
    Wilson interval, mean forward speed and planning ms per control step."""
    rows = ["| setting | episodes | falls | fall rate (95% interval) | speed (m/s) | plan ms |",
            "|---|---:|---:|---|---:|---:|"]  # fmt: skip
    for label, p in sorted(points.items()):
        low, high = wilson_interval(p.falls, p.episodes)
        rate = f"{p.falls / p.episodes:.1%} ({low:.1%} to {high:.1%})"
        rows.append(f"| {label} | {p.episodes} | {p.falls} | {rate} | {p.speed:.2f} | {p.ms:.1f} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="falls against planning time, suite robust")
    parser.add_argument("files", nargs="+", type=Path, help="records of suite robust (JSONL)")
    parser.add_argument("--out", type=Path, help="the figure to write (PNG); none: the table only")
    parser.add_argument("--title", default="humanoid_stand: the oracle's falls and plan time")
    parser.add_argument("--control-ms", type=float, default=15.0, help="the control period")
    parser.add_argument(
        "--timing", nargs="*", type=Path, default=[], help="runs timed apart: their settings' ms"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    records, timing = read_record_files(args.files), read_record_files(args.timing)
    if records is None or timing is None:
        return 2
    points = setting_points(records, timing)
    if not points:
        stop_line("no records", f"no suite robust records in {', '.join(map(str, args.files))}")
        return 2
    print(fall_table(points))  # the table is the command's output: stdout
    if args.out is not None:
        log.info("figure: %s", plot_falls(points, args.out, args.title, args.control_ms))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
