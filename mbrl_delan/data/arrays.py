"""Logged robot data from a file: (q, qd, [qdd], tau) arrays for inverse-dynamics fits.

The schema (`read_arrays`; one row per sample, N rows):

- ``q`` (N, nq): generalized positions in MuJoCo's qpos order ((N,) for one joint);
- ``qd`` (N, nv): generalized velocities;
- ``tau`` (N, nv): the generalized forces applied (they may include a controller's gravity
  and friction compensation: the model learns all of it);
- ``qdd`` (N, nv), optional: accelerations, computed from qd when absent (`accelerations`);
- ``t`` (N,), optional: time in s; or ``dt``, one number: the sampling interval in s;
- ``trajectory`` (N,), optional: integer id of each sample's trajectory; without it a new
  trajectory starts wherever ``t`` does not increase, else the file is one trajectory;
- ``tau_inertial``, ``tau_coriolis``, ``tau_gravity``, ``tau_friction`` (N, nv), optional: the
  parts M qdd, c(q, qd), g(q) and the joints' friction of tau, which ``python -m
  mbrl_delan.evaluate`` compares with the model's.

Files: ``.npz`` (`numpy.savez`, one array per field), ``.pt`` (`torch.save` of a dict of
tensors or arrays) or ``.csv`` (a header row; a vector field's columns are named
``<field><i>``: ``q0,q1,qd0,qd1,tau0,tau1,t,trajectory``). Every problem with a file raises
`ArrayFormatError` naming the file and the field.

Splits (`split_trajectories`): with at least three trajectories, whole ones go to ``test``,
and ``val`` is one contiguous segment of each other trajectory (or whole trajectories); with
fewer, each trajectory's last part is ``test`` and the part before it ``val``.
"""

from __future__ import annotations

import logging
import math
import pickle
import re
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.signal import butter, sosfiltfilt
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.systems.system import JointLayout

log = logging.getLogger(__name__)

SUFFIXES = (".npz", ".pt", ".csv")
COMPONENTS = (keys.TAU_INERTIAL, keys.TAU_CORIOLIS, keys.TAU_GRAVITY, keys.TAU_FRICTION)
VECTOR_FIELDS = ("q", "qd", "tau", "qdd", *COMPONENTS)
REQUIRED = ("q", "qd", "tau")
SPLITS = ("train", "val", "test")
_COLUMN = re.compile(r"^([a-z_]+?)(\d+)$")


class ArrayFormatError(ValueError):
    """A data file that does not follow the schema; the message names the file and field."""

    def __init__(self, path: str | Path, field: str, why: str) -> None:
        super().__init__(f"{path}: field {field!r}: {why}")
        self.path, self.field = str(path), field


@dataclass(frozen=True)
class DerivativeSettings:
    """How qdd is computed from qd when the data lack it: a zero-phase Butterworth low-pass
    of qd (`cutoff_hz`, None: no filtering) and central differences (`numpy.gradient`)."""

    cutoff_hz: float | None = None
    order: int = 4


# ---------------------------------------------------------------- reading


