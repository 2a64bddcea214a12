"""The mocap inverse-dynamics dataset: CMU clips -> (q, qd, qdd, tau) samples with provenance.

Per clip: find (or download) it, retarget it (`retarget`), label every sample with a split,
drop samples near glitches and at the borders of the held-out segment, keep about
``samples_per_clip`` evenly spaced samples, and compute their forces (`inverse_dynamics`).

The result is a float64 TensorDict of batch size (N,) with the keys (`mbrl_delan.keys`)

- ``q`` (N, 63), ``qd`` (N, 62), ``qdd`` (N, 62), ``tau`` (N, 62): ``qfrc_inverse``, the
  56 joint torques and the 6 root-residual forces in their dof slots (``torques="inverse"``,
  default); with ``torques="pd"`` the clip is tracked in simulation by PD control
  (`mbrl_delan.data.mocap.tracking`) and q, qd, qdd, tau are the achieved motion and the
  applied generalized forces (still ``mj_inverse(q, qd, qdd) = tau``);
- ``root_residual`` (N, 6): the root's part of tau, kept separately (it is the force the
  ground provides; nothing inside the body can produce it);
- ``("next", "q")`` (N, 63), ``("next", "qd")`` (N, 62): the state dt later, for next-state
  losses (semi-implicit Euler with qdd maps each sample onto it exactly);
- ``clip`` (N, 1) int64 index into ``provenance["clips"]``, ``frame`` (N, 1) the fractional
  AMC frame, ``time`` (N, 1) seconds into the clip, ``split`` (N, 1) int64:
  `TRAIN`, `VAL_TIME` (a held-out time segment of a training clip), `VAL_CLIP` (a held-out
  clip).

`save_dataset` writes the TensorDict as a memory-mapped TensorDict (``data/``) next to
``provenance.json`` (clips, their files, sources and SHA-256, filter settings, timestep,
model, inverse-dynamics options, split and glitch settings, per-clip counts);
`load_dataset` reads both back.
"""

from __future__ import annotations

import json
import logging
import shutil
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from hashlib import sha256
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import torch
from tensordict import TensorDict
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.data.buffer import check_finite
from mbrl_delan.data.mocap.amc import read_amc, read_asf
from mbrl_delan.data.mocap.clips import CMU_URL_TEMPLATE, ClipFiles, find_clip
from mbrl_delan.data.mocap.inverse import inverse_dynamics, root_dofs
from mbrl_delan.data.mocap.retarget import (
    FilterSettings,
    RetargetedClip,
    humanoid_cmu_xml,
    retarget,
)
from mbrl_delan.data.mocap.tracking import TrackingSettings, track_clip

log = logging.getLogger(__name__)

FORMAT = "mbrl_delan.mocap/1"
TRAIN, VAL_TIME, VAL_CLIP = 0, 1, 2
SPLIT_NAMES = {TRAIN: "train", VAL_TIME: "val_time", VAL_CLIP: "val_clip"}
_DROP = -1

# Real CMU subject_trial names (downloadable from the CMU site): walks, a run, a walk
# forward/backward/sideways, modern dance, Michael-Jackson-style hops and jumps.
DEFAULT_CLIPS = (
    "02_01", "02_02", "05_01", "05_02", "05_03", "05_04", "05_05", "05_07",
    "07_03", "07_05", "09_06", "09_12", "131_03", "131_07", "131_12",
)  # fmt: skip
DEFAULT_VAL_CLIPS = ("02_02", "05_07", "131_07")  # a walk, a dance, a jump
TORQUE_SOURCES = ("inverse", "pd")  # mj_inverse of the reference, or PD tracking in simulation


@dataclass
class MocapDataset:
    """Samples (TensorDict, batch (N,)) and their provenance (JSON-serialisable dict)."""

    data: TensorDict
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def clips(self) -> tuple[str, ...]:
        return tuple(self.provenance["clips"])

    def __len__(self) -> int:
        return int(self.data.batch_size[0])


@dataclass
class DatasetSplits:
    """The three parts of a dataset, each a TensorDict of batch (N_part,)."""

    train: TensorDict
    val_time: TensorDict  # held-out time segments of the training clips
    val_clip: TensorDict  # held-out whole clips


