"""Metric logging of a run: ``metrics.jsonl`` in the run dir, and wandb in offline mode.

Every record carries the loop ``iteration`` it belongs to. On resume from a checkpoint taken at
iteration ``k``, records with ``iteration > k`` are dropped from ``metrics.jsonl`` (they will be
logged again), so the file never holds the same step twice.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from mbrl_delan.training.checkpoint import atomic_write

log = logging.getLogger(__name__)

RUN_CONFIG = "config.yaml"  # the run's resolved config, written by the entry point
METRICS_FILE = "metrics.jsonl"
SUMMARY_FILE = "summary.json"
WANDB_ID_FILE = "wandb_id.txt"
ITERATION = "iteration"  # step key of every metrics record


def _jsonable(value: Any) -> Any:
    """Plain JSON value: tensors / numpy scalars become numbers, NaN/inf become null."""
    if hasattr(value, "tolist") and callable(value.tolist):  # torch / numpy
        value = value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def read_metrics(path: str | Path) -> list[dict[str, Any]]:
    """Records of a ``metrics.jsonl`` file; a damaged line (e.g. cut by a crash) is skipped."""
    path = Path(path)
    if not path.is_file():
        return []
    records = []
    with path.open(encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                log.warning("skipping unreadable line %d of %s", lineno, path)
                continue
            if isinstance(record, dict):
                records.append(record)
    return records


def _truncate_metrics(path: Path, resume_iteration: int | None) -> None:
    """Keep only records with ``iteration <= resume_iteration`` (none when it is None)."""
    if not path.exists():
        return
    if resume_iteration is None:
        log.warning("%s exists and this is not a resumed run: starting it afresh", path)
        kept: list[dict[str, Any]] = []
    else:
        kept = [
            r
            for r in read_metrics(path)
            if isinstance(r.get(ITERATION), int) and r[ITERATION] <= resume_iteration
        ]
    lines = "".join(json.dumps(r) + "\n" for r in kept)
    atomic_write(path, lambda f: f.write(lines.encode("utf-8")), keep_prev=False)


class Recorder:
    """Writes metric records to ``run_dir/metrics.jsonl`` and (optionally) to wandb.

    Args:
        run_dir: the run's folder (created if missing).
        use_wandb: also log to wandb, in offline mode unless ``WANDB_MODE`` is set.
        wandb_project: wandb project name.
        wandb_group: wandb group (e.g. a sweep name), or None.
        config: the run's resolved configuration, stored with the wandb run.
        resume_iteration: the iteration of the checkpoint a resumed run starts from; records
            after it are removed. ``None`` starts a fresh ``metrics.jsonl``.
    """

    def __init__(
        self,
        run_dir: Path,
        use_wandb: bool,
        wandb_project: str,
        wandb_group: str | None,
        config: dict[str, Any],
        resume_iteration: int | None = None,
    ):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.metrics_path = self.run_dir / METRICS_FILE
        _truncate_metrics(self.metrics_path, resume_iteration)
        self._file: IO[str] | None = self.metrics_path.open("a", encoding="utf-8")
        self._wandb_run: Any = None
        if use_wandb:
            self._wandb_run = self._init_wandb(
                wandb_project, wandb_group, config, resume=resume_iteration is not None
            )

    def _init_wandb(
        self, project: str, group: str | None, config: dict[str, Any], resume: bool
    ) -> Any:
        """A wandb run, or None (with a warning) when wandb is missing or fails to start."""
        id_file = self.run_dir / WANDB_ID_FILE
        run_id = id_file.read_text().strip() if resume and id_file.is_file() else None
        try:
            import wandb

            run = wandb.init(
                project=project,
                group=group,
                config=_jsonable(config),
                dir=str(self.run_dir),
                mode=os.environ.get("WANDB_MODE", "offline"),
                id=run_id,
                resume="allow" if run_id else None,
            )
        # wandb raises many error types (usage, network, service); logging must not stop a run.
        except Exception as err:  # noqa: BLE001
            log.warning(
                "wandb could not start (%s: %s); logging to %s only",
                type(err).__name__,
                err,
                self.metrics_path,
            )
            return None
        if run is not None and getattr(run, "id", None):
            id_file.write_text(str(run.id))
        return run

    @property
    def wandb_active(self) -> bool:
        """Whether records also go to wandb."""
        return self._wandb_run is not None

    def log(self, metrics: Mapping[str, Any], iteration: int) -> None:
        """Append one record ``{"iteration": iteration, **metrics}`` and flush it."""
        if self._file is None:
            raise RuntimeError("Recorder.log called after finish()")
        record = {ITERATION: int(iteration), **_jsonable(dict(metrics))}
        self._file.write(json.dumps(record) + "\n")
        self._file.flush()
        if self._wandb_run is not None:
            self._wandb_log(record, iteration)

    def _wandb_log(self, record: dict[str, Any], iteration: int) -> None:
        numbers = {k: v for k, v in record.items() if isinstance(v, int | float)}
        try:
            self._wandb_run.log(numbers, step=int(iteration))
        except Exception as err:  # noqa: BLE001 - see _init_wandb
            log.warning("wandb.log failed (%s); wandb logging is off for this run", err)
            self._wandb_run = None

    def log_video(self, key: str, path: str | Path, iteration: int) -> None:
        """Log the video file `path` (e.g. MP4) to wandb as ``wandb.Video`` under `key`.

        A no-op without wandb; a wandb failure only warns (the file stays in the run dir).
        """
        if self._wandb_run is None:
            return
        try:
            import wandb

            video = wandb.Video(str(path), caption=Path(path).name, format="mp4")
            self._wandb_run.log({key: video}, step=int(iteration))
        except Exception as err:  # noqa: BLE001 - see _init_wandb
            log.warning("wandb could not log the video %s (%s)", path, err)

    def write_summary(self, summary: Mapping[str, Any]) -> Path:
        """Write ``run_dir/summary.json`` atomically (and the wandb run summary)."""
        path = self.run_dir / SUMMARY_FILE
        text = json.dumps(_jsonable(dict(summary)), indent=2, sort_keys=True) + "\n"
        atomic_write(path, lambda f: f.write(text.encode("utf-8")), keep_prev=False)
        if self._wandb_run is not None:
            try:
                self._wandb_run.summary.update(_jsonable(dict(summary)))
            except Exception as err:  # noqa: BLE001 - see _init_wandb
                log.warning("wandb summary update failed (%s)", err)
        return path

    def finish(self) -> None:
        """Close the metrics file and the wandb run. Safe to call twice."""
        if self._file is not None:
            self._file.close()
            self._file = None
        if self._wandb_run is not None:
            try:
                self._wandb_run.finish()
            except Exception as err:  # noqa: BLE001 - see _init_wandb
                log.warning("wandb finish failed (%s)", err)
            self._wandb_run = None

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()
