"""Benchmark records: one JSON object per measured figure, written as JSON Lines.

Every record has the fields `suite`, `case`, `metric`, `value`, `unit`, `device` (the stable
names tools read) plus free extra fields (nv, batch, dtype, threads, versions, ...). A
figure that was not measured (skipped as too slow or too large) has `value: null` and a
`note` saying why, so the file stays valid JSON (no NaN) and the gap is visible.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

BASE_FIELDS = ("suite", "case", "metric", "value", "unit", "device")


@dataclass
class BenchRecord:
    """One measured figure."""

    suite: str
    case: str
    metric: str
    value: float | None  # None: not measured, `extra["note"]` says why
    unit: str
    device: str
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The flat JSON object: the base fields first, then the extra fields."""
        clash = set(BASE_FIELDS) & set(self.extra)
        if clash:
            raise ValueError(f"extra fields may not reuse the base field names {sorted(clash)}")
        value = self.value
        if value is not None and not math.isfinite(value):
            raise ValueError(f"{self.metric} of {self.case}: value {value} is not finite")
        base = dict(
            suite=self.suite,
            case=self.case,
            metric=self.metric,
            value=None if value is None else float(value),
            unit=self.unit,
            device=self.device,
        )
        return {**base, **self.extra}


class RecordWriter:
    """Appends records to a JSON Lines file, one `write` system call per line.

    The file is opened with O_APPEND for every record, so lines from several writers (or
    runs) never interleave within a line and a crash leaves only whole lines behind; an
    existing file is extended, never truncated. `path=None` keeps the records in memory only.
    """

    def __init__(self, path: str | Path | None) -> None:
        self.path = None if path is None else Path(path)
        self.records: list[BenchRecord] = []
        if self.path is not None:  # fail now, not after the first measurement
            self.path.parent.mkdir(parents=True, exist_ok=True)
            os.close(os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644))

    def write(self, record: BenchRecord) -> None:
        line = json.dumps(record.to_dict(), allow_nan=False, sort_keys=False) + "\n"
        self.records.append(record)
        if self.path is None:
            return
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            data = line.encode()
            written = os.write(fd, data)
            if written != len(data):
                raise OSError(f"short write to {self.path}: {written} of {len(data)} bytes")
        finally:
            os.close(fd)


def read_records(path: str | Path) -> list[dict[str, Any]]:
    """All records of a JSON Lines file, in order."""
    lines = Path(path).read_text().splitlines()
    return [json.loads(line) for line in lines if line.strip()]


def _format_value(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.4g}" if abs(value) < 1e4 else f"{value:.3e}"


def format_table(records: Iterable[BenchRecord]) -> str:
    """A fixed-width text table: case, metric, value, unit, note."""
    rows = [
        (r.case, r.metric, _format_value(r.value), r.unit, str(r.extra.get("note", "")))
        for r in records
    ]
    header = ("case", "metric", "value", "unit", "note")
    widths = [max(len(x) for x in col) for col in zip(header, *rows, strict=False)]
    lines = [
        "  ".join(x.ljust(w) for x, w in zip(row, widths, strict=True)).rstrip()
        for row in (header, tuple("-" * w for w in widths), *rows)
    ]
    return "\n".join(lines)
