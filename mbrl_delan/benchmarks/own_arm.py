"""Suite `own_arm`: ``python -m mbrl_delan.fit data=excitation`` at its defaults on real arms.

Its figure: ``python -m mbrl_delan.benchmarks.own_arm FILE [FILE ...] --out PNG [--robot panda]
[--friction]``: held-out torque MSE against training samples, one line per model (the mean
over seeds, a band from the smallest to the largest), the points in the log.

For every robot (`mbrl_delan.systems.arms`: panda, iiwa14, ur5e), with and without joint
friction, every training-set size and every model (``delan``, ``mlp``, ``white_box``): one fit
on the arm's excitation data (`mbrl_delan.data.excitation`, seeded by the bench's ``seed``,
which also seeds the fit), the test split held-out whole trajectories. One record per figure
(case ``<robot>_<model>[_friction]_<samples>``):

- ``test_torque_r2``: R^2 of the test torques (per-DoF normalised, `TorqueErrors`);
- ``test_torque_mse``: mean over test samples and DoFs of (tau_hat - tau)^2, N^2 m^2;
- ``mass_matrix_error`` (delan, white_box): median over the test states of
  ||M_model(q) - M(q)||_F / ||M(q)||_F, M the arm's own (`mj_fullM`, armature included);
- ``friction_torque_share`` (delan, white_box): RMS over the test samples of the model's
  friction torque / RMS of the test torques;
- ``fit_wall_s``: the fit's wall time, data made and evaluation included (a learned model
  trains until the validation error stops falling: the time to convergence);
- ``fit_epoch_s``: the training time per epoch (learned models).

Fields: ``robot``, ``model``, ``friction``, ``samples`` (training-set size asked:
``data.samples``), ``seed``, ``epochs``, ``train_samples`` and the host's.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch

from mbrl_delan import keys
from mbrl_delan.benchmarks import OWN_ARM_MODELS, OWN_ARM_ROBOTS, SuiteOptions, host_fields
from mbrl_delan.benchmarks.figures import describe_curves, plot_error_curves, read_record_files
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.checks import compose_config
from mbrl_delan.conf.fitting import FIT_CONFIG_DIR, fit_splits
from mbrl_delan.models.inverse import DeLaNInverse, InverseDynamicsModel
from mbrl_delan.models.rigid_body import WhiteBoxInverse

log = logging.getLogger(__name__)

SUITE = "own_arm"
UNITS = {"test_torque_mse": "N^2 m^2", "fit_wall_s": "s", "fit_epoch_s": "s"}


@dataclass(frozen=True)
class OwnArmConfig:
    """The grid: robots x friction x samples x models, at `seed`; `overrides` go to every fit."""

    robots: tuple[str, ...] = OWN_ARM_ROBOTS
    friction: tuple[bool, ...] = (False, True)
    samples: tuple[int, ...] = (10_000,)
    models: tuple[str, ...] = OWN_ARM_MODELS
    seed: int = 0
    overrides: tuple[str, ...] = ()

    @classmethod
    def quick(cls) -> OwnArmConfig:
        return cls(robots=("panda",), friction=(False,), samples=(600,),
                   overrides=("epochs=2",))  # fmt: skip


def friction_torque_share(model: InverseDynamicsModel, test: Any) -> float | None:
    """RMS of the model's friction torque over the test samples / RMS of their torques."""
    q, qd = test[keys.Q], test[keys.QD]
    with torch.no_grad():
        if isinstance(model, DeLaNInverse):
            friction = model.dynamics.terms(
                q.to(model.tau_scale), qd.to(model.tau_scale)
            ).dissipation
        elif isinstance(model, WhiteBoxInverse):
            friction = model.friction_torque(q, qd, test[keys.QDD])
        else:
            return None
    rms = lambda x: float(x.double().pow(2).mean().sqrt())  # noqa: E731
    return rms(friction) / rms(test[keys.TAU])


