"""``python -m mbrl_delan.rescore RUN_DIR [episodes=N] [body=] [springs=] [samples=N] [out=]``.

A finished train run's paired final evaluation, again, from its record: its config, its
final weights (``world_model.pt``, else the checkpoint's) and the oracle's episodes of its
last paired evaluation in ``metrics.jsonl``. The model's planner meets the same starts with
the same planner seeds, so ``body=fitted`` (the default) repeats the recorded episodes, and
``body=mjcf`` puts the MJCF's own inertias, damping and armature under a tree model
(`model=tree`, `tree_delan`) and keeps the rest of the fit (contact law, joint limits,
springs, residual, scales): what the fitted rigid body costs the plans. ``springs=env`` puts
the env's own joint springs (its physics' MJCF: on `humanoid_stand_exo` the exoskeleton's)
in a tree model's tree and zeroes the residual's quadratic potential (`model.spring_potential`;
its network kept): what the learned springs cost the plans. ``samples=N`` plans the model's
episodes with N samples per iteration (`planner.num_samples`) against the recorded oracle's:
how much of the gap a wider search closes.

JSON on stdout, or in ``out=FILE``: `paired_episodes`, `falls`, `oracle_falls`, `both_stood`,
`standing_return_ratio` (as the run's summary), the episodes' `returns` and `steps`, the
record's own `recorded_steps`, `body`, `springs` and `num_samples`; `command`, `git_commit`,
`dirty` and `host` as every record has them.

Exit codes: 0 done, 2 a folder that is not a finished paired run (one line naming what it
lacks), a bad option, or ``body=mjcf`` or ``springs=env`` on a model without a tree.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from mbrl_delan.conf.checks import DTYPES, ConfigError
from mbrl_delan.conf.loop import build_loop, build_world_model, env_parts
from mbrl_delan.evaluate import key_value_option, stop_on_input
from mbrl_delan.models.tree import RigidBodyTree
from mbrl_delan.provenance import program_name, provenance
from mbrl_delan.runs import load_run
from mbrl_delan.training.checkpoint import CheckpointError, RunWriteError, atomic_write
from mbrl_delan.training.loop import MBRLLoop
from mbrl_delan.training.recorder import METRICS_FILE, read_metrics

log = logging.getLogger("mbrl_delan.rescore")

BODIES = ("fitted", "mjcf")
SPRINGS = ("fitted", "env")
RIGID_BODY = ("raw_inertia", "raw_damping", "raw_armature", "start_factor")  # the tree's
TREE_SPRINGS = {False: ("stiffness", "spring_ref"), True: ("raw_stiffness", "spring_ref")}
QUADRATIC = ("field.spring_stiffness", "field.spring_offset")  # the residual's potential
OPTIONS = ("episodes", "body", "springs", "samples", "out")
TREE_MODELS = ("tree", "tree_delan")


def recorded_evaluation(run_dir: Path) -> dict[str, Any]:
    """The last record of `run_dir`'s ``metrics.jsonl`` with the oracle's paired episodes;
    FileNotFoundError without one."""
    records = [r for r in read_metrics(run_dir / METRICS_FILE) if "oracle_episode_steps" in r]
    if not records:
        raise FileNotFoundError(
            f"{run_dir / METRICS_FILE} holds no paired final evaluation (oracle_episode_steps): "
            "only a finished run with budget.paired=true can be re-scored"
        )
    return records[-1]


def mjcf_body(cfg: DictConfig, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """`state` with its tree's inertias, damping and armature replaced by the MJCF's own;
    a ValueError for a model without a tree."""
    _need_tree(cfg, "body=mjcf")
    exact_cfg = cfg.copy()
    exact_cfg.model.start = "mjcf"
    exact = build_world_model(exact_cfg, env_parts(exact_cfg).system, torch.device("cpu"),
                              DTYPES[cfg.dtype]).state_dict()  # fmt: skip
    return state | {f"dynamics.tree.{k}": exact[f"dynamics.tree.{k}"] for k in RIGID_BODY}


def env_springs(cfg: DictConfig, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """`state` with its tree's springs the env's own (stiffness and rest of each DoF in the
    env's physics MJCF) and the residual's quadratic potential zeroed; a ValueError for a
    model without a tree."""
    _need_tree(cfg, "springs=env")
    learned = bool(cfg.model.get("learn_springs", False))
    physics = env_parts(cfg).physics.mj_model()
    own = RigidBodyTree.from_mujoco(physics, learn_springs=learned).state_dict()
    swapped = {f"dynamics.tree.{k}": own[k] for k in TREE_SPRINGS[learned]}
    zeroed = {k: torch.zeros_like(v) for k, v in state.items() if k.endswith(QUADRATIC)}
    return state | swapped | zeroed


def _need_tree(cfg: DictConfig, option: str) -> None:
    """A ValueError naming `option` unless the run's model has a tree."""
    if cfg.model.name not in TREE_MODELS:
        raise ValueError(f"{option} needs a tree model (model=tree, tree_delan): {cfg.model.name}")


def rescore(
    run_dir: Path, episodes: int | None = None, body: str = "fitted", springs: str = "fitted",
    samples: int | None = None,
) -> dict[str, Any]:  # fmt: skip
    """The paired figures of `run_dir`'s final model on its recorded starts (module
    docstring); `episodes` None: as many as the record holds; `samples` None: the run's."""
    if body not in BODIES:
        raise ValueError(f"body={body!r}: one of {', '.join(BODIES)}")
    if springs not in SPRINGS:
        raise ValueError(f"springs={springs!r}: one of {', '.join(SPRINGS)}")
    record = recorded_evaluation(run_dir)
    run = load_run(run_dir)  # its config (migrated) and final weights
    cfg = run.config
    n = len(record["oracle_episode_steps"]) if episodes is None else episodes
    if not 0 < n <= len(record["oracle_episode_steps"]):
        raise ValueError(f"episodes={n}: the record holds {len(record['oracle_episode_steps'])}")
    state = run.model.state_dict()
    if body == "mjcf":
        state = mjcf_body(cfg, state)
    if springs == "env":
        state = env_springs(cfg, state)
    if samples is not None:
        cfg.planner.num_samples = samples
    with tempfile.TemporaryDirectory() as scratch:  # the loop's buffer, never written here
        loop, _ = build_loop(cfg, Path(scratch))
        loop.model.load_state_dict(state)
        options = {"body": body, "springs": springs, "num_samples": cfg.planner.num_samples}
        return _paired(loop, record, n) | options | {"run": str(run_dir)}


def _paired(loop: MBRLLoop, record: dict[str, Any], n: int) -> dict[str, Any]:
    """`n` paired episodes of the loop's planner against the record's oracle episodes."""
    loop.oracle_returns = record["oracle_episode_returns"][:n]
    loop.oracle_steps = record["oracle_episode_steps"][:n]
    ev = loop.evaluate(loop.policy, n, paired=True)
    figures = loop.paired_figures(ev)
    return figures | {"returns": ev.returns, "steps": ev.steps,
                      "recorded_steps": record.get("eval_episode_steps", [])[:n]}  # fmt: skip


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=program_name("mbrl_delan.rescore"),
        description="A finished train run's paired final evaluation, again, from its record.",
    )
    p.add_argument("run_dir", type=Path, help="a finished train run's folder or record folder")
    p.add_argument(
        "options", nargs="*", type=key_value_option(OPTIONS),
        help="episodes=N (default: the record's), body=fitted|mjcf, springs=fitted|env, "
        "samples=N (default: the run's), out=FILE",
    )  # fmt: skip
    return p


