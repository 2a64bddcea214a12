"""`python -m mbrl_delan.train`: model-based RL with a learned world model and a sampling planner.

Builds the parts from the Hydra config, runs the loop of `training/loop.py`, checkpoints
every round (atomically) and writes `metrics.jsonl`, `summary.json` and plots in the run dir.
`resume=<run dir>` continues a stopped run from its last checkpoint with its saved config.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Any

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from mbrl_delan import EXIT_INTERRUPTED
from mbrl_delan.conf.checks import (
    ConfigError,
    command_line_overrides,
    exit_on_config_errors,
    validate_train_config,
)
from mbrl_delan.conf.loop import (
    build_loop,
    schedule_of,
    start_mechanics,
    with_fit_structure,
)
from mbrl_delan.conf.videos import check_video, write_videos
from mbrl_delan.data.buffer import NonFiniteDataError
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.provenance import provenance
from mbrl_delan.runs import OracleEpisodes, oracle_of_run, write_oracle
from mbrl_delan.stops import STOPPED, stop_line
from mbrl_delan.sweep import (
    crash_dir,
    discard_unstarted_run_dir,
    exit_or_raise,
    last_iteration,
    marks_crash,
    resumed_config,
    with_sweep_group,
)
from mbrl_delan.systems.external import MissingPackageError
from mbrl_delan.training.checkpoint import (
    CHECKPOINT_FILE,
    CheckpointError,
    RunWriteError,
    atomic_write,
    load_checkpoint,
    prev_path,
    remove_stale_temps,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from mbrl_delan.training.fidelity import FidelityReference
from mbrl_delan.training.fit import TrainingDivergedError
from mbrl_delan.training.loop import LoopHooks, MBRLLoop
from mbrl_delan.training.plots import plot_run
from mbrl_delan.training.recorder import (
    METRICS_FILE,
    RUN_CONFIG,
    SUMMARY_FILE,
    WEIGHTS_FILE,
    Recorder,
    WandbOptions,
    resume_metrics,
)
from mbrl_delan.training.summary import last_evaluation, run_summary, with_zero_baseline

log = logging.getLogger("mbrl_delan.train")
LOG_FILE = "train.log"  # Hydra's log of the run, in its run dir (hydra.job.name)


OmegaConf.register_new_resolver(
    "run_dir_or", lambda resume, default: resume or default, replace=True
)


def _save(run_dir: Path, loop: MBRLLoop) -> None:
    state = {
        "loop": loop.state_dict(),
        "rng": rng_state(),
        "oracle_returns": loop.oracle_returns,
        "oracle_steps": loop.oracle_steps,
        "warmup_done": loop.warmup_done,
    }
    save_checkpoint(run_dir / CHECKPOINT_FILE, state)


def _oracle_from(cfg: DictConfig) -> OracleEpisodes | None:
    """The episodes `budget.oracle_from` names (None where it is unset); a run dir that does
    not hold them, or evaluated other ones, is a config error."""
    if cfg.budget.oracle_from is None:
        return None
    try:
        return oracle_of_run(cfg.budget.oracle_from, cfg)
    except (FileNotFoundError, ValueError) as err:
        raise ConfigError(str(err)) from err


def _take_oracle(loop: MBRLLoop, episodes: OracleEpisodes) -> None:
    """Another run's oracle and zero-torque episodes as this run's (`budget.oracle_from`)."""
    loop.oracle_returns, loop.oracle_steps = episodes.returns, episodes.steps
    loop.zero_returns = episodes.zero_returns
    loop.oracle_planning = dict(episodes.planning)
    if episodes.fidelity_reference is not None:
        loop.fidelity_reference = FidelityReference.from_state_dict(episodes.fidelity_reference)


def _keep_oracle(cfg: DictConfig, run_dir: Path, loop: MBRLLoop, stamp: dict[str, Any]) -> None:
    """The oracle's and zero-torque episodes this run evaluated itself, on their own
    (`write_oracle`): another run's `budget.oracle_from` for the same config."""
    if cfg.budget.oracle_from is not None or loop.oracle_returns is None or not loop.zero_returns:
        return
    reference = loop.fidelity_reference
    episodes = OracleEpisodes(loop.oracle_returns, loop.oracle_steps, loop.zero_returns,
                              None if reference is None else reference.state_dict(),
                              loop.oracle_planning)  # fmt: skip
    write_oracle(run_dir, cfg, episodes, stamp)


