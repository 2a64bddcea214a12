"""Suite `fit_arrays`: ``python -m mbrl_delan.fit data=arrays`` at its defaults on arms.

For arm2 and arm3 (`mbrl_delan/systems/assets/`, their joints' damping removed: frictionless
arms): 22 smooth random trajectories of 160 control steps (4 s) each, tracked in MuJoCo by PD
control (`mbrl_delan.data.synthetic.trajectory_dataset`), written to an ``.npz`` file; the fit's
split holds out 4 whole trajectories for test and a 10% segment of each other one for
validation (2,592 training samples). Fitted
at the defaults with no other flag (`mbrl_delan.fit.fit_inverse_dynamics`): DeLaN and the
MLP; beside them, the identify suite's model and recipe (`benchmarks.identify`: a plain
DeLaN, hidden 64, float64, its own 10% validation split) on the same training and validation
trajectories. On the test trajectories (case ``<system>_<setting>``, setting ``delan``,
``mlp`` or ``identify``):

- ``test_torque_mse_si``: mean over samples and DoFs of (tau_hat - tau)^2, N^2 m^2;
- ``mass_matrix_rel_error_median`` (DeLaN settings): median over the test samples of
  ||M_learned(q) - M(q)||_F / ||M(q)||_F, M from `mj_fullM`;
- ``mse_ratio_to_identify`` (delan, mlp): the setting's test MSE / the identify recipe's;
- ``friction_torque_share`` (delan): RMS over the test samples of DeLaN's friction torque /
  RMS of the test torques (the arms have none: the share is what DeLaN learned in error);
- ``fit_s``: wall time of the fit.

``seed=N`` (the bench option) seeds the fits' weights and minibatches; the data stay the same.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.benchmarks import BenchSettings, host_fields
from mbrl_delan.benchmarks.figures import read_record_files
from mbrl_delan.benchmarks.identify import IdentifyConfig, fit_identification, make_model
from mbrl_delan.benchmarks.own_arm import friction_torque_share
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import FitArraysSuiteConfig
from mbrl_delan.data.arrays import save_arrays
from mbrl_delan.data.inverse_data import FitSystem, array_inverse_data
from mbrl_delan.data.synthetic import reference_terms, trajectory_dataset
from mbrl_delan.fit_run import fit_inverse_dynamics
from mbrl_delan.systems.system import System, load_system
from mbrl_delan.training.inverse_fit import evaluate_torques

log = logging.getLogger(__name__)

SUITE = "fit_arrays"
SYSTEMS = ("arm2", "arm3")
NOT_METRICS = ("epochs", "stopping")  # a setting's fields beside its figures


def stopping(cfg: Any) -> dict[str, Any]:
    """What ends a fit of config `cfg`: its thresholds, patience and validation split."""
    return {"patience": cfg.patience, "min_delta": cfg.min_delta,
            "min_rel_delta": cfg.min_rel_delta, "val_by": cfg.data.split.val_by}  # fmt: skip


@dataclass(frozen=True)
class FitArraysConfig:
    """Sizes: trajectories x steps per system, generated with `seed`; the fits' weights and
    minibatches from `fit_seed`; `overrides` go to every fit (quick: epochs); with
    `torque_noise`, the torques carry Gaussian measurement noise of that share of each
    joint's RMS (seeded by `seed` + 1), the noise-free ones kept for `truth_torque_mse_si`."""

    trajectories: int = 22
    steps: int = 160
    seed: int = 0
    fit_seed: int = 0
    systems: tuple[str, ...] = SYSTEMS
    overrides: tuple[str, ...] = ()
    identify: IdentifyConfig = IdentifyConfig()
    torque_noise: float = 0.0  # measurement noise on every torque: this share of its joint's RMS

    @classmethod
    def quick(cls) -> FitArraysConfig:
        return cls(
            trajectories=6,
            steps=20,
            systems=("arm2",),
            overrides=("epochs=2",),
            identify=IdentifyConfig.quick(),
        )


