"""`load_run(run_dir)`: the trained model and config of any finished ``fit`` or ``train`` run.

A ``fit`` run (``python -m mbrl_delan.fit``) holds ``model.pt``: its inverse-dynamics model
(`mbrl_delan.models.inverse`). A ``train`` run (``python -m mbrl_delan.train``) holds
``checkpoint.pt``: its world model (a `DeLaN` or an ensemble) as of the last checkpoint.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn

from mbrl_delan.conf.checks import DTYPES, load_config_plugins, migrate
from mbrl_delan.conf.fitting import build_system_model
from mbrl_delan.data.inverse_data import system_of
from mbrl_delan.models.inverse import InverseDynamicsModel
from mbrl_delan.training.checkpoint import CHECKPOINT_FILE, load_checkpoint
from mbrl_delan.training.inverse_fit import MODEL_FILE, PROVENANCE_FILE, read_fit_run
from mbrl_delan.training.recorder import RUN_CONFIG, SUMMARY_FILE, WEIGHTS_FILE


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
    if (run_dir / MODEL_FILE).is_file():
        cfg, model = load_fit_model(run_dir)
        return Run("fit", run_dir, cfg, model.eval(), summary)
    weights = [run_dir / f for f in (CHECKPOINT_FILE, WEIGHTS_FILE) if (run_dir / f).is_file()]
    if (run_dir / RUN_CONFIG).is_file() and weights:
        return Run("train", run_dir, *_train_model(run_dir, weights[0]), summary)
    raise FileNotFoundError(
        f"{run_dir} is not a finished run: it holds neither {MODEL_FILE} (fit) nor "
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
    reference's state) and its zero-torque returns, as its checkpoint holds them, and the
    oracle's planning time (`Evaluation.planning_figures`, {} where it was not timed)."""

    returns: list[float]
    steps: list[int] | None
    zero_returns: list[float]
    fidelity_reference: dict[str, Any] | None
    planning: dict[str, float] = field(default_factory=dict)


ORACLE_FILE = "oracle.json"  # a train run's oracle and zero-torque episodes, on their own
ORACLE_REFERENCE_FILE = "oracle_reference.pt"  # ... and its fidelity reference, where it has one


def oracle_config(cfg: DictConfig) -> dict[str, Any]:
    """What of `cfg` a run's oracle episodes depend on (`ORACLE_KEYS`), as plain values."""
    values = {}
    for key in ORACLE_KEYS:
        value = OmegaConf.select(cfg, key)
        values[key] = _oracle_part(key, value) if isinstance(value, DictConfig) else value
    return values


def write_oracle(run_dir: Path, cfg: DictConfig, episodes: OracleEpisodes,
                 stamp: dict[str, Any]) -> None:  # fmt: skip
    """`ORACLE_FILE` (and `ORACLE_REFERENCE_FILE`) in `run_dir`: the episodes with the config
    they were evaluated under and `stamp` (the command, commit and host), so that a folder of
    these alone is a `budget.oracle_from` for every model's paired run of that config (kept
    under ``docs/records/oracles/<env>/<preset>_s<seed>/``)."""
    limit = OmegaConf.select(cfg, "env.episode_len")
    record = {
        "config": oracle_config(cfg),
        "returns": list(episodes.returns),
        "steps": None if episodes.steps is None else list(episodes.steps),
        "falls": None
        if episodes.steps is None or limit is None
        else sum(s < limit for s in episodes.steps),
        "zero_returns": list(episodes.zero_returns),
        "planning": dict(episodes.planning),
        **{k: stamp.get(k) for k in ("command", "git_commit", "dirty", "host")},
    }
    text = json.dumps(record, indent=1) + "\n"
    (run_dir / ORACLE_FILE).write_text(text, encoding="utf-8")
    if episodes.fidelity_reference is not None:
        torch.save(episodes.fidelity_reference, run_dir / ORACLE_REFERENCE_FILE)


def oracle_of_run(run_dir: str | Path, cfg: DictConfig) -> OracleEpisodes:
    """The oracle and zero-torque episodes of the train run in `run_dir` (its `ORACLE_FILE`,
    else its checkpoint), for a run of config `cfg` that would evaluate the same ones
    (`ORACLE_KEYS` equal).

    Raises FileNotFoundError without them, ValueError naming the first key whose value
    differs or when the run has not evaluated both yet."""
    run_dir = Path(run_dir)
    if (run_dir / ORACLE_FILE).is_file():
        return _oracle_of_record(run_dir, cfg)
    config_path, checkpoint_path = run_dir / RUN_CONFIG, run_dir / CHECKPOINT_FILE
    for path in (config_path, checkpoint_path):
        if not path.is_file():
            raise FileNotFoundError(
                f"budget.oracle_from: {path} does not exist (nor {run_dir / ORACLE_FILE})"
            )
    _same_oracle(run_dir, oracle_config(migrate(OmegaConf.load(config_path))), cfg)
    state = load_checkpoint(checkpoint_path, weights_only=False)
    zero = state["loop"].get("zero_returns")
    if state.get("oracle_returns") is None or zero is None:
        raise ValueError(f"budget.oracle_from={run_dir}: its oracle has not been evaluated yet")
    return OracleEpisodes(state["oracle_returns"], state.get("oracle_steps"), zero,
                          state["loop"].get("fidelity_reference"),
                          state["loop"].get("oracle_planning") or {})  # fmt: skip


def _oracle_of_record(run_dir: Path, cfg: DictConfig) -> OracleEpisodes:
    try:
        record = json.loads((run_dir / ORACLE_FILE).read_text(encoding="utf-8"))
        theirs, returns, zero = record["config"], record["returns"], record["zero_returns"]
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(
            f"budget.oracle_from: {run_dir / ORACLE_FILE} is malformed ({err})"
        ) from err
    _same_oracle(run_dir, theirs, cfg)
    reference = run_dir / ORACLE_REFERENCE_FILE
    state = torch.load(reference, weights_only=False) if reference.is_file() else None
    return OracleEpisodes(returns, record.get("steps"), zero, state, record.get("planning") or {})


def _same_oracle(run_dir: Path, theirs: dict[str, Any], cfg: DictConfig) -> None:
    ours = oracle_config(cfg)
    for key in ORACLE_KEYS:
        if theirs.get(key) != ours[key]:
            raise ValueError(
                f"budget.oracle_from={run_dir}: its {key} is {theirs.get(key)!r}, this run's "
                f"{ours[key]!r}"
            )


def load_fit_model(run_dir: str | Path) -> tuple[DictConfig, InverseDynamicsModel]:
    """A finished fit's config and its trained model (on the CPU, in the fit's dtype), built
    on the system its data name (the MJCF's tree and armature, or the joint list), once the
    run's ``plugins`` are loaded (a plugin's model)."""
    cfg, state = read_fit_run(run_dir)
    load_config_plugins(cfg)
    model = build_system_model(cfg, system_of(read_provenance(run_dir)))
    model = model.to(DTYPES[cfg.get("dtype", "float32")])
    model.load_state_dict(state)
    return cfg, model


def read_provenance(run_dir: str | Path) -> dict[str, Any]:
    """A fit's ``dataset_provenance.json`` ({} when it has none)."""
    path = Path(run_dir) / PROVENANCE_FILE
    return json.loads(path.read_text()) if path.is_file() else {}
