"""The videos of a training run from its config (``video=true``): the backend checked before
the run starts, the evaluation episodes of a round drawn to ``<run dir>/videos``."""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig
from tensordict import TensorDictBase

from mbrl_delan.conf.checks import ConfigError
from mbrl_delan.conf.loop import env_parts, schedule_of
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.tracking import MotionTracking
from mbrl_delan.training.loop import MBRLLoop
from mbrl_delan.training.recorder import Recorder
from mbrl_delan.training.video import (
    RENDER_ERRORS,
    VideoBackendError,
    VideoRecorder,
    check_backend,
    resolve_backend,
    rollout_states,
    root_travels,
    step_reward_overlays,
)

log = logging.getLogger(__name__)


VIDEO_DIR = "videos"


def check_video(cfg: DictConfig) -> None:
    """With `video=true`: check the video keys and render a test frame, before any training."""
    if not cfg.video:
        return
    for key in ("video_width", "video_height"):
        if cfg[key] % 2:
            raise ConfigError(f"{key}={cfg[key]!r} is not valid; it must be an even integer >= 2")
    try:
        backend = check_backend(cfg.video_backend)
    except VideoBackendError as err:
        raise ConfigError(f"video=true: {err}") from err
    log.info("videos: MuJoCo renders with the %r OpenGL backend", backend)


def _record_episode(video: VideoRecorder, path: Path, rollout: TensorDictBase, task: Task) -> Path:
    """One episode's MP4; a tracking task's shows its reference pose as a translucent ghost
    in each frame."""
    q, qd = rollout_states(rollout)
    overlays = step_reward_overlays(rollout)
    ghost = task.reference_poses(q.shape[0]) if isinstance(task, MotionTracking) else None
    return video.record(path, q, qd, overlays, ghost)


def write_videos(cfg: DictConfig, run_dir: Path, loop: MBRLLoop, recorder: Recorder) -> None:
    """Render the kept episodes of this round's evaluation to ``<run dir>/videos`` and wandb,
    and at the final one the oracle's (``oracle_ep<j>.mp4``); a tracking task's reference
    pose is drawn in each frame as a translucent ghost.

    Only the final evaluation is rendered, or every one with `video_every_eval=true`. Runs after
    the round's checkpoint: a failed video only warns and never leaves a partial MP4.
    """
    evaluation, k = loop.last_evaluation, loop.counters.iteration
    if not cfg.video or evaluation is None or not evaluation.rollouts:
        return
    final = loop.finished(schedule_of(cfg))
    if not final and not cfg.video_every_eval:
        return
    episodes = [
        (f"eval_iter{k}_ep{j}", f"eval_ep{j}", r) for j, r in enumerate(evaluation.rollouts)
    ]
    if final:  # and the oracle's episodes from the same starts
        episodes += [
            (f"oracle_ep{j}", f"oracle_ep{j}", r) for j, r in enumerate(loop.oracle_rollouts)
        ]
    task = env_parts(cfg).task
    try:
        with VideoRecorder(
            loop.system.mj_model(),
            cfg.video_width,
            cfg.video_height,
            fps=1.0 / loop.system.control_dt,
            backend=resolve_backend(cfg.video_backend),
            track_root=root_travels(loop.system.layout.types),
            markers=task.markers(),
        ) as video:
            for stem, key, rollout in episodes:
                path = _record_episode(video, run_dir / VIDEO_DIR / f"{stem}.mp4", rollout, task)
                log.info("video: %s", path)
                recorder.log_video(f"video/{key}", path, loop.counters.env_steps)
    except RENDER_ERRORS as err:
        name = type(err).__name__
        log.warning("no video of iteration %d (%s: %s); the run goes on", k, name, err)