def _clip_rng(seed: int, name: str) -> np.random.Generator:
    """One generator per (seed, clip name): the split of a clip does not depend on the others."""
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def split_labels(
    time: np.ndarray,
    held_out_clip: bool,
    val_time_fraction: float,
    gap_s: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, tuple[float, float] | None]:
    """Split label per sample time (T,) -> (T,) int64 (`_DROP` in the guard gaps).

    A training clip holds out one contiguous segment of ``val_time_fraction`` of its length,
    at a random place; samples within ``gap_s`` of the segment are dropped, so that no
    training sample is a filter width away from a validation one.
    Returns the labels and the segment (start, stop) in seconds, or None.
    """
    labels = np.full(time.shape, VAL_CLIP if held_out_clip else TRAIN, dtype=np.int64)
    if held_out_clip or val_time_fraction <= 0:
        return labels, None
    if not val_time_fraction < 1:
        raise ValueError(f"val_time_fraction must be in [0, 1), got {val_time_fraction}")
    t0, t1 = float(time[0]), float(time[-1])
    length = val_time_fraction * (t1 - t0)
    start = t0 + rng.uniform(0.0, (t1 - t0) - length)
    stop = start + length
    labels[(time > start - gap_s) & (time < stop + gap_s)] = _DROP
    labels[(time >= start) & (time <= stop)] = VAL_TIME
    return labels, (start, stop)


def _evenly(index: np.ndarray, n: int | None) -> np.ndarray:
    """At most n entries of a sorted index array, evenly spread over it."""
    if n is None or index.size <= n:
        return index
    return index[np.unique(np.round(np.linspace(0, index.size - 1, n)).astype(np.int64))]


def _clip_samples(
    clip: RetargetedClip,
    model: mujoco.MjModel,
    labels: np.ndarray,
    clip_index: int,
    samples_per_clip: int | None,
    passive: bool,
    applied: Tensor | None = None,
) -> TensorDict:
    """The chosen samples of one clip with their forces, TensorDict (n,).

    ``applied`` (T, nv): the generalized forces of every clip sample when they are known
    (PD tracking); otherwise they are computed by `inverse_dynamics`.
    """
    chosen = torch.from_numpy(_evenly(np.flatnonzero(labels != _DROP), samples_per_clip))
    q, qd, qdd = clip.q[chosen], clip.qd[chosen], clip.qdd[chosen]
    if applied is None:
        tau = inverse_dynamics(model, q, qd, qdd, passive=passive).tau  # (n, nv)
    else:
        tau = applied[chosen].clone()  # (n, nv)
    n = int(chosen.numel())
    td = TensorDict(
        {
            keys.Q: q,
            keys.QD: qd,
            keys.QDD: qdd,
            keys.TAU: tau,
            keys.ROOT_RESIDUAL: tau[:, list(root_dofs(model))].clone(),
            keys.NEXT_Q: clip.next_q[chosen],
            keys.NEXT_QD: clip.next_qd[chosen],
            keys.CLIP: torch.full((n, 1), clip_index, dtype=torch.int64),
            keys.FRAME: clip.frame[chosen].unsqueeze(-1),
            keys.TIME: clip.time[chosen].unsqueeze(-1),
            keys.SPLIT: torch.from_numpy(labels)[chosen].unsqueeze(-1),
        },
        batch_size=[n],
    )
    check_finite(td, f"mocap clip {clip.name}")
    return td


def _file_sha(path: Path) -> str:
    return sha256(path.read_bytes()).hexdigest()


