"""Suite `own_arm`: ``python -m mbrl_delan.fit data=excitation`` at its defaults on arms.

Its figure: ``python -m mbrl_delan.benchmarks.own_arm FILE [FILE ...] --out PNG [--robot panda]
[--friction KIND]``: held-out torque MSE against training samples, one line per model (the
mean over seeds, a band from the smallest to the largest), the points in the log. Its table
of what the MJCF lacks: ``python -m mbrl_delan.benchmarks.own_arm FILE [FILE ...] --table``
(markdown on standard output, `structure_table`).

For every robot (`mbrl_delan.systems.arms`: panda, iiwa14, ur5e, slim7, light6), friction
kind (none, frictionloss, coulomb_viscous), structure the MJCF lacks (none, counterbalance,
coupling: springs in the arm that makes the data only), training-set size, training design,
test design and model (``tree_delan``, ``delan``, ``mlp``, ``white_box``): one fit on the
arm's excitation data (`mbrl_delan.data.excitation`, seeded by the bench's ``seed``, which
also seeds the fit and draws the CAD file), the models given ``model_mjcf`` (exact: the
arm's own MJCF; cad: its inertials off as a CAD export's, `mbrl_delan.systems.arms`). The
test split: whole held-out trajectories of the training design, or trajectories of another
design (``data.test_design``); validation: whole training trajectories. One record per
figure, case
``<robot>_<model>_<friction>[_<structure>]_<samples>_<train design>[_to_<test design>][_cad]``:

- ``test_torque_r2``, ``val_torque_r2``: R^2 of the test and validation torques (per-DoF
  normalised, `TorqueErrors`);
- ``test_torque_mse``: mean over test samples and DoFs of (tau_hat - tau)^2, N^2 m^2;
- ``truth_torque_r2``: ``test_torque_r2`` of the arm's own dynamics (its MJCF's numbers,
  springs and friction law, `true_arm`) on the same measured test data: the most any model
  can reach with the data's noise;
- ``mass_matrix_error`` (delan, tree_delan, white_box): median over the test states of
  ||M_model(q) - M(q)||_F / ||M(q)||_F, M the arm's own (`mj_fullM`, armature included);
- ``friction_torque_share`` (delan, tree_delan, white_box): RMS over the test samples of the
  model's friction torque / RMS of the test torques;
- ``fit_wall_s``: the fit's wall time, data made and evaluation included (a learned model
  trains until the validation error stops falling: the time to convergence);
- ``fit_epoch_s``: the training time per epoch (learned models);
- with springs, tree_delan: ``spring_stiffness_error``, the median over test states of
  ||K_res - K||_F / ||K||_F on the springs' joints, K = d tau_spring / dq of the arm's springs
  (`spring_stiffness_matrix`) and K_res = d g_res / dq of the DeLaN residual's potential
  force (central differences); ``spring_stiffness``, the residual's learned stiffness (the
  median of K_res's shoulder diagonal, or of its wrist pair's coupling entry), against the
  field ``arm_spring_stiffness``;
- with springs: ``spring_torque_share``, RMS of the springs' torque on their joints over RMS
  of those joints' test torques.

Fields: ``robot``, ``model``, ``friction``, ``structure``, ``model_mjcf``, ``samples``
(training-set size asked: ``data.samples``), ``train_design``, ``test_design``, ``seed``,
``epochs``, ``train_samples`` and the host's.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import tempfile
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mbrl_delan import keys
from mbrl_delan.benchmarks import (
    OWN_ARM_MODELS,
    OWN_ARM_ROBOTS,
    BenchSettings,
    host_fields,
    with_options,
)
from mbrl_delan.benchmarks.figures import describe_curves, plot_error_curves, read_record_files
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import OwnArmSuiteConfig
from mbrl_delan.conf.checks import compose_config
from mbrl_delan.conf.fitting import FIT_CONFIG_DIR
from mbrl_delan.fit_run import fit_splits
from mbrl_delan.models.inverse import DeLaNInverse, InverseDynamicsModel
from mbrl_delan.models.rigid_body import WhiteBoxInverse, data_friction_law
from mbrl_delan.stops import stop_line
from mbrl_delan.systems.arms import (
    FRICTION_KINDS,
    arm_model,
    coulomb_friction,
    friction_kind,
    shoulder_joint,
    spring_torque,
    wrist_pair,
)
from mbrl_delan.systems.jacobian import central_jacobian
from mbrl_delan.training.inverse_fit import evaluate_torques

log = logging.getLogger(__name__)

SUITE = "own_arm"
UNITS = {
    "test_torque_mse": "N^2 m^2",
    "fit_wall_s": "s",
    "fit_epoch_s": "s",
    "spring_stiffness": "N m/rad",
}


@dataclass(frozen=True)
class OwnArmConfig:
    """The grid: robots x friction x samples x models, at `seed`; `overrides` go to every fit."""

    robots: tuple[str, ...] = OWN_ARM_ROBOTS
    friction: tuple[str, ...] = ("none", "coulomb_viscous")
    samples: tuple[int, ...] = (10_000,)
    models: tuple[str, ...] = OWN_ARM_MODELS
    designs: tuple[str, ...] = ("fourier",)
    test_designs: tuple[str | None, ...] = (None,)  # None: the training design's held-out
    structures: tuple[str, ...] = ("none",)
    model_mjcf: str = "exact"
    seed: int = 0
    overrides: tuple[str, ...] = ()

    @classmethod
    def quick(cls) -> OwnArmConfig:
        return cls(robots=("panda",), friction=("none",), samples=(600,),
                   overrides=("epochs=2",))  # fmt: skip


def friction_torque_share(model: InverseDynamicsModel, test: Any) -> float | None:
    """RMS of the model's friction torque over the test samples / RMS of their torques."""
    q, qd = test[keys.Q], test[keys.QD]
    with torch.no_grad():
        if isinstance(model, DeLaNInverse):
            friction = model.friction_torque(qd.to(model.tau_scale))
        elif isinstance(model, WhiteBoxInverse):
            friction = model.friction_torque(q, qd, test[keys.QDD])
        else:
            return None
    rms = lambda x: float(x.double().pow(2).mean().sqrt())  # noqa: E731
    return rms(friction) / rms(test[keys.TAU])