def _read_npz(path: Path) -> dict[str, Any]:
    if not zipfile.is_zipfile(path):  # np.load would take it for pickled data
        raise ArrayFormatError(
            path, "<file>", "is not a readable .npz archive (a truncated file, or not a zip one)"
        )
    with np.load(path, allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


def _read_pt(path: Path) -> dict[str, Any]:
    data = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(data, Mapping):
        raise ArrayFormatError(path, "<file>", f"holds a {type(data).__name__}, not a dict")
    return {str(k): v.numpy() if isinstance(v, torch.Tensor) else v for k, v in data.items()}


def _read_csv(path: Path) -> dict[str, Any]:
    with path.open() as f:
        header = [name.strip() for name in f.readline().strip().split(",")]
    try:
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as err:
        raise ArrayFormatError(path, "<rows>", f"not a table of numbers ({err})") from None
    if table.shape[1] != len(header):
        raise ArrayFormatError(
            path, "<header>", f"{len(header)} names for {table.shape[1]} columns"
        )
    columns: dict[str, list[tuple[int, np.ndarray]]] = {}
    out: dict[str, Any] = {}
    for j, name in enumerate(header):
        match = _COLUMN.match(name)
        if match and match.group(1) in VECTOR_FIELDS:
            columns.setdefault(match.group(1), []).append((int(match.group(2)), table[:, j]))
        else:
            out[name] = table[:, j]
    for name, cols in columns.items():
        order = sorted(cols, key=lambda c: c[0])
        if [i for i, _ in order] != list(range(len(order))):
            raise ArrayFormatError(
                path, name, f"columns {[f'{name}{i}' for i, _ in order]} are not {name}0..."
            )
        out[name] = np.stack([c for _, c in order], axis=1)
    return out


def read_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """The file's fields as float arrays (``trajectory`` as int64); unknown fields are kept.

    Raises FileNotFoundError for a missing file and `ArrayFormatError` for one that cannot
    be read or lacks ``q``, ``qd`` or ``tau``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"data file not found: {path}")
    if path.suffix not in SUFFIXES:
        raise ArrayFormatError(path, "<file>", f"unknown type; use one of {', '.join(SUFFIXES)}")
    readers = {".npz": _read_npz, ".pt": _read_pt, ".csv": _read_csv}
    try:
        raw = readers[path.suffix](path)
    except (OSError, ValueError, RuntimeError, EOFError, pickle.UnpicklingError,
            zipfile.BadZipFile) as err:  # fmt: skip
        if isinstance(err, ArrayFormatError):
            raise
        raise ArrayFormatError(path, "<file>", f"cannot be read ({err})") from None
    for name in REQUIRED:
        if name not in raw:
            raise ArrayFormatError(path, name, f"missing (the file has {sorted(raw)})")
    out = {}
    for name, value in raw.items():
        try:
            out[name] = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise ArrayFormatError(path, name, "is not numeric") from None
    return out


# ---------------------------------------------------------------- checking


def _vector(path: Path, name: str, value: np.ndarray, n: int, width: int) -> np.ndarray:
    """A (N, width) field, (N,) accepted for width 1; named errors for shape and NaN/inf."""
    if value.ndim == 1 and width == 1:
        value = value[:, None]
    if value.ndim != 2:
        raise ArrayFormatError(path, name, f"shape {value.shape}; expected ({n}, {width})")
    if value.shape[0] != n:
        raise ArrayFormatError(path, name, f"{value.shape[0]} rows, but q has {n}")
    if value.shape[1] != width:
        raise ArrayFormatError(
            path, name, f"{value.shape[1]} columns; the joints give {width} (a wrong joint count?)"
        )
    _finite(path, name, value)
    return value


def _finite(path: Path, name: str, value: np.ndarray) -> None:
    bad = ~np.isfinite(value)
    if bad.any():
        row = int(np.argwhere(bad)[0][0])
        raise ArrayFormatError(path, name, f"{int(bad.sum())} NaN or inf values (first: row {row})")


def _times(path: Path, fields: Mapping[str, np.ndarray], n: int) -> np.ndarray | None:
    """Sample times (N,) from ``t`` or ``dt``; None when the file has neither."""
    if "t" in fields:
        t = fields["t"].reshape(-1) if fields["t"].size == n else None
        if t is None:
            raise ArrayFormatError(path, "t", f"shape {fields['t'].shape}; expected ({n},)")
        _finite(path, "t", t)
        return t
    if "dt" in fields:
        dt = fields["dt"].reshape(-1)
        if dt.size != 1 or not math.isfinite(float(dt[0])) or float(dt[0]) <= 0:
            raise ArrayFormatError(path, "dt", f"{dt[:3]}; expected one number > 0")
        return np.arange(n) * float(dt[0])
    return None


def _trajectories(
    path: Path, fields: Mapping[str, np.ndarray], t: np.ndarray | None, n: int
) -> np.ndarray:
    """Trajectory id per sample (N,) int64: the ``trajectory`` field, else a new one wherever
    t does not increase, else all 0."""
    if "trajectory" in fields:
        ids = fields["trajectory"].reshape(-1)
        if ids.size != n:
            raise ArrayFormatError(path, "trajectory", f"{ids.size} values, but q has {n} rows")
        _finite(path, "trajectory", ids)
        if not np.array_equal(ids, np.round(ids)):
            raise ArrayFormatError(path, "trajectory", "holds non-integer ids")
        return ids.astype(np.int64)
    if t is None:
        return np.zeros(n, dtype=np.int64)
    return np.concatenate([[0], np.cumsum(np.diff(t) <= 0)]).astype(np.int64)


def save_arrays(data: TensorDict | Mapping[str, Any], path: str | Path) -> Path:
    """Write the schema's fields of `data` (tensors or arrays) to a ``.npz``, ``.pt`` or
    ``.csv`` file; the other keys are left out."""
    path = Path(path)
    names = (*VECTOR_FIELDS, "t", "dt", "trajectory")
    fields = {k: np.asarray(data[k]) for k in names if k in data.keys()}
    if path.suffix == ".npz":
        np.savez(path, **fields)
    elif path.suffix == ".pt":
        torch.save({k: torch.from_numpy(v) for k, v in fields.items()}, path)
    elif path.suffix == ".csv":
        columns, header = [], []
        for name, value in fields.items():
            if name in VECTOR_FIELDS:
                value = value.reshape(value.shape[0], -1)
                columns += list(value.T)
                header += [f"{name}{i}" for i in range(value.shape[1])]
            else:
                columns.append(value.reshape(-1))
                header.append(name)
        np.savetxt(
            path, np.stack(columns, axis=1), delimiter=",", header=",".join(header), comments=""
        )
    else:
        raise ValueError(f"{path}: unknown type; use one of {', '.join(SUFFIXES)}")
    return path


def accelerations(
    qd: np.ndarray, t: np.ndarray, settings: DerivativeSettings, name: str
) -> np.ndarray:
    """qdd of one trajectory: qd (T, nv) low-passed (zero-phase Butterworth) and
    differentiated by central differences at the times t (T,)."""
    if qd.shape[0] < 3:
        raise ValueError(f"{name}: {qd.shape[0]} samples are too few to differentiate qd")
    steps = np.diff(t)
    if (steps <= 0).any():
        raise ValueError(f"{name}: t does not increase")
    if settings.cutoff_hz is not None:
        rate = 1.0 / float(np.median(steps))
        if settings.cutoff_hz >= rate / 2:
            raise ValueError(
                f"{name}: cutoff {settings.cutoff_hz} Hz is not below half the sampling "
                f"rate ({rate / 2:g} Hz)"
            )
        sos = butter(settings.order, settings.cutoff_hz, fs=rate, output="sos")
        padlen = 3 * (2 * len(sos) + 1)
        if qd.shape[0] <= padlen:
            raise ValueError(f"{name}: {qd.shape[0]} samples are too few for the low-pass filter")
        qd = sosfiltfilt(sos, qd, axis=0, padlen=padlen)
    return np.gradient(qd, t, axis=0)


def load_arrays(
    path: str | Path,
    layout: JointLayout,
    derivative: DerivativeSettings | None = None,
) -> TensorDict:
    """The file as a float64 TensorDict (N,) with q, qd, qdd, tau, ``trajectory`` (N, 1),
    ``time`` (N, 1) (NaN when the file has no times) and any of the tau parts.

    Raises `ArrayFormatError` for a field that is missing, of the wrong shape or joint count,
    of another length than q, or holding NaN or inf, and for qdd that cannot be computed."""
    return arrays_tensordict(path, read_arrays(path), layout, derivative)


def arrays_tensordict(
    path: str | Path,
    fields: Mapping[str, np.ndarray],
    layout: JointLayout,
    derivative: DerivativeSettings | None = None,
) -> TensorDict:
    """`load_arrays` on the fields `read_arrays` read from `path` (named in errors)."""
    path = Path(path)
    n = fields["q"].shape[0] if fields["q"].ndim else 0
    if n < 2:
        raise ArrayFormatError(path, "q", f"{n} samples; need at least 2")
    widths = {"q": layout.nq, "qd": layout.nv, "tau": layout.nv}
    widths |= {name: layout.nv for name in ("qdd", *COMPONENTS) if name in fields}
    arrays = {name: _vector(path, name, fields[name], n, w) for name, w in widths.items()}
    t = _times(path, fields, n)
    ids = _trajectories(path, fields, t, n)
    if "qdd" not in arrays:
        if t is None:
            raise ArrayFormatError(path, "qdd", "missing, and no t or dt to compute it from qd")
        arrays["qdd"] = np.empty_like(arrays["qd"])
        for i in np.unique(ids):
            rows = ids == i
            try:
                arrays["qdd"][rows] = accelerations(
                    arrays["qd"][rows],
                    t[rows],
                    derivative or DerivativeSettings(),
                    f"trajectory {i}",
                )
            except ValueError as err:
                raise ArrayFormatError(path, "qdd", f"cannot be computed: {err}") from None
    td = TensorDict(
        {name: torch.from_numpy(np.ascontiguousarray(a)) for name, a in arrays.items()},
        batch_size=[n],
    )
    td[keys.TRAJECTORY] = torch.from_numpy(ids).unsqueeze(-1)
    time = t if t is not None else np.full(n, np.nan)
    td[keys.TIME] = torch.from_numpy(np.asarray(time, dtype=np.float64)).unsqueeze(-1)
    return td


# ---------------------------------------------------------------- splitting


VAL_BY = ("trajectories", "segments")


def split_trajectories(
    ids: torch.Tensor,
    val_fraction: float,
    test_fraction: float,
    seed: int,
    val_by: str = "trajectories",
) -> dict[str, torch.Tensor]:
    """Boolean masks (N,) of the ``train``, ``val`` and ``test`` samples for trajectory ids
    (N,) or (N, 1).

    With at least three trajectories, whole trajectories (shuffled with `seed`) go to test,
    ``round(test_fraction x count)`` of them but at least one where the fraction is > 0.
    Validation: in each remaining trajectory one contiguous segment of `val_fraction` of its
    samples at a random place (`val_by="segments"`), or whole trajectories as for test
    (`val_by="trajectories"`). With too few trajectories for whole ones, the last
    `test_fraction` of every trajectory is test and the `val_fraction` before it val."""
    if val_by not in VAL_BY:
        raise ValueError(f"val_by must be one of {VAL_BY}, got {val_by!r}")
    ids = ids.reshape(-1).cpu()
    unique = ids.unique()
    count = unique.numel()
    generator = torch.Generator().manual_seed(seed)
    n_test = max(int(test_fraction > 0), round(test_fraction * count))
    n_val = (
        max(int(val_fraction > 0), round(val_fraction * count)) if val_by == "trajectories" else 0
    )
    if count - n_test - n_val >= 1:
        order = unique[torch.randperm(count, generator=generator)]
        test = torch.isin(ids, order[:n_test])
        if val_by == "segments":
            val = _segments(ids, order[n_test:], val_fraction, generator)
        else:
            val = torch.isin(ids, order[n_test : n_test + n_val])
        return {"train": ~(test | val), "val": val, "test": test}
    log.info("%d trajectories: holding out the end of each one (val, then test)", count)
    test = torch.zeros(ids.numel(), dtype=torch.bool)
    val = torch.zeros(ids.numel(), dtype=torch.bool)
    for i in unique:
        rows = torch.nonzero(ids == i).reshape(-1)  # in the file's order
        n_test = round(test_fraction * rows.numel())
        n_val = round(val_fraction * rows.numel())
        test[rows[rows.numel() - n_test :]] = True
        val[rows[rows.numel() - n_test - n_val : rows.numel() - n_test]] = True
    return {"train": ~(test | val), "val": val, "test": test}


def _segments(
    ids: torch.Tensor, trajectories: torch.Tensor, fraction: float, generator: torch.Generator
) -> torch.Tensor:
    """One contiguous segment of `fraction` of each trajectory's samples, at a random place.
    (N,) bool."""
    val = torch.zeros(ids.numel(), dtype=torch.bool)
    for i in trajectories.tolist():
        rows = torch.nonzero(ids == i).reshape(-1)
        length = round(fraction * rows.numel())
        start = int(torch.randint(0, rows.numel() - length + 1, (1,), generator=generator))
        val[rows[start : start + length]] = True
    return val
