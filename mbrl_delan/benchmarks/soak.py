"""Suite `soak`: a long training loop on the pendulum, its memory and time round by round.

`python -m mbrl_delan.bench suite=soak` runs `ROUNDS` rounds of `python -m mbrl_delan.train`'s
loop in this process (DeLaN, MPPI, the pendulum at the sizes of `OVERRIDES`; no checkpoints,
logger or videos) and records after every round:

- `rss_mb`: the process's resident memory (MB, 2^20 bytes) at the round's end;
- `round_s`: the seconds of the round (collect, refit, evaluate when due);

with the round and its env steps as fields, and once, `rss_growth_mb`: the resident memory at
the last round minus that at the end of the first half (the buffer, the fits and the caches
have settled by then), which a leak makes grow with the rounds. `quick=true`: 3 rounds of
20-step episodes, 16 samples over a horizon of 10.
"""

from __future__ import annotations

import logging
import os
import resource
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from mbrl_delan.benchmarks import BenchSettings, host_fields
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import SuiteConfig

log = logging.getLogger(__name__)

SUITE = "soak"
ROUNDS, QUICK_ROUNDS = 50, 3
QUICK_OVERRIDES = ("env.episode_len=20", "planner.num_samples=16", "env.horizon=10")
CASE = "pendulum-delan-mppi"
OVERRIDES = (
    "env=pendulum", "model=delan", "planner=mppi", "logger=none",
    "env.episode_len=50", "planner.num_samples=64", "planner.iterations=2",
    "budget.eval_every=10", "budget.eval_episodes=1", "budget.final_eval_episodes=1",
    "budget.oracle_episodes=1", "budget.env_steps=null", "fit.max_epochs=10",
)  # fmt: skip


def rss_mb() -> float:
    """Resident memory of this process in MB: /proc/self/statm on Linux, else the peak from
    getrusage (which can only grow)."""
    statm = Path("/proc/self/statm")
    if statm.is_file():
        pages = int(statm.read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return peak / (2**20 if sys.platform == "darwin" else 2**10)


def soak_rounds(rounds: int, device: str, extra: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """Run the loop for `rounds` rounds (`OVERRIDES`, then `extra`); per round its number,
    env steps, seconds and RSS."""
    from mbrl_delan.conf.checks import CONFIG_DIR, compose_config, validate_train_config
    from mbrl_delan.conf.loop import build_loop, schedule_of
    from mbrl_delan.training.loop import LoopHooks

    overrides = [*OVERRIDES, *extra, f"budget.iterations={rounds}", f"device={device}"]
    cfg = validate_train_config(compose_config(CONFIG_DIR, overrides))
    rows: list[dict[str, Any]] = []
    last = time.perf_counter()

    def log_round(metrics: dict[str, Any]) -> None:
        nonlocal last
        now = time.perf_counter()
        row = {"round": len(rows) + 1, "env_steps": int(metrics["env_steps"])}
        rows.append({**row, "round_s": now - last, "rss_mb": rss_mb()})
        log.info("soak: round %d, %.2f s, %.1f MB", row["round"], now - last, rows[-1]["rss_mb"])
        last = now

    with tempfile.TemporaryDirectory() as run_dir:
        loop, oracle = build_loop(cfg, Path(run_dir))
        loop.run(schedule_of(cfg), oracle, LoopHooks(log_round=log_round))
    return rows


def run_soak_suite(options: SuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    """The registered suite: `rss_mb` and `round_s` per round, then `rss_growth_mb` (the
    suite has no options of its own)."""
    rounds, extra = (QUICK_ROUNDS, QUICK_OVERRIDES) if bench.quick else (ROUNDS, ())
    device, host = str(bench.device), host_fields(bench.device)
    rows = soak_rounds(rounds, device, extra)
    for row in rows:
        fields = {"round": row["round"], "env_steps": row["env_steps"], **host}
        yield BenchRecord(SUITE, CASE, "rss_mb", row["rss_mb"], "MB", device, fields)
        yield BenchRecord(SUITE, CASE, "round_s", row["round_s"], "s", device, fields)
    settled = rows[len(rows) // 2 - 1] if len(rows) > 1 else rows[0]
    growth = rows[-1]["rss_mb"] - settled["rss_mb"]
    fields = {"rounds": len(rows), "from_round": settled["round"], **host}
    yield BenchRecord(SUITE, CASE, "rss_growth_mb", growth, "MB", device, fields)