@dataclass(frozen=True)
class Case:
    """One fit of the grid."""

    robot: str
    friction: str
    samples: int
    model: str
    design: str
    test_design: str | None  # None: the training design's held-out trajectories
    structure: str = "none"
    model_mjcf: str = "exact"

    @property
    def name(self) -> str:
        cross = f"_to_{self.test_design}" if self.test_design not in (None, self.design) else ""
        springs = "" if self.structure == "none" else f"_{self.structure}"
        cad = "" if self.model_mjcf == "exact" else f"_{self.model_mjcf}"
        return (f"{self.robot}_{self.model}_{self.friction}{springs}_{self.samples}_"
                f"{self.design}{cross}{cad}")  # fmt: skip


def true_arm(robot: str, friction: str, train: Any, structure: str = "none") -> WhiteBoxInverse:
    """The arm's own inverse dynamics as a white box (its MJCF's inertials, friction,
    armature and springs, the friction's law), in the loss units of the training split
    `train`."""
    truth = arm_model(robot, friction)
    model = WhiteBoxInverse(arm_model(robot, structure=structure), prior_scale=1.0,
                            friction_law=data_friction_law(friction))  # fmt: skip
    model.fit_normalization(train)
    model.viscous.copy_(torch.as_tensor(truth.dof_damping))
    model.armature.copy_(torch.as_tensor(truth.dof_armature))
    model.coulomb.copy_(torch.as_tensor(coulomb_friction(robot, friction) + truth.dof_frictionloss))
    return model


def spring_joints(robot: str, structure: str) -> tuple[int, ...]:
    """The joints `structure`'s springs act on (`mbrl_delan.systems.arms`)."""
    model = arm_model(robot)
    return (shoulder_joint(model),) if structure == "counterbalance" else wrist_pair(model)