def _save_weights(run_dir: Path, loop: MBRLLoop) -> None:
    """The final world model's state dict as `WEIGHTS_FILE`: small, where the checkpoint
    holds the replay buffer too, so a record folder can keep it and be re-scored."""
    state = loop.model.state_dict()
    atomic_write(run_dir / WEIGHTS_FILE, lambda f: torch.save(state, f), keep_prev=False)


def _resolve_run(cfg: DictConfig) -> tuple[DictConfig, Path, dict[str, Any] | None, bool]:
    """The config and run dir to use, the checkpoint when resuming, and whether the command
    line changed the resumed run's config (saved only once it is checked). Writes nothing
    but an unreadable checkpoint's move aside (`load_checkpoint`'s `set_aside`)."""
    if cfg.resume is None:
        run_dir = Path(HydraConfig.get().runtime.output_dir)
        return with_sweep_group(cfg), run_dir, None, False
    run_dir = Path(cfg.resume)
    overrides = HydraConfig.get().overrides.task if HydraConfig.initialized() else []
    run_cfg, changed = resumed_config(overrides, cfg)
    for key in changed:
        log.info("resume: %s=%s", key, OmegaConf.select(run_cfg, key))
    ckpt = run_dir / CHECKPOINT_FILE
    state = None
    if ckpt.exists() or prev_path(ckpt).exists():
        state = load_checkpoint(ckpt, weights_only=False, set_aside=True)
    return run_cfg, run_dir, state, bool(changed)


@marks_crash
def train(cfg: DictConfig) -> dict[str, Any]:
    """Run (or resume) one training run; returns its summary.

    When it raises, the run dir gets ``crash.json`` (see ``mbrl_delan.sweep``).
    """
    cfg, run_dir, state, changed = _resolve_run(cfg)
    cfg = validate_train_config(cfg)
    if state is None and cfg.model.get("init_from") is not None:
        cfg = with_fit_structure(cfg)
    check_video(cfg)
    taken = None if state is not None else _oracle_from(cfg)  # checked before anything is made
    run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.resume is not None:
        remove_stale_temps(run_dir)
    loop, oracle = build_loop(cfg, run_dir)
    stamp = provenance("mbrl_delan.train")  # the command, the code, the host at the start
    if state is None and cfg.model.get("init_from") is not None:
        start_mechanics(cfg.model, loop.model, loop.system)
    # written once the run is built: an error found while building (a missing clip) leaves no
    # folder (`_discard_refused`); a resume's accepted overrides stay for later ones
    if state is None or changed:
        text = OmegaConf.to_yaml(cfg, resolve=True).encode()
        atomic_write(run_dir / RUN_CONFIG, lambda f: f.write(text), keep_prev=False)
    if taken is not None:
        _take_oracle(loop, taken)
        log.info("the oracle's and zero-torque episodes of %s", cfg.budget.oracle_from)
    if state is not None:
        loop.load_state_dict(state["loop"])
        set_rng_state(state["rng"])
        loop.oracle_returns, loop.warmup_done = state["oracle_returns"], state["warmup_done"]
        loop.oracle_steps = state.get("oracle_steps")  # absent from older checkpoints
        log.info(
            "resumed %s at iteration %d (%d env steps)",
            run_dir,
            loop.counters.iteration,
            loop.counters.env_steps,
        )
        if loop.finished(schedule_of(cfg)) and (run_dir / SUMMARY_FILE).is_file():
            resume_metrics(run_dir / METRICS_FILE, loop.counters.iteration, loop.last_round)
            log.info("the run is finished: nothing to run, its results are left as they are")
            summary = json.loads((run_dir / SUMMARY_FILE).read_text(encoding="utf-8"))
            if "gap_closed" not in summary or "eval_steps_median" not in summary:
                summary = _complete_summary(cfg, run_dir, loop, summary)  # an older run's
            _print_summary(run_dir, summary)
            return summary
    recorder = Recorder(
        run_dir,
        cfg.logger.backend,
        cfg.logger.project,
        cfg.logger.group,
        OmegaConf.to_container(cfg, resolve=True),
        resume_iteration=loop.counters.iteration if state else None,
        step_key="env_steps",
        last_record=loop.last_round,
        wandb_options=WandbOptions.of(cfg.logger),
    )
    with recorder:
        _run(cfg, run_dir, loop, oracle, recorder)
        _save_weights(run_dir, loop)
        _keep_oracle(cfg, run_dir, loop, stamp)
        summary = run_summary(cfg, run_dir, loop) | stamp
        recorder.write_summary(summary)
        for path in plot_run(run_dir):
            recorder.log_image(path.stem, path)
        recorder.log_artifact(run_dir / CHECKPOINT_FILE)
    _print_summary(run_dir, summary)
    return summary