def _mass_matrix_error(model: Any, system: System, q: torch.Tensor) -> float:
    """Median relative Frobenius error of a DeLaN's M against `mj_fullM` at q (N, nq) of
    hinge joints (nq = nv)."""
    reference = reference_terms(system, q).mass_matrix
    q = q.to(next(model.parameters()).dtype)
    with torch.no_grad():
        learned = model.dynamics.terms(q, torch.zeros_like(q)).mass_matrix.double()
    error = (learned - reference).norm(dim=(-2, -1)) / reference.norm(dim=(-2, -1))
    return float(error.median())


def _identify_fit(system: System, data: Any, cfg: IdentifyConfig) -> tuple[Any, float]:
    """The identify suite's DeLaN and recipe on the fit's training and validation samples."""
    train = torch.cat([data.splits["train"], data.splits["val"]]).select(
        keys.Q, keys.QD, keys.QDD, keys.TAU
    )
    train[keys.ACTION] = torch.linalg.solve(  # tau = B a
        system.actuation.to(torch.float64), train[keys.TAU].T
    ).T
    model = make_model(system, cfg)
    start = time.perf_counter()
    fit = fit_identification(model, train.to(cfg.dtype), cfg)
    return fit.model, time.perf_counter() - start


def _test_mse(predict: Any, test: TensorDict) -> float:
    with torch.no_grad():
        tau_hat = predict(test[keys.Q], test[keys.QD], test[keys.QDD])
    return float((tau_hat.double() - test[keys.TAU]).pow(2).mean())


def _with_torque_noise(data: TensorDict, share: float, seed: int) -> TensorDict:
    """`data` with its torques plus N(0, (share x each joint's RMS)^2) noise."""
    tau = data[keys.TAU]
    noise = torch.randn(tau.shape, generator=torch.Generator().manual_seed(seed), dtype=tau.dtype)
    noisy = data.clone()
    noisy[keys.TAU] = tau + share * tau.pow(2).mean(0).sqrt() * noise
    return noisy


def run_system(name: str, cfg: FitArraysConfig, folder: Path) -> Iterator[BenchRecord]:
    system = load_system(name)
    clean = trajectory_dataset(
        system, cfg.trajectories, cfg.steps, torch.Generator().manual_seed(cfg.seed),
        damping=False,
    )  # fmt: skip
    noisy = cfg.torque_noise > 0
    data = _with_torque_noise(clean, cfg.torque_noise, cfg.seed + 1) if noisy else clean
    path = save_arrays(data, folder / f"{name}.npz")
    split = array_inverse_data(path, FitSystem.of(name))
    test = split.splits["test"]
    truth = (
        array_inverse_data(save_arrays(clean, folder / f"{name}_clean.npz"), FitSystem.of(name))
        .splits["test"] if noisy else test
    )  # fmt: skip
    host = host_fields(torch.device("cpu"))
    samples = {k: int(v.shape[0]) for k, v in split.splits.items()}
    fields = dict(system=name, samples=samples, data_seed=cfg.seed, fit_seed=cfg.fit_seed,
                  overrides=list(cfg.overrides), torque_noise=cfg.torque_noise)  # fmt: skip
    results: dict[str, dict[str, float]] = {}
    for model_name in ("delan", "mlp"):
        start = time.perf_counter()
        overrides = [f"seed={cfg.fit_seed}", *cfg.overrides]
        result = fit_inverse_dynamics(
            path, name, folder / f"{name}_{model_name}", model_name, overrides
        )
        figures = {
            "test_torque_mse_si": result.summary["final"]["test"]["mse_si"],
            "fit_s": time.perf_counter() - start,
        }
        if noisy:
            dtype = next(result.model.parameters()).dtype
            figures["truth_torque_mse_si"] = evaluate_torques(result.model, truth.to(dtype)).mse_si
        if model_name == "delan":
            figures["mass_matrix_rel_error_median"] = _mass_matrix_error(
                result.model, system, test[keys.Q]
            )
            figures["friction_torque_share"] = friction_torque_share(result.model, test)
        results[model_name] = figures | {
            "epochs": result.summary["epochs"],
            "stopping": stopping(result.config),
        }
    identify_cfg = replace(cfg.identify, seed=cfg.fit_seed)
    model, seconds = _identify_fit(system, split, identify_cfg)
    results["identify"] = {
        "test_torque_mse_si": _test_mse(model.dynamics.inverse_dynamics, test),
        **(
            {"truth_torque_mse_si": _test_mse(model.dynamics.inverse_dynamics, truth)}
            if noisy
            else {}
        ),  # fmt: skip
        "mass_matrix_rel_error_median": _mass_matrix_error(model, system, test[keys.Q]),
        "fit_s": seconds,
    }
    best = results["identify"]["test_torque_mse_si"]
    for setting in ("delan", "mlp"):
        results[setting]["mse_ratio_to_identify"] = results[setting]["test_torque_mse_si"] / best
    units = {"test_torque_mse_si": "N^2 m^2", "truth_torque_mse_si": "N^2 m^2", "fit_s": "s"}
    for setting, figures in results.items():
        extra = {k: v for k, v in figures.items() if k in NOT_METRICS}
        for metric, value in figures.items():
            if metric in NOT_METRICS:
                continue
            log.info("%s %s: %s = %.4g", name, setting, metric, value)
            yield BenchRecord(
                SUITE,
                f"{name}_{setting}",
                metric,
                value,
                units.get(metric, "fraction"),
                "cpu",
                dict(fields, setting=setting, **extra, **host),
            )