def spring_stiffness_matrix(robot: str, structure: str, q: np.ndarray, step: float = 1e-4
                            ) -> np.ndarray:  # fmt: skip
    """K = d tau_spring / dq of the arm's springs in configurations q (N, nq), by central
    differences of `step` (exact for linear springs). (N, nv, nv)"""
    model = arm_model(robot, structure=structure)
    return central_jacobian(lambda x: spring_torque(model, x), q, range(model.nv), step)


@torch.no_grad()
def residual_stiffness_matrix(model: DeLaNInverse, q: torch.Tensor, step: float = 1e-4
                              ) -> torch.Tensor:  # fmt: skip
    """K_res = d g_res / dq of the tree's DeLaN residual's potential force at q (N, nq), by
    central differences of `step` (hinges and slides: nq = nv). (N, nv, nv)"""
    residual, zero = model.dynamics.residual, torch.zeros_like(q)
    return central_jacobian(lambda x: residual.terms(x, zero).gravity, q, range(q.shape[-1]),
                            step)  # fmt: skip


STIFFNESS_STATES = 256  # test states the springs' stiffness is compared in


def spring_figures(case: Case, fitted: InverseDynamicsModel, test: Any) -> dict[str, float]:
    """The springs' torque share and, for a tree's DeLaN residual, its learned stiffness
    against the arm's (module docstring); {} without springs."""
    if case.structure == "none":
        return {}
    joints = list(spring_joints(case.robot, case.structure))
    q = test[keys.Q][:STIFFNESS_STATES].to("cpu", torch.float64)
    spring = spring_torque(arm_model(case.robot, structure=case.structure),
                           test[keys.Q].to("cpu", torch.float64).numpy())  # fmt: skip
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    tau = test[keys.TAU][:, joints].to("cpu", torch.float64).numpy()
    out = {"spring_torque_share": rms(spring[:, joints]) / rms(tau)}
    arm = spring_stiffness_matrix(case.robot, case.structure, q.numpy())[:, joints][..., joints]
    pick = (0, 0) if len(joints) == 1 else (0, 1)  # the shoulder's, the pair's coupling
    out["arm_spring_stiffness"] = float(np.median(arm[:, pick[0], pick[1]]))
    if isinstance(fitted, DeLaNInverse) and getattr(fitted.dynamics, "residual", None):
        learned = residual_stiffness_matrix(fitted, q.to(fitted.tau_scale))
        learned = learned.to(torch.float64).numpy()[:, joints][..., joints]
        error = np.linalg.norm(learned - arm, axis=(1, 2)) / np.linalg.norm(arm, axis=(1, 2))
        out["spring_stiffness_error"] = float(np.median(error))
        out["spring_stiffness"] = float(np.median(learned[:, pick[0], pick[1]]))
    return out


def fit_case(case: Case, cfg: OwnArmConfig, folder: Path) -> dict[str, float]:
    """One fit's figures (module docstring)."""
    test = [] if case.test_design in (None, case.design) else [
        f"data.test_design={case.test_design}"]  # fmt: skip
    overrides = [
        "data=excitation", f"data.robot={case.robot}", f"data.friction={case.friction}",
        f"data.samples={case.samples}", f"data.design={case.design}", *test,
        f"data.structure={case.structure}", f"data.model_mjcf={case.model_mjcf}",
        f"data.seed={cfg.seed}", f"seed={cfg.seed}", f"model={case.model}", "logger=none",
        *cfg.overrides,
    ]  # fmt: skip
    start = time.perf_counter()
    summary, fitted, splits = fit_splits(compose_config(FIT_CONFIG_DIR, overrides), folder)
    wall = time.perf_counter() - start
    test = summary["final"]["test"]
    figures = {
        "test_torque_r2": test["r2"],
        "val_torque_r2": summary["final"]["val"]["r2"],
        "test_torque_mse": test["mse_si"],
        "fit_wall_s": wall,
        "epochs": summary["epochs"],
        "train_samples": summary["samples"]["train"],
    }
    truth = true_arm(case.robot, case.friction, splits["train"], case.structure)
    figures["truth_torque_r2"] = evaluate_torques(truth, splits["test"], 4096).r2
    if "mass_matrix_error" in summary:
        figures["mass_matrix_error"] = summary["mass_matrix_error"]["test"]
    share = friction_torque_share(fitted, splits["test"])
    if share is not None:
        figures["friction_torque_share"] = share
    if summary.get("train_s") is not None and case.model != "white_box":
        figures["fit_epoch_s"] = summary["train_s"] / summary["epochs"]
    return figures | spring_figures(case, fitted, splits["test"])


