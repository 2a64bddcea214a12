"""Suite `mocap`: how fast the mocap pipeline and the inverse-dynamics fits run (issue 5).

Three kinds of figure, on the settings of ``python -m mbrl_delan.fit``: the config Hydra
composes from the fit's config dir (`mocap_config`), its dataset and models built by the fit's
own builders:

- `retarget_frames_per_s`: AMC frames retargeted onto humanoid_CMU per second: for every clip
  of the dataset, `read_asf`, `read_amc` and `retarget` (filter, spline resampling to the
  model timestep, qd and qdd), the MjModel loaded once beforehand. Work per call: the clips'
  AMC frames together.
- `dataset_build_s`: seconds of one `build_dataset` call with the config's clips and settings
  (finding the files, reading, retargeting, glitch detection, `mj_inverse`, splitting and
  subsampling), clips from local folders only (no download).
- `fit_samples_per_s` (one record per model: delan, mlp, ensemble): training samples per
  second of one epoch of `train_epoch` (what `fit_inverse_model` runs each epoch: shuffled
  minibatches of the config's batch size, loss, backward, gradient clipping, Adam step) on
  the training split of the dataset just built, after `fit_normalization`; samples per epoch
  / seconds per epoch;
- `fit_epoch_s` (one record per model): the seconds of that epoch (the same timing).

`quick=true`: the one small clip of tests/data (09_06) and tiny sizes
(`QUICK_OVERRIDES`). Clips that are not found give `value: null` records with a note.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import mujoco
import torch
from omegaconf import DictConfig
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.accelerate.compile import compile_fit
from mbrl_delan.benchmarks import (
    BenchSettings,
    Timing,
    TimingConfig,
    host_fields,
    synchronizer,
    time_call,
)
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import OverridesSuiteConfig
from mbrl_delan.conf.checks import DTYPES, compose_config
from mbrl_delan.conf.fitting import FIT_CONFIG_DIR, validate_fit_config
from mbrl_delan.conf.inverse import InverseContext, build_inverse_model
from mbrl_delan.data.fit_kinds import make_dataset
from mbrl_delan.data.mocap import (
    ClipFiles,
    ClipNotFoundError,
    FilterSettings,
    MocapDataset,
    find_clip,
    humanoid_cmu_xml,
    read_amc,
    read_asf,
    retarget,
    split_dataset,
)
from mbrl_delan.data.mocap.retarget import joint_layout
from mbrl_delan.models.inverse import MODEL_NAMES, InverseDynamicsModel
from mbrl_delan.systems.system import JointLayout
from mbrl_delan.training.inverse_fit import InverseFitSettings, train_epoch

log = logging.getLogger(__name__)

SUITE = "mocap"
METRICS = ("retarget_frames_per_s", "dataset_build_s", "fit_samples_per_s", "fit_epoch_s")
REPO_ROOT = Path(__file__).resolve().parents[2]
TEST_DATA = REPO_ROOT / "tests" / "data"
QUICK_CLIP = "09_06"
# mbrl_delan/configs/fit/data/cmu_mocap.yaml's clips (not data.mocap.DEFAULT_CLIPS, an older list)
QUICK_OVERRIDES = (  # the small clip of tests/data and tiny networks (seconds in all)
    f"data.clips=['{QUICK_CLIP}']",
    "data.val_clips=[]",
    f"data.folders=['{TEST_DATA}']",
    "data.samples_per_clip=64",
    "data.split.gap_s=0.1",
    "batch_size=16",
    "model.hidden=16",
    "model.ensemble_size=2",
)

BUILD_MAX_REPEATS = 3  # one build takes seconds: at most this many timed builds
BUILD_MAX_WARMUP = 1


@dataclass(frozen=True)
class MocapBenchConfig:
    """The settings of ``python -m mbrl_delan.fit`` the suite runs with: the fit config Hydra
    composes from ``mbrl_delan/configs/fit`` (its data and training keys) and each model's own (its
    ``model`` group), with the same overrides (`mocap_config`)."""

    fit: DictConfig  # data, training (batch_size, lr, ...), loss, dtype, seed
    models: dict[str, DictConfig]  # name -> that model's group

    @property
    def data(self) -> DictConfig:
        return self.fit.data

    @property
    def clips(self) -> list[str]:
        return list(self.data.clips)

    @property
    def dtype(self) -> torch.dtype:
        return DTYPES[self.fit.dtype]

    @property
    def filter(self) -> FilterSettings:
        f = self.data.filter
        return FilterSettings(cutoff_hz=f.cutoff_hz, order=f.order, edge_trim_s=f.edge_trim_s)

    def resolved_folders(self) -> list[Path]:
        """The clip folders, relative ones against the repository root."""
        paths = map(Path, self.data.folders)
        return [(p if p.is_absolute() else REPO_ROOT / p).resolve() for p in paths]


def mocap_config(
    overrides: Sequence[str] = (), models: Sequence[str] = MODEL_NAMES
) -> MocapBenchConfig:
    """The fit config of ``python -m mbrl_delan.fit <overrides>`` and of each model's
    ``model=<name> <overrides>`` (an override of a key that model lacks is left out)."""
    shared = [o for o in overrides if not o.startswith("model.")]
    groups = {}
    for name in models:
        plain = compose_config(FIT_CONFIG_DIR, [f"model={name}"]).model
        own = [o for o in overrides if o.startswith("model.") and _key(o) in plain]
        full = compose_config(FIT_CONFIG_DIR, [*shared, f"model={name}", *own])
        validate_fit_config(full)
        groups[name] = full.model
    return MocapBenchConfig(compose_config(FIT_CONFIG_DIR, shared), groups)


def _key(override: str) -> str:
    """`model.hidden=16` -> `hidden`."""
    return override.split("=", 1)[0].removeprefix("model.")


# ----------------------------------------------------------------------------- data


def find_clips(cfg: MocapBenchConfig) -> list[ClipFiles]:
    """Every clip's files from the local folders or the cache (no download)."""
    folders = cfg.resolved_folders()
    return [find_clip(name, folders=folders, download=False) for name in cfg.clips]