def _count(options: dict[str, str], key: str) -> int | None:
    """The whole number given as `key` (None when not given); a ValueError naming it."""
    text = options.get(key)
    if text is not None and not (text.isdigit() and int(text) > 0):
        raise ValueError(f"{key}={text}: a whole number above 0")
    return None if text is None else int(text)


def main(argv: Sequence[str] | None = None) -> int:
    """The command line (module docstring); the exit code."""
    args = parser().parse_args(argv)
    options = dict(args.options)
    logging.basicConfig(level=logging.INFO, format="[%(name)s][%(levelname)s] - %(message)s")
    try:
        episodes, samples = (_count(options, key) for key in ("episodes", "samples"))
        result = rescore(args.run_dir, episodes, options.get("body", "fitted"),
                         options.get("springs", "fitted"), samples)  # fmt: skip
        text = json.dumps(result | provenance("mbrl_delan.rescore"), indent=1)
        if "out" in options:
            atomic_write(Path(options["out"]), lambda f: f.write(text.encode()), keep_prev=False)
        else:
            print(text)
    except (FileNotFoundError, ValueError, ConfigError, CheckpointError, RunWriteError) as err:
        return stop_on_input(err)
    log.info("%s: %d of %d fell (the oracle %d), %.4f of its return where both stood",
             args.run_dir, result["falls"], result["paired_episodes"], result["oracle_falls"],
             result["standing_return_ratio"])  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