def run_own_arm(cfg: OwnArmConfig) -> Iterator[BenchRecord]:
    host = host_fields(torch.device("cpu"))
    grid = itertools.product(cfg.robots, cfg.friction, cfg.samples, cfg.models, cfg.designs,
                             cfg.test_designs, cfg.structures, (cfg.model_mjcf,))  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        for case in itertools.starmap(Case, grid):
            figures = fit_case(case, cfg, Path(tmp) / case.name)
            stiffness = figures.pop("arm_spring_stiffness", None)
            fields = {
                "robot": case.robot, "model": case.model, "friction": case.friction,
                "structure": case.structure, "model_mjcf": case.model_mjcf,
                "samples": case.samples, "train_design": case.design,
                "test_design": case.test_design or case.design, "seed": cfg.seed,
                "epochs": figures.pop("epochs"), "train_samples": figures.pop("train_samples"),
                **({} if stiffness is None else {"arm_spring_stiffness": stiffness}), **host,
            }  # fmt: skip
            for metric, value in figures.items():
                log.info("%s: %s = %.4g", case.name, metric, value)
                unit = UNITS.get(metric, "fraction")
                yield BenchRecord(SUITE, case.name, metric, value, unit, "cpu", fields)


def run_own_arm_suite(options: OwnArmSuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    """The registered suite, on the CPU (`OwnArmConfig.quick` under `bench.quick`); every
    option that is not None replaces its field (`overrides`: added to the config's)."""
    cfg = OwnArmConfig.quick() if bench.quick else OwnArmConfig()
    given = asdict(options) | {"overrides": (*cfg.overrides, *options.overrides),
                               "seed": options.seed or 0}  # fmt: skip
    cfg = with_options(cfg, given)
    yield from run_own_arm(cfg)


def sample_curves(
    records: list[dict[str, Any]], robot: str, friction: str, metric: str = "test_torque_mse"
) -> dict[str, list[tuple[int, list[float]]]]:
    """Model -> [(samples, the metric's values over seeds)] of one arm and friction kind,
    sorted by samples (records written before the kinds: friction true or false)."""
    curves: dict[str, dict[int, list[float]]] = {}
    for r in records:
        if (r.get("suite"), r.get("metric"), r.get("robot")) != (SUITE, metric, robot):
            continue
        if friction_kind(r.get("friction", "none")) != friction or r.get("value") is None:
            continue
        curves.setdefault(r["model"], {}).setdefault(int(r["samples"]), []).append(r["value"])
    return {m: sorted(by_n.items()) for m, by_n in sorted(curves.items())}


TABLE_MODELS = ("white_box", "tree_delan", "mlp")  # the table's models, in its order
TABLE_ROWS = ("none", "counterbalance", "coupling")  # ... and structures


def _by_seed(records: list[dict[str, Any]], metric: str) -> dict[tuple, dict[int, float]]:
    """(structure, robot, model) -> seed -> the metric's value."""
    out: dict[tuple, dict[int, float]] = {}
    for r in records:
        if r.get("suite") == SUITE and r.get("metric") == metric and r.get("value") is not None:
            key = (r.get("structure", "none"), r["robot"], r["model"])
            out.setdefault(key, {})[int(r["seed"])] = float(r["value"])
    return out


def _any_model(values: dict[tuple, dict[int, float]], row: tuple) -> dict[int, float]:
    """A figure of the data, not the model: any model's record of the row's (structure,
    robot)."""
    return next((v for k, v in values.items() if k[:2] == row), {})


def structure_table(records: list[dict[str, Any]]) -> list[str]:
    """The markdown table of what an MJCF lacks (docs/own_robot.md): per structure and arm,
    each model's test R^2 per seed ('a / b / c'), the arm's own R^2, tree_delan's M error,
    the springs' torque share and the residual's learned stiffness against the arm's."""
    seeds = sorted({int(r["seed"]) for r in records if r.get("suite") == SUITE})

    def cell(values: dict[int, float], fmt: str, scale: float = 1.0) -> str:
        return " / ".join(format(scale * values[s], fmt) if s in values else "-" for s in seeds)

    figures = {m: _by_seed(records, m) for m in (
        "test_torque_r2", "truth_torque_r2", "mass_matrix_error", "spring_torque_share",
        "spring_stiffness")}  # fmt: skip
    arm = {(r.get("structure"), r["robot"]): r["arm_spring_stiffness"] for r in records
           if r.get("suite") == SUITE and "arm_spring_stiffness" in r}  # fmt: skip
    rows = sorted({k[:2] for k in figures["test_torque_r2"]},
                  key=lambda k: (TABLE_ROWS.index(k[0]), k[1]))  # fmt: skip
    head = [
        "MJCF lacks",
        "arm",
        *(f"{m} R²" for m in TABLE_MODELS),
        "arm's own R²",
        "tree_delan M error (%)",
        "springs' torque share",
        "learned / arm's stiffness",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        r2 = [cell(figures["test_torque_r2"].get((*row, m), {}), ".4f") for m in TABLE_MODELS]
        stiffness = "-"
        if row in arm:
            learned = figures["spring_stiffness"].get((*row, "tree_delan"), {})
            stiffness = f"{cell(learned, '.3g')} / {arm[row]:.3g}"
        lines.append("| " + " | ".join([
            *row, *r2, cell(_any_model(figures["truth_torque_r2"], row), ".4f"),
            cell(figures["mass_matrix_error"].get((*row, "tree_delan"), {}), ".2f", 100),
            cell(_any_model(figures["spring_torque_share"], row), ".2f"), stiffness,
        ]) + " |")  # fmt: skip
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="suite own_arm's sample-efficiency figure, or (--table) its table of what "
        "the MJCF lacks"
    )
    parser.add_argument("files", nargs="+", type=Path, help="records of suite own_arm (JSONL)")
    parser.add_argument("--out", type=Path, help="the figure to write (PNG)")
    parser.add_argument("--table", action="store_true",
                        help="print the markdown table of structure records instead")  # fmt: skip
    parser.add_argument("--robot", default="panda", choices=OWN_ARM_ROBOTS)
    parser.add_argument("--friction", default="none", choices=FRICTION_KINDS,
                        help="the arm's joint friction")  # fmt: skip
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    records = read_record_files(args.files)
    if records is None:
        return 2
    if args.table:
        print("\n".join(structure_table(records)))
        return 0
    if args.out is None:
        parser.error("give --out PNG for the figure, or --table")
    curves = sample_curves(records, args.robot, args.friction)
    if not curves:
        files = ", ".join(map(str, args.files))
        stop_line("no records", f"no {SUITE} test_torque_mse records of {args.robot} in {files}")
        return 2
    for line in describe_curves(curves, x="samples"):
        log.info("%s", line)
    with_friction = "" if args.friction == "none" else f" with {args.friction} friction"
    title = f"{args.robot}{with_friction}: held-out torque error"
    figure = plot_error_curves(curves, args.out, title, "training samples",
                               "test torque MSE (N$^2$ m$^2$)", xlog=True)  # fmt: skip
    log.info("figure: %s", figure)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