def count_frames(files: list[ClipFiles]) -> int:
    """AMC frames of all clips together."""
    return sum(read_amc(f.amc, read_asf(f.asf)).n_frames for f in files)


def retarget_call(
    files: list[ClipFiles], model: mujoco.MjModel, settings: FilterSettings
) -> Callable[[], int]:
    """A call that reads and retargets every clip; returns the samples produced."""

    def call() -> int:
        samples = 0
        for f in files:
            skeleton = read_asf(f.asf)
            clip = retarget(read_amc(f.amc, skeleton), skeleton, model, settings, name=f.name)
            samples += len(clip)
        return samples

    return call


class DatasetBuilder:
    """A call that builds the dataset as ``fit`` does; keeps the last one built."""

    def __init__(self, cfg: MocapBenchConfig) -> None:
        self.cfg = cfg
        self.last: MocapDataset | None = None

    def __call__(self) -> MocapDataset:
        data = self.cfg.data.copy()
        data.folders = [str(p) for p in self.cfg.resolved_folders()]
        data.download = False
        self.last = make_dataset(data)
        return self.last


def training_split(dataset: MocapDataset, device: torch.device, dtype: torch.dtype) -> TensorDict:
    """The training part: q, qd, qdd, tau on the device in the training dtype. (N,)"""
    train = split_dataset(dataset).train
    return train.select(keys.Q, keys.QD, keys.QDD, keys.TAU).to(device=device, dtype=dtype)


# ----------------------------------------------------------------------------- fitting


def make_inverse_model(
    name: str,
    layout: JointLayout,
    cfg: MocapBenchConfig,
    dof_parents: list[int] | None = None,
    armature: list[float] | None = None,
) -> InverseDynamicsModel:
    """The inverse-dynamics model ``name`` as ``fit`` builds it (`fit.build_inverse_model`)
    (``dof_parents``, ``armature``: the MuJoCo model's ``dof_parentid`` and ``dof_armature``,
    for DeLaN's tree sparsity and known armature)."""
    fit = cfg.fit
    context = InverseContext(
        layout, fit.loss.std_floor, fit.translation_invariant, dof_parents, armature
    )
    return build_inverse_model(cfg.models[name], context)


def epoch_call(
    model: InverseDynamicsModel, train: TensorDict, cfg: MocapBenchConfig
) -> Callable[[], float]:
    """A call that trains ``model`` for one epoch on ``train`` (N,); returns its mean loss."""
    fit = cfg.fit
    optimizer = torch.optim.Adam(model.parameters(), lr=fit.lr)
    settings = InverseFitSettings(
        epochs=1, batch_size=fit.batch_size, max_grad_norm=fit.max_grad_norm
    )
    generator = torch.Generator(device=train.device).manual_seed(fit.seed)
    return lambda: train_epoch(model, optimizer, train, settings, generator)


# ----------------------------------------------------------------------------- records


def _record(
    case: str,
    metric: str,
    unit: str,
    device: str,
    fields: dict[str, Any],
    timing: Timing | None,
    value: float | None,
    note: str | None = None,
) -> BenchRecord:
    extra = dict(fields)
    if timing is not None:
        extra.update(timing.fields())
    if note is not None:
        extra["note"] = note
    return BenchRecord(SUITE, case, metric, value, unit, device, extra)


def _build_timing(timing: TimingConfig) -> TimingConfig:
    """At most `BUILD_MAX_WARMUP` untimed and `BUILD_MAX_REPEATS` timed builds."""
    return replace(
        timing,
        repeats=min(timing.repeats, BUILD_MAX_REPEATS),
        warmup=min(timing.warmup, BUILD_MAX_WARMUP),
    )