def _complete_summary(
    cfg: DictConfig, run_dir: Path, loop: MBRLLoop, summary: dict[str, Any]
) -> dict[str, Any]:
    """A finished run's summary saved before its newer fields, completed: the zero-control
    baseline (evaluated from its final evaluation's starts, then kept in its checkpoint) and
    the final evaluation's median episode length."""
    if "gap_closed" not in summary:
        loop.evaluate_zero(cfg.budget.final_eval_episodes)
        _save(run_dir, loop)
        summary = with_zero_baseline(loop, summary)
    if "eval_steps_median" not in summary:
        summary["eval_steps_median"] = last_evaluation(run_dir).get("eval_steps_median")
    text = json.dumps(summary, indent=2, sort_keys=True) + "\n"
    atomic_write(run_dir / SUMMARY_FILE, lambda f: f.write(text.encode("utf-8")), keep_prev=False)
    log.info("completed %s with the fields it was saved without", run_dir / SUMMARY_FILE)
    return summary


def _run(
    cfg: DictConfig,
    run_dir: Path,
    loop: MBRLLoop,
    oracle: PlannerPolicy,
    recorder: Recorder,
) -> None:
    """`loop.run` with the entry point's hooks: metrics to the recorder, an atomic checkpoint
    after each stage, videos and a progress bar after each round, and one over the oracle's
    episodes (terminals only, as the round's bar)."""
    by_steps = cfg.budget.env_steps is not None  # the bar counts env steps, else rounds
    bar = tqdm(
        total=cfg.budget.env_steps if by_steps else cfg.budget.iterations,
        initial=loop.counters.env_steps if by_steps else loop.counters.iteration,
        desc="mbrl",
        unit="step" if by_steps else "iter",
        disable=None,
    )

    def after_round(metrics: dict[str, Any]) -> None:
        write_videos(cfg, run_dir, loop, recorder)
        bar.update(metrics["env_steps"] - bar.n if by_steps else 1)
        bar.set_postfix(
            steps=metrics["env_steps"],
            ret=f"{metrics['train_return']:.1f}",
            oracle=f"{metrics['oracle_return_mean']:.1f}",
        )

    oracle_bar = tqdm(desc="oracle", unit="episode", disable=None, delay=1.0)

    def oracle_episode(done: int, total: int) -> None:
        oracle_bar.total = total
        oracle_bar.update(done - oracle_bar.n)
        if done == total:
            oracle_bar.close()

    hooks = LoopHooks(
        log_round=lambda metrics: recorder.log(metrics, loop.counters.iteration),
        checkpoint=lambda: _save(run_dir, loop),
        after_round=after_round,
        oracle_episode=oracle_episode,
    )
    try:
        loop.run(schedule_of(cfg), oracle, hooks)
    finally:
        oracle_bar.close()
        bar.close()


