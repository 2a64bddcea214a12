"""`load_run(run_dir)`: the trained model and config of any finished ``fit`` or ``train`` run.

A ``fit`` run (``python -m mbrl_delan.fit``) holds ``model.pt``: its inverse-dynamics model
(`mbrl_delan.models.inverse`). A ``train`` run (``python -m mbrl_delan.train``) holds
``checkpoint.pt``: its world model (a `DeLaN` or an ensemble) as of the last checkpoint.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn

from mbrl_delan.conf.checks import migrate
from mbrl_delan.training.checkpoint import CHECKPOINT_FILE, load_checkpoint
from mbrl_delan.training.recorder import RUN_CONFIG, SUMMARY_FILE, WEIGHTS_FILE

FIT_MODEL_FILE = "model.pt"  # `mbrl_delan.conf.fitting.MODEL_FILE`


@dataclass
class Run:
    """A finished run: ``kind`` is ``"fit"`` or ``"train"``; ``summary`` is None when the run
    wrote none (stopped before its end)."""

    kind: str
    run_dir: Path
    config: DictConfig
    model: nn.Module
    summary: dict[str, Any] | None


def load_run(run_dir: str | Path) -> Run:
    """The config and trained model (on the CPU, in the run's dtype, in evaluation mode) of
    a fit or train run; the modules of the run's ``plugins`` are imported first (its own env,
    model).

    Raises FileNotFoundError when `run_dir` holds neither a fit's ``model.pt`` nor a train
    run's ``config.yaml`` with its ``checkpoint.pt`` or its final weights ``world_model.pt``
    (a record folder)."""
    run_dir = Path(run_dir)
    summary_path = run_dir / SUMMARY_FILE
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else None
    if (run_dir / FIT_MODEL_FILE).is_file():
        from mbrl_delan.conf.fitting import load_fit_model

        cfg, model = load_fit_model(run_dir)
        return Run("fit", run_dir, cfg, model.eval(), summary)
    weights = [run_dir / f for f in (CHECKPOINT_FILE, WEIGHTS_FILE) if (run_dir / f).is_file()]
    if (run_dir / RUN_CONFIG).is_file() and weights:
        return Run("train", run_dir, *_train_model(run_dir, weights[0]), summary)
    raise FileNotFoundError(
        f"{run_dir} is not a finished run: it holds neither {FIT_MODEL_FILE} (fit) nor "
        f"{RUN_CONFIG} and {CHECKPOINT_FILE} or {WEIGHTS_FILE} (train)"
    )


def _train_model(run_dir: Path, weights: Path) -> tuple[DictConfig, nn.Module]:
    """A train run's config and its world model with the weights of its checkpoint or its
    `WEIGHTS_FILE`."""
    from mbrl_delan.conf.checks import DTYPES, load_config_plugins
    from mbrl_delan.conf.loop import build_world_model, env_parts

    cfg = migrate(OmegaConf.load(run_dir / RUN_CONFIG))  # a run saved before newer keys too
    load_config_plugins(cfg)  # a plugin's env or model, as the run had it
    system = env_parts(cfg).system
    model = build_world_model(cfg, system, torch.device("cpu"), DTYPES[cfg.dtype])
    state = load_checkpoint(weights)  # tensors and plain containers only
    model.load_state_dict(state["loop"]["model"] if weights.name == CHECKPOINT_FILE else state)
    return cfg, model.eval()


# what a run's oracle and zero-torque episodes depend on: another run that agrees on these
# met the same starts with the same planner (`oracle_of_run`)
ORACLE_KEYS = ("env", "planner", "seed", "dtype", "budget.oracle_planner",
               "budget.oracle_episodes", "budget.final_eval_episodes", "budget.paired")  # fmt: skip
# env keys that are only defaults of other groups: the planner's and the budget's are compared
# where they land (`planner`, `budget.*`), the models' do not touch the oracle
OTHER_GROUPS_ENV_KEYS = ("horizon", "random_episodes", "iterations", "env_steps", "eval_every",
                         "eval_episodes", "final_eval_episodes", "paired_eval", "plan_knots",
                         "plan_interpolation", "oracle_planner")  # fmt: skip


def _oracle_part(key: str, node: DictConfig) -> dict[str, Any]:
    """What of group `key`'s config the oracle's episodes depend on: all of it, but of `env`
    not the defaults it gives the other groups (`OTHER_GROUPS_ENV_KEYS`, `model_*`, `mppi_*`)."""
    values = OmegaConf.to_container(node, resolve=True)
    if key != "env":
        return values
    return {k: v for k, v in values.items() if k not in OTHER_GROUPS_ENV_KEYS
            and not k.startswith(("model_", "mppi_"))}  # fmt: skip


@dataclass
class OracleEpisodes:
    """A train run's oracle evaluation (returns and control steps per episode, its fidelity
    reference's state) and its zero-torque returns, as its checkpoint holds them."""

    returns: list[float]
    steps: list[int] | None
    zero_returns: list[float]
    fidelity_reference: dict[str, Any] | None


def oracle_of_run(run_dir: str | Path, cfg: DictConfig) -> OracleEpisodes:
    """The oracle and zero-torque episodes of the train run in `run_dir`, for a run of config
    `cfg` that would evaluate the same ones (`ORACLE_KEYS` equal).

    Raises FileNotFoundError without the run's config or checkpoint, ValueError naming the
    first key whose value differs or when the run has not evaluated both yet."""
    run_dir = Path(run_dir)
    config_path, checkpoint_path = run_dir / RUN_CONFIG, run_dir / CHECKPOINT_FILE
    for path in (config_path, checkpoint_path):
        if not path.is_file():
            raise FileNotFoundError(f"budget.oracle_from: {path} does not exist")
    source = migrate(OmegaConf.load(config_path))
    for key in ORACLE_KEYS:
        theirs, ours = OmegaConf.select(source, key), OmegaConf.select(cfg, key)
        if isinstance(ours, DictConfig):
            theirs, ours = (_oracle_part(key, c) for c in (theirs, ours))
        if theirs != ours:
            raise ValueError(
                f"budget.oracle_from={run_dir}: its {key} is {theirs!r}, this run's {ours!r}"
            )
    state = load_checkpoint(checkpoint_path, weights_only=False)
    zero = state["loop"].get("zero_returns")
    if state.get("oracle_returns") is None or zero is None:
        raise ValueError(f"budget.oracle_from={run_dir}: its oracle has not been evaluated yet")
    return OracleEpisodes(state["oracle_returns"], state.get("oracle_steps"), zero,
                          state["loop"].get("fidelity_reference"))  # fmt: skip