def _data_fields(cfg: MocapBenchConfig, host: dict[str, Any]) -> dict[str, Any]:
    return {
        "clips": cfg.clips,
        "n_clips": len(cfg.clips),
        "folders": [str(p) for p in cfg.resolved_folders()],
        "samples_per_clip": cfg.data.samples_per_clip,
        "cutoff_hz": cfg.filter.cutoff_hz,
        **host,
    }


def _missing_records(
    case: str, fields: dict[str, Any], cfg: MocapBenchConfig, device: str, note: str
) -> Iterator[BenchRecord]:
    """Null records for every figure when the clips (or humanoid_CMU.xml) are not there."""
    yield _record(case, "retarget_frames_per_s", "frames/s", "cpu", fields, None, None, note)
    yield _record(case, "dataset_build_s", "s", "cpu", fields, None, None, note)
    for name in cfg.models:
        fit_case = f"{name}-b{cfg.fit.batch_size}"
        for metric, unit in (("fit_samples_per_s", "samples/s"), ("fit_epoch_s", "s")):
            yield _record(fit_case, metric, unit, device, fields, None, None, note)


def _fit_records(
    name: str,
    mj_model: mujoco.MjModel,
    train: TensorDict,
    cfg: MocapBenchConfig,
    bench: BenchSettings,
    host: dict[str, Any],
) -> Iterator[BenchRecord]:
    torch.manual_seed(cfg.fit.seed)
    layout, parents = joint_layout(mj_model), mj_model.dof_parentid.tolist()
    armature = mj_model.dof_armature.tolist()
    model = make_inverse_model(name, layout, cfg, parents, armature)
    model = model.to(device=bench.device, dtype=cfg.dtype)
    if cfg.models[name].get("compile_fit", False):
        compile_fit(model)
    model.fit_normalization(train)
    n = int(train.shape[0])
    fields = {
        "model": name,
        "batch_size": cfg.fit.batch_size,
        "train_samples": n,
        "steps_per_epoch": math.ceil(n / cfg.fit.batch_size),
        "n_parameters": sum(p.numel() for p in model.parameters()),
        "dtype": str(cfg.dtype).removeprefix("torch."),
        "lr": cfg.fit.lr,
        "compile_fit": bool(cfg.models[name].get("compile_fit", False)),
        **host,
    }
    timing = time_call(epoch_call(model, train, cfg), bench.timing, synchronizer(bench.device))
    seconds, case, device = (
        timing.seconds_per_call,
        f"{name}-b{cfg.fit.batch_size}",
        str(bench.device),
    )
    yield _record(case, "fit_samples_per_s", "samples/s", device, fields, timing, n / seconds)
    yield _record(case, "fit_epoch_s", "s", device, fields, timing, seconds)


def run_mocap(cfg: MocapBenchConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    """Every figure of the suite for ``cfg``, one record at a time."""
    host = host_fields(bench.device)
    case = f"cmu_mocap-{len(cfg.clips)}clips"
    fields = _data_fields(cfg, host)
    try:
        files = find_clips(cfg)
        mj_model = mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml()))
    except (ClipNotFoundError, FileNotFoundError, ModuleNotFoundError) as err:
        log.warning("mocap suite: %s", err)
        note = f"skipped: {type(err).__name__}: {err}"
        yield from _missing_records(case, fields, cfg, str(bench.device), note)
        return
    frames = count_frames(files)
    log.info("mocap suite: retargeting %d clips (%d frames)", len(files), frames)
    timing = time_call(retarget_call(files, mj_model, cfg.filter), bench.timing)
    value = frames / timing.seconds_per_call
    retarget_fields = {**fields, "frames": frames}
    yield _record(case, "retarget_frames_per_s", "frames/s", "cpu", retarget_fields, timing, value)
    log.info("mocap suite: building the dataset")
    builder = DatasetBuilder(cfg)
    timing = time_call(builder, _build_timing(bench.timing))
    dataset = builder.last if builder.last is not None else builder()  # time_call built it
    build_fields = {**fields, "samples": len(dataset)}
    seconds = timing.seconds_per_call
    yield _record(case, "dataset_build_s", "s", "cpu", build_fields, timing, seconds)
    train = training_split(dataset, bench.device, cfg.dtype)
    for name in cfg.models:
        log.info("mocap suite: one epoch of %s on %d samples", name, train.shape[0])
        yield from _fit_records(name, mj_model, train, cfg, bench, host)


def suite_config(options: OverridesSuiteConfig, quick: bool = False) -> MocapBenchConfig:
    """The suite's settings: the fit's defaults, or `QUICK_OVERRIDES` under `quick`; then the
    options' fit-config `overrides`."""
    return mocap_config([*(QUICK_OVERRIDES if quick else ()), *options.overrides])


def run_mocap_suite(options: OverridesSuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    """The registered suite: `run_mocap` with `suite_config`."""
    yield from run_mocap(suite_config(options, bench.quick), bench)