def _print_summary(run_dir: Path, s: dict[str, Any]) -> None:
    log.info("run dir: %s", run_dir)
    log.info(
        "%s / %s / %s, seed %s: eval return %.4g +- %.2g, oracle %.4g (fraction %.3f), "
        "%d env steps, %.0f s",
        s["env"],
        s["model"],
        s["planner"],
        s["seed"],
        s["eval_return_mean"],
        s["eval_return_std"] or 0.0,
        s["oracle_return_mean"],
        s["fraction_of_oracle"] or float("nan"),
        s["env_steps"],
        s["wall_time_s"],
    )


def _discard_refused(cfg: DictConfig) -> None:
    """A new run stopped before it wrote its config (refused by its input, or Ctrl-C while it
    was being built) leaves no folder; a resumed run's folder is never touched."""
    run_dir = crash_dir(cfg)
    if cfg.resume is None and run_dir is not None:
        discard_unstarted_run_dir(run_dir, LOG_FILE)


def _stopped_by_user(cfg: DictConfig) -> None:
    """Ctrl-C's one line: the run dir and the command that continues it from its last
    checkpoint; a new run stopped before its config was written leaves no folder."""
    run_dir = crash_dir(cfg)
    if run_dir is None or not (run_dir / RUN_CONFIG).is_file():
        stop_line(STOPPED, "before the run started: nothing was kept", logging.WARNING)
        _discard_refused(cfg)
        return
    if not (run_dir / CHECKPOINT_FILE).is_file():
        stop_line(STOPPED, f"before the first checkpoint: {run_dir} holds the config only; "
                  "run the command again to start over", logging.WARNING)  # fmt: skip
        return
    rounds = last_iteration(run_dir)
    after = f"round {rounds}" if rounds is not None else "no round"
    stop_line(STOPPED, f"after {after}: {run_dir} keeps its last checkpoint; continue with "
              f"python -m mbrl_delan.train resume={run_dir}", logging.WARNING)  # fmt: skip


@hydra.main(version_base="1.3", config_path="configs/train", config_name="config")
def run(cfg: DictConfig) -> float | None:
    """The Hydra task: the config was checked by `StartChecks` before the run dir existed."""
    try:
        summary = train(cfg)
    except KeyboardInterrupt:
        _stopped_by_user(cfg)
        sys.exit(EXIT_INTERRUPTED)
    except ConfigError as err:
        stop_line("config error", err)
        _discard_refused(cfg)
        exit_or_raise(2, err)
    except TrainingDivergedError as err:
        hint = (
            f"; the model started from model.init_from={cfg.model.init_from}: a DeLaN fitted "
            "on motion capture without model.armature=true can have a nearly singular M off "
            "the mocap's states, so its forward predictions blow up (docs/humanoid.md, "
            "starting from the mocap fit)"
        )
        stop_line("training diverged", f"{err} (the last good checkpoint is kept)"
                  f"{hint if cfg.model.get('init_from') is not None else ''}")  # fmt: skip
        exit_or_raise(1, err)
    except NonFiniteDataError as err:
        stop_line("bad data", f"{err} (not added to the buffer; the last checkpoint is kept)")
        exit_or_raise(1, err)
    except MissingPackageError as err:
        stop_line("missing package", err)
        _discard_refused(cfg)
        exit_or_raise(2, err)
    except (CheckpointError, FileNotFoundError) as err:
        stop_line("cannot resume", err)
        exit_or_raise(2, err)
    except RunWriteError as err:
        run_dir = crash_dir(cfg)
        resumable = run_dir is not None and (run_dir / CHECKPOINT_FILE).is_file()
        hint = f"; once it can be written, python -m mbrl_delan.train resume={run_dir}"
        stop_line("write error", f"{err}{hint if resumable else ''}")
        exit_or_raise(2, err)
    return summary["eval_return_mean"]


def main() -> None:
    """``python -m mbrl_delan.train``: a config error exits 2 with one line naming it."""
    sys.argv[1:] = command_line_overrides(sys.argv[1:])
    exit_on_config_errors(run)


if __name__ == "__main__":
    main()
