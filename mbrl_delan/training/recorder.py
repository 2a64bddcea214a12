"""Metric logging of a run: ``metrics.jsonl`` in the run dir, and one logger beside it
(`LOGGERS`): wandb in offline mode, or TorchRL's CSV or TensorBoard logger.

Every record carries the loop ``iteration`` it belongs to; the loggers plot each record
against its `step_key` field (the train loop's ``env_steps``, the fit's ``epoch``). On resume
from a checkpoint taken at iteration ``k``, records with ``iteration > k`` are dropped from
``metrics.jsonl`` (they will be logged again), so the file never holds the same step twice.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mbrl_delan.training.checkpoint import atomic_write, write_failure

log = logging.getLogger(__name__)

RUN_CONFIG = "config.yaml"  # the run's resolved config, written by the entry point
METRICS_FILE = "metrics.jsonl"
SUMMARY_FILE = "summary.json"
WEIGHTS_FILE = "world_model.pt"  # a train run's final world model (state dict), kept to re-score
WANDB_ID_FILE = "wandb_id.txt"
ITERATION = "iteration"  # step key of every metrics record
LOGGERS = ("none", "wandb", "csv", "tensorboard")  # `logger.backend`


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


def read_metrics(path: str | Path, warn: bool = True) -> list[dict[str, Any]]:
    """Records of a ``metrics.jsonl`` file; damaged lines (e.g. cut by a crash) are skipped,
    with one warning naming them (`warn`; a caller that reads a file again passes False)."""
    path = Path(path)
    if not path.is_file():
        return []
    records, damaged = [], []
    with path.open(encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                damaged.append(lineno)
                continue
            if isinstance(record, dict):
                records.append(record)
    if damaged and warn:
        which = "lines" if len(damaged) > 1 else "line"
        log.warning("skipping unreadable %s %s of %s", which, ", ".join(map(str, damaged)), path)
    return records


def resume_metrics(
    path: Path, resume_iteration: int | None, last_record: Mapping[str, Any] | None = None
) -> None:
    """Make ``metrics.jsonl`` hold the records up to the checkpoint's iteration: later ones
    (rounds the resumed run does again) are removed, and the checkpoint's own copy of its
    round's record (`last_record`) replaces that record when it is missing or torn (the file
    is appended without fsync, the checkpoint is fsynced). ``resume_iteration=None``: a fresh
    file. The file is rewritten only when that changes it."""
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
        if last_record is not None and all(r[ITERATION] != resume_iteration for r in kept):
            log.warning(
                "%s: the record of iteration %d is missing or torn; restored from the checkpoint",
                path,
                resume_iteration,
            )
            kept.append({ITERATION: resume_iteration, **_jsonable(dict(last_record))})
    lines = "".join(json.dumps(r) + "\n" for r in kept)
    if path.read_text(encoding="utf-8", errors="replace") != lines:
        atomic_write(path, lambda f: f.write(lines.encode("utf-8")), keep_prev=False)


WANDB_MODES = ("offline", "online", "disabled")  # `logger.mode`


@dataclass(frozen=True)
class WandbOptions:
    """A wandb run's identity beyond its project and group: `name` (None: wandb's own),
    `tags`, `entity` (None: the user's default) and `mode` (one of `WANDB_MODES`; None: the
    ``WANDB_MODE`` variable, else offline)."""

    name: str | None = None
    tags: tuple[str, ...] = ()
    entity: str | None = None
    mode: str | None = None

    @classmethod
    def of(cls, logger: Mapping[str, Any]) -> WandbOptions:
        """From a ``logger`` config (its keys ``name``, ``tags``, ``entity``, ``mode``)."""
        return cls(
            logger.get("name"), tuple(logger.get("tags") or ()), logger.get("entity"),
            logger.get("mode"),
        )  # fmt: skip


class Recorder:
    """Writes metric records to ``run_dir/metrics.jsonl`` and to one logger of `LOGGERS`.

    Args:
        run_dir: the run's folder (created if missing).
        backend: ``none``; ``wandb`` (offline unless ``WANDB_MODE`` is set, the run inside
            ``run_dir/wandb``); ``csv`` or ``tensorboard`` (TorchRL's ``CSVLogger`` and
            ``TensorboardLogger``, under ``run_dir/csv`` and ``run_dir/tensorboard``).
        project: wandb project name.
        group: wandb group (e.g. a sweep name), or None.
        config: the run's resolved configuration, stored with the logger's run.
        resume_iteration: the iteration of the checkpoint a resumed run starts from; records
            after it are removed. ``None`` starts a fresh ``metrics.jsonl``.
        last_record: the checkpoint's copy of that iteration's record (`resume_metrics`).
        step_key: the record field the loggers plot against (the iteration when absent).
        wandb_options: the wandb run's name, tags, entity and mode (`WandbOptions`).
    """

    def __init__(
        self,
        run_dir: Path,
        backend: str,
        project: str,
        group: str | None,
        config: dict[str, Any],
        resume_iteration: int | None = None,
        step_key: str = ITERATION,
        last_record: Mapping[str, Any] | None = None,
        wandb_options: WandbOptions = WandbOptions(),
    ):
        if backend not in LOGGERS:
            raise ValueError(f"logger {backend!r} is not one of {', '.join(LOGGERS)}")
        self.run_dir, self.step_key = Path(run_dir), step_key
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.metrics_path = self.run_dir / METRICS_FILE
        resume_metrics(self.metrics_path, resume_iteration, last_record)
        self._file: IO[str] | None = self.metrics_path.open("a", encoding="utf-8")
        self._wandb_run: Any = None
        self._scalars: Any = None  # a TorchRL logger (csv, tensorboard)
        self._hparams = flat_config(config)  # TensorBoard's hparams, with the summary's numbers
        self._last_step = 0  # of the last record, where the CSV logger puts the summary
        if backend == "wandb":
            self._wandb_run = self._init_wandb(
                project, group, config, wandb_options, resume=resume_iteration is not None
            )
        elif backend != "none":
            self._scalars = _torchrl_logger(backend, self.run_dir, config)

    def _init_wandb(
        self,
        project: str,
        group: str | None,
        config: dict[str, Any],
        options: WandbOptions,
        resume: bool,
    ) -> Any:
        """A wandb run, or None (with a warning) when wandb is missing or fails to start."""
        id_file = self.run_dir / WANDB_ID_FILE
        run_id = id_file.read_text().strip() if resume and id_file.is_file() else None
        try:
            import wandb

            run = wandb.init(
                project=project,
                group=group,
                name=options.name,
                tags=list(options.tags) or None,
                entity=options.entity,
                config=_jsonable(config),
                dir=str(self.run_dir),
                mode=options.mode or os.environ.get("WANDB_MODE", "offline"),
                id=run_id,
                resume="allow" if run_id else None,
                # wandb's own lines (its run history and summary) only at DEBUG
                settings={"silent": not log.isEnabledFor(logging.DEBUG)},
            )
            run.define_metric(self.step_key)
            run.define_metric("*", step_metric=self.step_key)
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
        """Append one record ``{"iteration": iteration, **metrics}`` and flush it; its numbers
        go to the logger against the record's `step_key`."""
        if self._file is None:
            raise RuntimeError("Recorder.log called after finish()")
        record = {ITERATION: int(iteration), **_jsonable(dict(metrics))}
        try:
            self._file.write(json.dumps(record) + "\n")
            self._file.flush()
        except OSError as err:  # a full disk: name the file, keep the records before it
            raise write_failure(self.metrics_path, err) from err
        numbers = {k: v for k, v in record.items() if isinstance(v, int | float)}
        step = self._last_step = int(numbers.get(self.step_key, iteration))
        if self._wandb_run is not None:
            self._wandb_call("log", lambda: numbers)
        if self._scalars is not None:
            for name, value in numbers.items():
                self._scalars.log_scalar(name, float(value), step=step)

    def _wandb_call(self, what: str, data: Callable[[], dict[str, Any]]) -> None:
        """``run.log(data())``; a failure warns and turns wandb off (see `_init_wandb`)."""
        try:
            self._wandb_run.log(data())
        except Exception as err:  # noqa: BLE001 - see _init_wandb
            log.warning("wandb could not %s (%s); wandb logging is off for this run", what, err)
            self._wandb_run = None

    def log_video(self, key: str, path: str | Path, step: int) -> None:
        """Log the video file `path` (e.g. MP4) to wandb as ``wandb.Video`` under `key`, at
        `step` of `step_key`. Without wandb a no-op (the file stays in the run dir, which
        TorchRL's CSV and TensorBoard loggers would otherwise copy as raw frames)."""
        if self._wandb_run is not None:
            self._wandb_call(
                f"log the video {path}",
                lambda: {key: _wandb_media("Video", path), self.step_key: int(step)},
            )

    def log_image(self, key: str, path: str | Path) -> None:
        """Log the figure `path` (PNG) under `key`: to wandb as ``wandb.Image``, to
        TensorBoard as an image; the CSV logger keeps only scalars (the file is in the run dir)."""
        if self._wandb_run is not None:
            self._wandb_call(f"log the figure {path}", lambda: {key: _wandb_media("Image", path)})
        if self._scalars is not None and hasattr(self._scalars.experiment, "add_image"):
            import matplotlib.image

            pixels = matplotlib.image.imread(str(path))[..., :3]  # (H, W, 3) in [0, 1]
            self._scalars.experiment.add_image(key, pixels, dataformats="HWC")

    def write_summary(self, summary: Mapping[str, Any]) -> Path:
        """Write ``run_dir/summary.json`` atomically and give its numbers to the logger: the
        wandb run's summary; TensorBoard's hparams (the config with these as its metrics,
        ``summary/<key>``); the CSV logger's ``summary/<key>`` at the last record's step."""
        path = self.run_dir / SUMMARY_FILE
        values = _jsonable(dict(summary))
        text = json.dumps(values, indent=2, sort_keys=True) + "\n"
        atomic_write(path, lambda f: f.write(text.encode("utf-8")), keep_prev=False)
        if self._wandb_run is not None:
            try:
                self._wandb_run.summary.update(values)
            except Exception as err:  # noqa: BLE001 - see _init_wandb
                log.warning("wandb summary update failed (%s)", err)
        if self._scalars is not None:
            self._scalar_summary(values)
        return path

    def _scalar_summary(self, values: Mapping[str, Any]) -> None:
        """The summary's numbers as ``summary/<key>``: TensorBoard's hparams metrics (one
        row for the run), the CSV logger's scalars at the last record's step."""
        numbers = {
            f"summary/{k}": float(v)
            for k, v in values.items()
            if isinstance(v, int | float) and not isinstance(v, bool)
        }
        writer = self._scalars.experiment
        if hasattr(writer, "add_hparams"):
            writer.add_hparams(self._hparams, numbers, run_name=".")
            return
        for name, value in numbers.items():
            self._scalars.log_scalar(name, value, step=self._last_step)

    def log_artifact(self, path: str | Path, kind: str = "model") -> None:
        """The file `path` (a train run's final checkpoint, a fit's model) as a wandb artifact
        of type `kind`, named ``<run id>-<file stem>``; without wandb a no-op (the file stays
        in the run dir)."""
        if self._wandb_run is None:
            return
        try:
            import wandb

            artifact = wandb.Artifact(f"{self._wandb_run.id}-{Path(path).stem}", type=kind)
            artifact.add_file(str(path))
            self._wandb_run.log_artifact(artifact)
        except Exception as err:  # noqa: BLE001 - see _init_wandb
            log.warning("wandb could not store %s as an artifact (%s)", path, err)

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
        if self._scalars is not None:
            writer = self._scalars.experiment
            if hasattr(writer, "close"):  # TensorBoard's SummaryWriter: flush the events
                writer.close()
            self._scalars = None

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()