def fit_case(robot: str, friction: bool, samples: int, model: str, cfg: OwnArmConfig,
             folder: Path) -> dict[str, float]:  # fmt: skip
    """One fit's figures (module docstring)."""
    overrides = [
        "data=excitation", f"data.robot={robot}", f"data.friction={str(friction).lower()}",
        f"data.samples={samples}", f"data.seed={cfg.seed}", f"seed={cfg.seed}",
        f"model={model}", "logger=none", *cfg.overrides,
    ]  # fmt: skip
    start = time.perf_counter()
    summary, fitted, splits = fit_splits(compose_config(FIT_CONFIG_DIR, overrides), folder)
    wall = time.perf_counter() - start
    test = summary["final"]["test"]
    figures = {
        "test_torque_r2": test["r2"],
        "test_torque_mse": test["mse_si"],
        "fit_wall_s": wall,
        "epochs": summary["epochs"],
        "train_samples": summary["samples"]["train"],
    }
    if "mass_matrix_error" in summary:
        figures["mass_matrix_error"] = summary["mass_matrix_error"]["test"]
    share = friction_torque_share(fitted, splits["test"])
    if share is not None:
        figures["friction_torque_share"] = share
    if summary.get("train_s") is not None and model != "white_box":
        figures["fit_epoch_s"] = summary["train_s"] / summary["epochs"]
    return figures


def run_own_arm(cfg: OwnArmConfig) -> Iterator[BenchRecord]:
    host = host_fields(torch.device("cpu"))
    grid = itertools.product(cfg.robots, cfg.friction, cfg.samples, cfg.models)
    with tempfile.TemporaryDirectory() as tmp:
        for robot, friction, samples, model in grid:
            case = f"{robot}_{model}{'_friction' if friction else ''}_{samples}"
            figures = fit_case(robot, friction, samples, model, cfg, Path(tmp) / case)
            fields = {
                "robot": robot, "model": model, "friction": friction, "samples": samples,
                "seed": cfg.seed, "epochs": figures.pop("epochs"),
                "train_samples": figures.pop("train_samples"), **host,
            }  # fmt: skip
            for metric, value in figures.items():
                log.info("%s: %s = %.4g", case, metric, value)
                unit = UNITS.get(metric, "fraction")
                yield BenchRecord(SUITE, case, metric, value, unit, "cpu", fields)


def run_own_arm_suite(opts: SuiteOptions) -> Iterator[BenchRecord]:
    """The registered suite, on the CPU (`OwnArmConfig.quick` under `opts.quick`); `robots`,
    `friction`, `samples`, `models`, `seed` and `overrides` from the options."""
    cfg = OwnArmConfig.quick() if opts.quick else OwnArmConfig()
    given: dict[str, Any] = {
        "robots": opts.robots, "friction": opts.friction, "samples": opts.samples,
        "models": opts.models,
    }  # fmt: skip
    cfg = replace(cfg, **{k: v for k, v in given.items() if v is not None})
    cfg = replace(cfg, seed=opts.seed or 0, overrides=cfg.overrides + tuple(opts.overrides))
    yield from run_own_arm(cfg)


def sample_curves(
    records: list[dict[str, Any]], robot: str, friction: bool, metric: str = "test_torque_mse"
) -> dict[str, list[tuple[int, list[float]]]]:
    """Model -> [(samples, the metric's values over seeds)] of one arm, sorted by samples."""
    curves: dict[str, dict[int, list[float]]] = {}
    for r in records:
        if (r.get("suite"), r.get("metric"), r.get("robot")) != (SUITE, metric, robot):
            continue
        if r.get("friction") != friction or r.get("value") is None:
            continue
        curves.setdefault(r["model"], {}).setdefault(int(r["samples"]), []).append(r["value"])
    return {m: sorted(by_n.items()) for m, by_n in sorted(curves.items())}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="suite own_arm's sample-efficiency figure")
    parser.add_argument("files", nargs="+", type=Path, help="records of suite own_arm (JSONL)")
    parser.add_argument("--out", type=Path, required=True, help="the figure to write (PNG)")
    parser.add_argument("--robot", default="panda", choices=OWN_ARM_ROBOTS)
    parser.add_argument("--friction", action="store_true", help="the arm with joint friction")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    records = read_record_files(args.files)
    if records is None:
        return 2
    curves = sample_curves(records, args.robot, args.friction)
    if not curves:
        log.error("no %s test_torque_mse records of %s in %s", SUITE, args.robot,
                  ", ".join(map(str, args.files)))  # fmt: skip
        return 2
    for line in describe_curves(curves, x="samples"):
        log.info("%s", line)
    title = f"{args.robot}{' with joint friction' if args.friction else ''}: held-out torque error"
    figure = plot_error_curves(curves, args.out, title, "training samples",
                               "test torque MSE (N$^2$ m$^2$)", xlog=True)  # fmt: skip
    log.info("figure: %s", figure)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
