"""`python -m mbrl_delan.bench suite=NAME out=FILE`: speed benchmarks as JSON Lines.

A dispatcher: ``suite=NAME`` chooses the config group ``configs/bench/suite/NAME.yaml``,
typed by the suite's schema (`mbrl_delan.conf.bench_schema.SUITE_SCHEMAS`), and runs the
suite's function (`mbrl_delan.benchmarks.SUITES`) on those options and the shared `BenchSettings`.

Each figure is one record `{"suite", "case", "metric", "value", "unit", "device", ...}`
appended to `out` as soon as it is measured (see `benchmarks/records.py`); the readable
table goes to the log at the end. `quick=true` runs tiny sizes (for tests and smoke runs).
Exit status 2 on a bad config value (an unknown suite included), naming the valid choices.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import replace

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from mbrl_delan.benchmarks import BenchSettings, TimingConfig, UnknownSuiteError, get_suite
from mbrl_delan.benchmarks.records import RecordWriter, format_table
from mbrl_delan.conf.bench_schema import SuiteConfig, check_suite_keys, typed_bench_config
from mbrl_delan.conf.checks import (
    CONFIGS,
    ConfigError,
    check_device,
    exit_on_config_errors,
    load_config_plugins,
)
from mbrl_delan.provenance import provenance
from mbrl_delan.stops import stop

log = logging.getLogger("mbrl_delan.bench")

QUICK_TIMING = TimingConfig(repeats=3, min_time_s=0.01, warmup=1)  # every suite's, quick=true


def build_options(cfg: DictConfig) -> tuple[SuiteConfig, BenchSettings]:
    """The suite's options (an instance of its schema) and the shared settings, checked once
    the config's ``plugins`` are loaded (their envs, models and planners count among the
    suite's choices); a `ConfigError` names the first bad key."""
    shared, own = typed_bench_config(cfg)
    load_config_plugins(shared)
    options = OmegaConf.to_object(own)
    options.check()
    timing = TimingConfig(repeats=shared.repeats, min_time_s=shared.min_time_s,
                          warmup=shared.warmup)  # fmt: skip
    bench = BenchSettings(
        device=check_device(shared.device),
        timing=QUICK_TIMING if shared.quick else timing,
        max_call_s=shared.max_call_s,
        max_memory_bytes=int(shared.max_memory_gb * 1024**3),
        quick=shared.quick,
    )
    return options, bench


def run(cfg: DictConfig) -> RecordWriter:
    """Run the configured suite, appending each record to `cfg.out` as it is measured."""
    options, bench = build_options(cfg)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    suite = get_suite(cfg.suite)
    try:
        writer = RecordWriter(cfg.out)
    except OSError as err:
        raise ConfigError(f"out={cfg.out!r}: cannot append records there ({err})") from err
    log.info(
        "suite %s on %s, %d torch threads%s",
        cfg.suite,
        bench.device,
        torch.get_num_threads(),
        f", appending to {writer.path}" if writer.path else "",
    )
    stamp = provenance("mbrl_delan.bench")  # the command, the code and the host at the start
    for record in suite(options, bench):
        writer.write(replace(record, extra=record.extra | stamp))
    log.info("suite %s:\n%s", cfg.suite, format_table(writer.records))
    return writer


@hydra.main(version_base="1.3", config_path="configs/bench", config_name="config")
def hydra_main(cfg: DictConfig) -> None:
    try:
        run(cfg)
    except (ConfigError, UnknownSuiteError) as err:
        stop("config error", err)


def _checked_main() -> None:
    defaults = OmegaConf.load(CONFIGS / "bench" / "config.yaml").defaults
    default_suite = next(d.suite for d in defaults if "suite" in d)
    check_suite_keys(sys.argv[1:], default_suite)  # Hydra's message would not name the suite
    hydra_main()


def main() -> None:
    """``python -m mbrl_delan.bench``: a config error, Hydra's included, exits 2 naming it."""
    exit_on_config_errors(_checked_main)


if __name__ == "__main__":
    main()