def build_dataset(
    clips: Sequence[str] = DEFAULT_CLIPS,
    val_clips: Sequence[str] = DEFAULT_VAL_CLIPS,
    folders: Sequence[str | Path] = (),
    cache_dir: str | Path | None = None,
    download: bool = True,
    url_template: str = CMU_URL_TEMPLATE,
    xml_path: str | Path | None = None,
    settings: FilterSettings | None = None,
    timestep: float | None = None,
    samples_per_clip: int | None = 1000,
    val_time_fraction: float = 0.2,
    gap_s: float = 0.25,
    glitch_deg: float = 60.0,
    glitch_pad_s: float = 0.25,
    passive: bool = True,
    seed: int = 0,
    torques: str = "inverse",
    tracking: TrackingSettings | None = None,
    skip_bad_clips: bool = False,
) -> MocapDataset:
    """Build the mocap dataset from CMU clips.

    Args:
        clips: clip names (subject_trial), in dataset order.
        val_clips: clips held out whole (`VAL_CLIP`); each must be in ``clips``.
        folders: local folders looked in first (`find_clip`).
        cache_dir: the download cache (`find_clip`).
        download: fetch clips missing locally into the cache (`find_clip`).
        url_template: where clips are downloaded from (`find_clip`).
        xml_path: the model; dm_control's humanoid_CMU.xml if None.
        settings: filtering and resampling (`FilterSettings()` if None).
        timestep: sample spacing (s); the model's timestep if None.
        samples_per_clip: evenly spaced samples kept per clip (None: all, ~4 per mocap frame).
        val_time_fraction: share of each training clip's duration held out as one segment.
        gap_s: samples this close to the held-out segment are dropped.
        glitch_deg: a captured bone turning more than this between two mocap frames marks a
            glitch (marker swap, solver flip; humans do not turn a limb 60 deg in 8 ms).
        glitch_pad_s: samples this close to a glitch are dropped.
        passive: keep the MJCF's joint springs and dampers in the inverse dynamics.
        seed: seeds the placement of the held-out segments.
        torques: "inverse" (``mj_inverse`` of the retargeted motion) or "pd" (track it in
            simulation with `track_clip`; the samples are the achieved motion and the
            applied forces).
        tracking: PD settings for ``torques="pd"`` (`TrackingSettings()` if None; its
            ``passive`` is set to ``passive``).
        skip_bad_clips: a clip that cannot be read or retargeted (a malformed file, too few
            frames) is left out with a warning, and listed in the provenance's
            ``skipped_clips`` with its error, instead of stopping the build. A clip found
            nowhere still stops it.
    """
    settings = settings or FilterSettings()
    clips = tuple(clips)
    unknown = [c for c in val_clips if c not in clips]
    if unknown:
        raise ValueError(f"val_clips {unknown} are not among the clips {list(clips)}")
    if len(set(clips)) != len(clips):
        raise ValueError(f"clips listed twice in {list(clips)}")
    if samples_per_clip is not None and samples_per_clip < 1:
        raise ValueError(f"samples_per_clip must be >= 1 or None, got {samples_per_clip}")
    if torques not in TORQUE_SOURCES:
        raise ValueError(f"torques must be one of {TORQUE_SOURCES}, got {torques!r}")
    tracking = replace(tracking or TrackingSettings(), passive=passive)
    xml = Path(xml_path) if xml_path is not None else humanoid_cmu_xml()
    model = mujoco.MjModel.from_xml_path(str(xml))
    parts, info, skipped = [], {}, {}
    for index, name in enumerate(clips):
        files = find_clip(name, folders, cache_dir, download, url_template)
        try:
            clip = _retarget_files(files, model, settings, timestep)
        except ValueError as err:  # MocapFormatError, a clip too short to filter
            if not skip_bad_clips:
                raise
            skipped[name] = str(err)
            log.warning("clip %s left out (data.skip_bad_clips): %s", name, err)
            continue
        applied, tracking_errors = None, None
        if torques == "pd":
            tracked = track_clip(model, clip, tracking)
            clip, applied = tracked.as_clip(clip), tracked.tau
            tracking_errors = tracked.errors().as_dict()
        time = clip.time.numpy()
        labels, segment = split_labels(
            time, name in val_clips, val_time_fraction, gap_s, _clip_rng(seed, name)
        )
        split_drop = int(np.sum(labels == _DROP))
        glitches = clip.glitch_times(glitch_deg)
        near = np.zeros(time.shape, dtype=bool)
        for g in glitches:
            near |= np.abs(time - g) <= glitch_pad_s
        glitch_drop = int(np.sum(near & (labels != _DROP)))
        labels[near] = _DROP
        td = _clip_samples(clip, model, labels, index, samples_per_clip, passive, applied)
        parts.append(td)
        counts = torch.bincount(td[keys.SPLIT].flatten(), minlength=3).tolist()
        info[name] = {
            "amc": str(files.amc),
            "asf": str(files.asf),
            "source": files.source,
            "sha256": {"amc": _file_sha(files.amc), "asf": _file_sha(files.asf)},
            "amc_frames": int(clip.jump_deg.size + 1),
            "retargeted_samples": len(clip),
            "duration_s": float(time[-1] - time[0]),
            "samples": {SPLIT_NAMES[k]: counts[k] for k in SPLIT_NAMES},
            "val_time_segment_s": list(segment) if segment else None,
            "dropped_near_val_segment": split_drop,
            "dropped_near_glitch": glitch_drop,
            "glitch_times_s": [round(float(g), 4) for g in glitches],
            "max_jump_deg": float(clip.jump_deg.max(initial=0.0)),
            "held_joints": list(clip.held),
            "missing_joints": list(clip.missing),
            "unused_channels": list(clip.unused),
            "out_of_range": clip.out_of_range,
            "tracking_errors": tracking_errors,
        }
        log.info(
            "%s: %d samples (train %d, val_time %d, val_clip %d); %d dropped near glitches",
            name,
            td.batch_size[0],
            *counts,
            glitch_drop,
        )
    if skipped and not parts:
        raise ValueError(f"every clip was left out: {skipped}")
    data = torch.cat(parts, dim=0) if parts else TensorDict({}, batch_size=[0])
    provenance = {
        "format": FORMAT,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "clips": list(clips),
        "clip_info": info,
        "skipped_clips": skipped,
        "filter": settings.as_dict(),
        "timestep": float(model.opt.timestep if timestep is None else timestep),
        "model": {
            "xml": str(xml),
            "sha256": _file_sha(xml),
            "nq": int(model.nq),
            "nv": int(model.nv),
            "joints": [model.joint(j).name for j in range(model.njnt)],
            "root_dofs": list(root_dofs(model)),
        },
        "inverse_dynamics": {"contacts": False, "limits": False, "passive": passive},
        "torques": {
            "source": torques,
            "tracking": tracking.as_dict() if torques == "pd" else None,
        },
        "split": {
            "codes": {v: k for k, v in SPLIT_NAMES.items()},
            "val_clips": list(val_clips),
            "val_time_fraction": val_time_fraction,
            "gap_s": gap_s,
            "seed": seed,
        },
        "glitch": {"threshold_deg": glitch_deg, "pad_s": glitch_pad_s},
        "samples_per_clip": samples_per_clip,
        "qd_qdd": "qd_k = differentiate_pos(Q_{k-1}, Q_k, dt); qdd_k = (qd_{k+1} - qd_k) / dt",
    }
    return MocapDataset(data=data, provenance=provenance)