def _mse_cell(row: dict[Any, Any], setting: str) -> str:
    value, epochs = row.get((setting, "test_torque_mse_si")), row.get((setting, "epochs"))
    text = "-" if value is None else f"{value:.3g}"
    return text if epochs is None else f"{text} ({epochs})"


def _rule(stopping: dict[str, Any]) -> str:
    return f"min_delta {stopping['min_delta']:g}, min_rel_delta {stopping['min_rel_delta']:g}"


def results_table(records: list[dict[str, Any]]) -> list[str]:
    """The suite's markdown table: per arm, run (its `overrides`) and seed, DeLaN's stopping
    rule, the test torque MSE of DeLaN and the MLP (with their epochs) and of the identify
    recipe, DeLaN's M error and its fit's time."""
    rows: dict[tuple, dict[Any, Any]] = {}
    for r in records:
        if r.get("suite") != SUITE:
            continue
        row = rows.setdefault((r["system"], tuple(r.get("overrides") or ()), r["fit_seed"]), {})
        row[(r["setting"], r["metric"])] = r["value"]
        row[(r["setting"], "epochs")] = r.get("epochs")
        if r["setting"] == "delan" and r.get("stopping"):
            row["rule"] = _rule(r["stopping"])
    head = ["arm", "DeLaN's stopping rule", "seed", "DeLaN test MSE (epochs)", "MLP (epochs)",
            "identify", "DeLaN M error", "DeLaN fit"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (arm, _, seed), row in sorted(rows.items()):
        error = row.get(("delan", "mass_matrix_rel_error_median"))
        seconds = row.get(("delan", "fit_s"))
        cells = [arm, row.get("rule", "-"), str(seed), _mse_cell(row, "delan"),
                 _mse_cell(row, "mlp"), _mse_cell(row, "identify"),
                 "-" if error is None else f"{100 * error:.2f}%",
                 "-" if seconds is None else f"{seconds:.0f} s"]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def run_fit_arrays(cfg: FitArraysConfig) -> Iterator[BenchRecord]:
    with tempfile.TemporaryDirectory() as tmp:
        for name in cfg.systems:
            yield from run_system(name, cfg, Path(tmp))


def run_fit_arrays_suite(
    options: FitArraysSuiteConfig, bench: BenchSettings
) -> Iterator[BenchRecord]:
    """The registered suite, on the CPU (`FitArraysConfig.quick` under `bench.quick`); the
    fits' seed from the options' `seed` (the data stay those of seed 0), their `overrides`
    added to every fit's."""
    cfg = FitArraysConfig.quick() if bench.quick else FitArraysConfig()
    overrides = (*cfg.overrides, *options.overrides)
    cfg = replace(cfg, fit_seed=options.seed or 0, overrides=overrides,
                  torque_noise=options.torque_noise,
                  systems=tuple(options.systems or cfg.systems))  # fmt: skip
    yield from run_fit_arrays(cfg)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="suite fit_arrays' table, from its records")
    parser.add_argument("files", nargs="+", type=Path, help="records of suite fit_arrays (JSONL)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    records = read_record_files(args.files)
    if records is None:
        return 2
    print("\n".join(results_table(records)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
