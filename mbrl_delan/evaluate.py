"""``python -m mbrl_delan.evaluate RUN_DIR [data=FILE] [out=FILE] [threshold=0.1]``.

A saved model's inverse-dynamics errors on data: a finished ``fit`` run's model, or a
``train`` run's DeLaN (`mbrl_delan.runs.load_run`). Without ``data=`` the fit's own data are
rebuilt from its config and every split evaluated (the figures of its ``summary.json``);
with ``data=FILE`` (`mbrl_delan.data.arrays`' schema, the run's joints) all of the file's
samples form one split, ``data``.

Per split (JSON on stdout, or in ``out=FILE``):

- the errors of ``summary.json`` (`training.inverse_fit.split_summary`): normalised MSE (per-DoF
  torque std of the model's training data; of this data for a train run's DeLaN), MSE in SI
  units, R^2, per DoF group, and per trajectory or clip;
- ``components`` where the data carry the parts of tau (``tau_inertial``, ``tau_coriolis``,
  ``tau_gravity``, ``tau_friction``) and the model has them (DeLaN): ``rel_error`` =
  ||learned - logged||_F / ||logged||_F over the split (None where the logged part is zero),
  and ``mse_si``;
- ``rollout`` (DeLaN, data with times): each trajectory integrated open loop from its first
  state by the learned forward dynamics (RK4, the logged torque held over each sample
  interval); ``rollout_s`` is the time until the position error, the RMS over coordinates of
  (q_model - q_logged) / std(q_logged), first exceeds ``threshold`` (the whole trajectory when
  it never does: ``reached_end``).

Exit codes: 0 done, 2 a missing or malformed run dir, checkpoint or data file (one line
naming it), or a model that does not give torques (a train run's ensemble).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor, nn

from mbrl_delan import keys
from mbrl_delan.data.arrays import COMPONENTS, ArrayFormatError
from mbrl_delan.data.inverse_data import FitSystem, InverseData, array_inverse_data, system_of
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.integrators import integrate
from mbrl_delan.models.inverse import DeLaNInverse, InverseDynamicsModel
from mbrl_delan.models.lagrangian import LagrangianDynamics
from mbrl_delan.provenance import program_name
from mbrl_delan.rules import ConfigError
from mbrl_delan.runs import Run, load_run
from mbrl_delan.stops import stop_line
from mbrl_delan.systems.system import JointLayout
from mbrl_delan.training.checkpoint import (
    CheckpointError,
    RunWriteError,
    atomic_write,
    check_writable,
)
from mbrl_delan.training.inverse_fit import evaluate_torques

log = logging.getLogger("mbrl_delan.evaluate")

# the stop line's kind of each input error of evaluate and rescore, the first that matches
INPUT_ERRORS: tuple[tuple[type[BaseException], str], ...] = (
    (ConfigError, "config error"),
    (ArrayFormatError, "bad data file"),
    (FileNotFoundError, "not found"),
    (CheckpointError, "bad checkpoint"),
    (RunWriteError, "write error"),
    (ValueError, "bad input"),
)


def stop_on_input(err: BaseException) -> int:
    """The stop line of an input error (`INPUT_ERRORS`' kind: the error); exit code 2."""
    kind = next(kind for cls, kind in INPUT_ERRORS if isinstance(err, cls))
    stop_line(kind, err)
    return 2


THRESHOLD = 0.1  # normalised position error that ends an open-loop rollout
OPTIONS = ("data", "out", "threshold", "batch_size")


class TrainDeLaNTorques(InverseDynamicsModel):
    """A train run's DeLaN as an inverse-dynamics model: tau = M qdd + c + g + d, the loss's
    torque scale from the evaluated data (`fit_normalization`)."""

    def __init__(self, delan: DeLaN) -> None:
        super().__init__(delan.layout.nv, 1e-3)
        self.delan = delan

    @property
    def dynamics(self) -> LagrangianDynamics:
        return self.delan.dynamics

    def predict_torque(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        return self.delan.dynamics.inverse_dynamics(q, qd, qdd)  # (..., nv)


def inverse_model(run: Run) -> InverseDynamicsModel:
    """The run's model as an inverse-dynamics model; ValueError for one without torques."""
    if isinstance(run.model, InverseDynamicsModel):
        return run.model
    if isinstance(run.model, DeLaN):
        return TrainDeLaNTorques(run.model).to(next(run.model.parameters()).dtype)
    raise ValueError(
        f"{run.run_dir}: a {type(run.model).__name__} predicts next states, not torques; "
        "evaluate needs a fit run or a train run's DeLaN"
    )


def _dynamics(model: nn.Module) -> LagrangianDynamics | None:
    if isinstance(model, DeLaNInverse | TrainDeLaNTorques):
        return model.dynamics
    return None


def run_system(run: Run) -> FitSystem:
    """The joints the run's model was built on."""
    if run.kind == "fit":
        from mbrl_delan.runs import read_provenance

        return system_of(read_provenance(run.run_dir))
    from mbrl_delan.conf.loop import env_parts

    return FitSystem.of_mjcf(Path(env_parts(run.config).system.xml_path))


# ---------------------------------------------------------------- the figures


@torch.no_grad()
def component_errors(dynamics: LagrangianDynamics, data: TensorDict) -> dict[str, Any]:
    """Learned M qdd, c, g and friction against the data's logged parts of tau (those it
    has)."""
    present = [k for k in COMPONENTS if k in data.keys()]
    if not present:
        return {}
    terms = dynamics.terms(data[keys.Q], data[keys.QD])
    learned = {
        keys.TAU_INERTIAL: (terms.mass_matrix @ data[keys.QDD].unsqueeze(-1)).squeeze(-1),
        keys.TAU_CORIOLIS: terms.coriolis,
        keys.TAU_GRAVITY: terms.gravity,
        keys.TAU_FRICTION: terms.dissipation,
    }
    out = {}
    for name in present:
        diff, norm = learned[name] - data[name], float(data[name].norm())
        out[name] = {  # rel_error: None for a part that is zero (friction-free joints)
            "rel_error": float(diff.norm()) / norm if norm > 0 else None,
            "mse_si": float(diff.pow(2).mean()),
        }
    return out


def rollout_time(
    dynamics: LagrangianDynamics,
    layout: JointLayout,
    data: TensorDict,
    q_std: Tensor,
    threshold: float,
) -> dict[str, Any]:
    """One trajectory (T,) rolled out open loop on its logged torques (module docstring)."""
    t = data[keys.TIME].reshape(-1)
    q, qd = data[keys.Q][:1], data[keys.QD][:1]  # (1, nq), (1, nv)
    for k in range(t.numel() - 1):
        tau = data[keys.TAU][k : k + 1]

        def accel(q_: Tensor, qd_: Tensor, tau: Tensor = tau) -> Tensor:
            return dynamics.forward_dynamics(q_, qd_, tau)

        state = integrate(layout, accel, q, qd, float(t[k + 1] - t[k]), "rk4")
        q, qd = state.q, state.qd
        error = ((q - data[keys.Q][k + 1 : k + 2]) / q_std).pow(2).mean().sqrt()
        if not bool(torch.isfinite(error)) or float(error) > threshold:
            return {"rollout_s": float(t[k + 1] - t[0]), "reached_end": False}
    return {"rollout_s": float(t[-1] - t[0]), "reached_end": True}


@torch.no_grad()
def rollouts(
    dynamics: LagrangianDynamics,
    layout: JointLayout,
    data: TensorDict,
    ids: Tensor,
    names: Sequence[str],
    threshold: float,
) -> dict[str, Any]:
    """`rollout_time` of every trajectory in `data` (N,) with group ids (N,)."""
    if keys.TIME not in data.keys() or not bool(torch.isfinite(data[keys.TIME]).all()):
        return {}
    q_std = data[keys.Q].std(dim=0).clamp_min(1e-6)
    per = {
        names[i]: rollout_time(dynamics, layout, data[ids == i], q_std, threshold)
        for i in ids.unique().tolist()
        if int((ids == i).sum()) > 1
    }
    times = torch.tensor([r["rollout_s"] for r in per.values()])
    return {
        "threshold": threshold,
        "median_rollout_s": float(times.median()) if times.numel() else math.nan,
        "trajectories": per,
    }


def evaluate_data(
    model: InverseDynamicsModel,
    data: InverseData,
    batch_size: int = 2048,
    threshold: float = THRESHOLD,
) -> dict[str, Any]:
    """Every non-empty split's errors (module docstring)."""
    from mbrl_delan.training.inverse_fit import group_errors, split_summary

    model.eval()
    dtype = next(model.parameters()).dtype
    dynamics = _dynamics(model)
    out: dict[str, Any] = {}
    for name, part in data.splits.items():
        if part.shape[0] == 0:
            continue
        part = part.to(dtype)
        errors = evaluate_torques(model, part, batch_size)
        summary = split_summary(errors, data.system.dof_groups)
        ids = data.groups[name]
        summary[data.group_kind] = group_errors(model, part, ids, data.group_names, batch_size)
        if dynamics is not None:
            summary["components"] = component_errors(dynamics, part)
            summary["rollout"] = rollouts(
                dynamics, data.system.layout, part, ids, data.group_names, threshold
            )
        out[name] = summary
    return out


def evaluate_run(
    run_dir: str | Path,
    data: str | Path | None = None,
    batch_size: int = 2048,
    threshold: float = THRESHOLD,
) -> dict[str, Any]:
    """A run's model on `data` (a file), or on its own data when None. Raises
    FileNotFoundError, ArrayFormatError and ValueError (a model without torques)."""
    run = load_run(run_dir)
    model = inverse_model(run)
    if data is None:
        if run.kind != "fit":
            raise ValueError(f"{run.run_dir} is a train run: give data=FILE")
        from mbrl_delan.conf.fitting import inverse_data as read_data

        inverse_data = read_data(run.config.data)
    else:
        inverse_data = _file_data(run, Path(data))
    if isinstance(model, TrainDeLaNTorques):
        model.fit_normalization(next(iter(inverse_data.splits.values())))
    splits = evaluate_data(model, inverse_data, batch_size, threshold)
    return {
        "run": str(run.run_dir),
        "kind": run.kind,
        "data": str(data or "the run's own"),
        "splits": splits,
    }


def _file_data(run: Run, path: Path) -> InverseData:
    """All samples of a file as the one split ``data``, on the run's joints."""
    loaded = array_inverse_data(path, run_system(run), val_fraction=0.0, test_fraction=0.0)
    return InverseData(
        splits={"data": loaded.splits["train"]},
        groups={"data": loaded.groups["train"]},
        group_names=loaded.group_names,
        group_kind=loaded.group_kind,
        system=loaded.system,
        provenance=loaded.provenance,
    )


def key_value_option(options: Sequence[str]) -> Callable[[str], tuple[str, str]]:
    """An argparse type for ``key=value`` options with a key in `options`: a bad one exits 2
    naming them."""

    def option(text: str) -> tuple[str, str]:
        key, sep, value = text.partition("=")
        if not sep or key not in options:
            known = ", ".join(k + "=" for k in options)
            raise argparse.ArgumentTypeError(f"{text!r} is not an option; the options are {known}")
        return key, value

    return option


_option = key_value_option(OPTIONS)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=program_name("mbrl_delan.evaluate"),
        description="A saved fit's (or train run's DeLaN's) inverse-dynamics errors on data.",
    )
    p.add_argument("run_dir", type=Path, help="a run dir of mbrl_delan.fit or mbrl_delan.train")
    p.add_argument(
        "options",
        nargs="*",
        type=_option,
        help="data=FILE (default: the fit's own data), out=FILE (default: stdout), "
        f"threshold=X (default {THRESHOLD}), batch_size=N (default 2048)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """The command line (module docstring); the exit code."""
    args = parser().parse_args(argv)
    options = dict(args.options)
    run_dir = args.run_dir
    logging.basicConfig(level=logging.INFO, format="[%(name)s][%(levelname)s] - %(message)s")
    out = Path(options["out"]) if "out" in options else None
    try:
        threshold = float(options.get("threshold", THRESHOLD))
        batch_size = int(options.get("batch_size", 2048))
        if not threshold > 0 or batch_size < 1:
            raise ValueError(f"need threshold > 0 and batch_size >= 1: {threshold}, {batch_size}")
        if out is not None:
            check_writable(out.parent)  # before the work: an unwritable out= fails at once
        result = evaluate_run(run_dir, options.get("data"), batch_size, threshold)
    except (FileNotFoundError, ValueError, CheckpointError, RunWriteError) as err:
        return stop_on_input(err)  # the data, run, checkpoint or out= file named
    for name, split in result["splits"].items():
        rollout = split.get("rollout", {}).get("median_rollout_s")
        log.info(
            "%s: MSE %.4g (normalised), %.4g (SI), R2 %.4f, %d samples%s",
            name,
            split["mse"],
            split["mse_si"],
            split["r2"],
            split["n"],
            f", median open-loop rollout {rollout:.3g} s" if rollout is not None else "",
        )
    text = json.dumps(result, indent=1)
    if out is None:
        print(text)
        return 0
    try:
        atomic_write(out, lambda f: f.write(text.encode("utf-8")), keep_prev=False)
    except RunWriteError as err:
        return stop_on_input(err)
    return 0


if __name__ == "__main__":
    sys.exit(main())