def _retarget_files(
    files: ClipFiles, model: mujoco.MjModel, settings: FilterSettings, timestep: float | None
) -> RetargetedClip:
    skeleton = read_asf(files.asf)
    motion = read_amc(files.amc, skeleton)
    return retarget(motion, skeleton, model, settings, timestep=timestep, name=files.name)


def split_dataset(dataset: MocapDataset | TensorDict) -> DatasetSplits:
    """The train, held-out-segment and held-out-clip parts of a dataset."""
    data = dataset.data if isinstance(dataset, MocapDataset) else dataset
    split = data[keys.SPLIT].flatten()
    return DatasetSplits(
        train=data[split == TRAIN],
        val_time=data[split == VAL_TIME],
        val_clip=data[split == VAL_CLIP],
    )


def save_dataset(dataset: MocapDataset, path: str | Path, overwrite: bool = False) -> Path:
    """Write ``path/data`` (memory-mapped TensorDict) and ``path/provenance.json``."""
    path = Path(path)
    if path.exists() and any(path.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{path} exists and is not empty (pass overwrite=True)")
        shutil.rmtree(path)
    path.mkdir(parents=True, exist_ok=True)
    dataset.data.memmap(prefix=str(path / "data"))
    (path / "provenance.json").write_text(json.dumps(dataset.provenance, indent=1))
    log.info("saved %d mocap samples to %s", len(dataset), path)
    return path


def load_dataset(path: str | Path) -> MocapDataset:
    """Read a dataset written by `save_dataset` (into memory)."""
    path = Path(path)
    meta = path / "provenance.json"
    if not meta.is_file() or not (path / "data").is_dir():
        raise FileNotFoundError(f"{path} is not a saved mocap dataset (no data/ or {meta.name})")
    provenance = json.loads(meta.read_text())
    if provenance.get("format") != FORMAT:
        raise ValueError(f"{meta}: format {provenance.get('format')!r}, expected {FORMAT!r}")
    data = TensorDict.load_memmap(str(path / "data")).to_tensordict()
    return MocapDataset(data=data, provenance=provenance)