def _wandb_media(kind: str, path: str | Path) -> Any:
    """``wandb.Video`` (MP4) or ``wandb.Image`` of the file `path`."""
    import wandb

    if kind == "Video":
        return wandb.Video(str(path), caption=Path(path).name, format="mp4")
    return wandb.Image(str(path), caption=Path(path).name)


def _torchrl_logger(backend: str, run_dir: Path, config: dict[str, Any]) -> Any:
    """TorchRL's ``CSVLogger`` (the run's config as its hyperparameters) or
    ``TensorboardLogger``, writing under ``run_dir/<backend>``."""
    from torchrl.record.loggers import CSVLogger, TensorboardLogger

    if backend == "tensorboard":
        try:
            import tensorboard  # noqa: F401 - TorchRL's logger needs it, and says so late
        except ImportError as err:
            raise ImportError(
                "logger=tensorboard needs the tensorboard package: pip install tensorboard"
            ) from err
        # its hparams are written with the summary's numbers as their metrics (write_summary)
        return TensorboardLogger(exp_name=backend, log_dir=str(run_dir))
    logger = CSVLogger(exp_name=backend, log_dir=str(run_dir))
    logger.log_hparams(flat_config(config))
    return logger


def flat_config(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested config as one level of ``a.b`` keys with plain values (numbers, strings,
    booleans; anything else, None and lists included, as its ``str``)."""
    flat: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flat_config(value, f"{name}."))
        elif isinstance(value, int | float | str | bool):
            flat[name] = value
        else:
            flat[name] = str(value)
    return flat
