"""Checkpoints, RNG state, run records (metrics.jsonl, summary.json, wandb) and plots."""

from __future__ import annotations

import errno
import json
import logging
import random
import sys
import types

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tiny import TINY_TRAIN

from mbrl_delan.data import all_transitions, make_replay_buffer
from mbrl_delan.training import (
    Recorder,
    load_checkpoint,
    read_metrics,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from mbrl_delan.training.checkpoint import prev_path
from mbrl_delan.training.plots import plot_run
from mbrl_delan.training.recorder import WandbOptions

# --- checkpoints -------------------------------------------------------------------------


def test_save_load_round_trip_keeps_previous(tmp_path):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"iteration": 1, "w": torch.ones(3)})
    assert not prev_path(path).exists()
    save_checkpoint(path, {"iteration": 2, "w": torch.zeros(3)})
    assert load_checkpoint(path)["iteration"] == 2
    assert load_checkpoint(prev_path(path))["iteration"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt", "ckpt.pt.prev"]


def test_buffer_state_in_checkpoint(tmp_path):
    buffer = make_replay_buffer(5)
    buffer.extend(TensorDict({"q": torch.arange(7.0).unsqueeze(-1)}, [7]))
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"buffer": buffer.state_dict(), "rng": rng_state()})
    restored = make_replay_buffer(5)
    restored.load_state_dict(load_checkpoint(path)["buffer"])
    assert torch.equal(all_transitions(restored)["q"].squeeze(-1), torch.tensor([2.0, 3, 4, 5, 6]))
    assert restored.writer.state_dict() == buffer.writer.state_dict()


# --- RNG state ---------------------------------------------------------------------------


def _draw(generator: torch.Generator) -> tuple:
    return (
        torch.rand(3).tolist(),
        np.random.rand(3).tolist(),
        np.random.randn(1).tolist(),
        [random.random() for _ in range(3)],
        torch.rand(3, generator=generator).tolist(),
    )


def test_rng_round_trip(tmp_path):
    gen = torch.Generator().manual_seed(5)
    np.random.randn(1)  # leaves a cached gaussian in numpy's state
    path = tmp_path / "rng.pt"
    save_checkpoint(path, {"rng": rng_state({"planner": gen})})
    first = _draw(gen)
    _draw(gen)
    set_rng_state(load_checkpoint(path)["rng"], {"planner": gen})
    assert _draw(gen) == first


def test_rng_missing_generator_is_an_error():
    state = rng_state()
    with pytest.raises(KeyError, match="fit"):
        set_rng_state(state, {"fit": torch.Generator()})


# --- recorder ----------------------------------------------------------------------------


def _recorder(run_dir, resume=None, backend="none"):
    return Recorder(run_dir, backend, "test", None, {"seed": 0}, resume_iteration=resume)


def test_metrics_jsonl_and_resume_truncation(tmp_path):
    with _recorder(tmp_path) as rec:
        for it in range(5):
            rec.log({"env_steps": 100 * it, "loss": torch.tensor(1.0 / (it + 1))}, iteration=it)
        rec.log({"bad": float("nan")}, iteration=5)
    records = read_metrics(tmp_path / "metrics.jsonl")
    assert [r["iteration"] for r in records] == [0, 1, 2, 3, 4, 5]
    assert records[2]["loss"] == pytest.approx(1 / 3) and records[5]["bad"] is None
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write('{"iteration": 6, "env_st')  # torn last line from a crash

    with _recorder(tmp_path, resume=3) as rec:  # checkpoint was taken at iteration 3
        rec.log({"env_steps": 400}, iteration=4)
    records = read_metrics(tmp_path / "metrics.jsonl")
    assert [r["iteration"] for r in records] == [0, 1, 2, 3, 4]
    assert records[-1] == {"iteration": 4, "env_steps": 400}
    lines = (tmp_path / "metrics.jsonl").read_text().splitlines()
    assert all(json.loads(line) for line in lines)

    _recorder(tmp_path).finish()  # not a resume: a fresh file
    assert read_metrics(tmp_path / "metrics.jsonl") == []


def test_summary_is_written_atomically(tmp_path):
    rec = _recorder(tmp_path)
    rec.write_summary({"env": "pendulum", "eval_return_mean": np.float32(1.5), "x": float("inf")})
    rec.finish()
    rec.finish()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary == {"env": "pendulum", "eval_return_mean": 1.5, "x": None}
    assert [p.name for p in tmp_path.iterdir() if "summary" in p.name] == ["summary.json"]


class _FakeRun:
    def __init__(self, **kwargs):
        self.kwargs = kwargs
        self.id = "abc123"
        self.logged: list = []
        self.summary: dict = {}
        self.finished = False
        self.metrics: list = []

    def define_metric(self, name, step_metric=None):
        self.metrics.append((name, step_metric))

    def log(self, data):
        self.logged.append(data)

    def finish(self):
        self.finished = True


def test_wandb_offline_by_default(tmp_path, monkeypatch):
    runs = []
    fake = types.ModuleType("wandb")
    fake.init = lambda **kw: runs.append(_FakeRun(**kw)) or runs[-1]
    monkeypatch.setitem(sys.modules, "wandb", fake)
    monkeypatch.delenv("WANDB_MODE", raising=False)
    rec = Recorder(tmp_path, "wandb", "proj", "grp", {"lr": 0.1}, step_key="env_steps")
    rec.log({"loss": 1.0, "name": "x", "env_steps": 40}, iteration=3)
    rec.write_summary({"env_steps": 10})
    rec.finish()
    (run,) = runs
    assert run.kwargs["mode"] == "offline" and run.kwargs["dir"] == str(tmp_path)
    assert (run.kwargs["project"], run.kwargs["group"]) == ("proj", "grp")
    assert run.logged == [{"iteration": 3, "loss": 1.0, "env_steps": 40}]
    assert run.metrics == [("env_steps", None), ("*", "env_steps")]  # charts against env steps
    assert run.summary == {"env_steps": 10} and run.finished

    monkeypatch.setenv("WANDB_MODE", "disabled")
    Recorder(tmp_path, "wandb", "proj", None, {}, resume_iteration=3).finish()
    assert runs[-1].kwargs["mode"] == "disabled"
    assert runs[-1].kwargs["id"] == "abc123"  # resumed runs continue the same wandb run
    assert (run.kwargs["name"], run.kwargs["tags"], run.kwargs["entity"]) == (None, None, None)

    options = WandbOptions(name="arm-s0", tags=("panda", "delan"), entity="lab", mode="online")
    Recorder(tmp_path / "named", "wandb", "proj", None, {}, wandb_options=options).finish()
    kwargs = runs[-1].kwargs
    assert (kwargs["name"], kwargs["entity"]) == ("arm-s0", "lab")
    assert kwargs["tags"] == ["panda", "delan"]
    assert kwargs["mode"] == "online"  # the config's mode over WANDB_MODE


def test_wandb_options_from_a_logger_config() -> None:
    from omegaconf import OmegaConf

    from mbrl_delan.conf.checks import compose_train_config

    cfg = compose_train_config(["logger.name=run1", "logger.tags=[a,b]", "logger.mode=disabled"])
    assert WandbOptions.of(cfg.logger) == WandbOptions("run1", ("a", "b"), None, "disabled")
    assert WandbOptions.of(OmegaConf.create({"backend": "csv"})) == WandbOptions()


def test_wandb_failure_warns_and_continues(tmp_path, monkeypatch, caplog):
    fake = types.ModuleType("wandb")

    def broken_init(**kwargs):
        raise RuntimeError("no wandb service")

    fake.init = broken_init
    monkeypatch.setitem(sys.modules, "wandb", fake)
    with caplog.at_level(logging.WARNING):
        rec = Recorder(tmp_path, "wandb", "proj", None, {})
    assert not rec.wandb_active and "no wandb service" in caplog.text
    rec.log({"loss": 1.0}, iteration=0)
    rec.finish()
    assert read_metrics(tmp_path / "metrics.jsonl") == [{"iteration": 0, "loss": 1.0}]


# --- plots -------------------------------------------------------------------------------


def test_plots_from_small_metrics(tmp_path):
    with _recorder(tmp_path) as rec:
        for it in range(6):
            record = {"env_steps": 200 * (it + 1), "train_return": 10.0 * it}
            if it % 2 == 1:
                record |= {
                    "eval_return_mean": 12.0 * it,
                    "eval_return_std": 2.0,
                    "oracle_return_mean": 80.0,
                    "model_error_1step": 0.1 / (it + 1),
                    "model_error_hstep": 1.0 / (it + 1),
                }
            rec.log(record, iteration=it)
    paths = plot_run(tmp_path)
    assert sorted(p.name for p in paths) == ["model_error.png", "returns.png"]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_run_plots_are_titled_with_env_model_planner_and_seed(tmp_path):
    from mbrl_delan.training.plots import run_title

    config = "seed: 2\nenv:\n  name: cartpole\nmodel:\n  name: delan\nplanner:\n  name: icem\n"
    (tmp_path / "config.yaml").write_text(config)
    assert run_title(tmp_path) == "cartpole / delan / icem, seed 2"
    assert run_title(tmp_path / "elsewhere") == ""


def test_plots_skip_missing_metrics(tmp_path):
    with _recorder(tmp_path) as rec:
        rec.log({"env_steps": 100, "train_return": 1.0}, iteration=0)
    assert [p.name for p in plot_run(tmp_path)] == ["returns.png"]
    assert plot_run(tmp_path / "empty") == []


@pytest.mark.parametrize("backend", ["csv", "tensorboard"])
def test_torchrl_loggers_get_every_number_against_env_steps(tmp_path, backend):
    """`logger=csv` and `logger=tensorboard` go through TorchRL's loggers: each number of a
    record at the record's env_steps, the figures as images (TensorBoard), the summary's
    numbers as ``summary/<key>`` (CSV: at the last step; TensorBoard: the hparams' metrics)."""
    import matplotlib.pyplot as plt

    figure = tmp_path / "returns.png"
    plt.figure(figsize=(2, 2))
    plt.savefig(figure)
    plt.close()
    rec = Recorder(tmp_path, backend, "test", None, {"seed": 0}, step_key="env_steps")
    for it, steps in enumerate((15, 30)):
        rec.log({"env_steps": steps, "train_return": 2.0 * it, "planner": "mppi"}, iteration=it)
    rec.log_image("returns", figure)
    rec.write_summary({"fraction_of_oracle": 0.75, "env": "pendulum", "finished": True})
    rec.finish()
    if backend == "csv":
        rows = (tmp_path / "csv" / "scalars" / "train_return.csv").read_text().splitlines()
        assert rows == ["15,0.0", "30,2.0"]
        summary = tmp_path / "csv" / "scalars" / "summary" / "fraction_of_oracle.csv"
        assert summary.read_text().splitlines() == ["30,0.75"]
        assert not (tmp_path / "csv" / "scalars" / "summary" / "finished.csv").exists()
        return
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tmp_path / "tensorboard"))  # (the hyperparameters: a subfolder)
    acc.Reload()
    scalars = acc.Scalars("train_return")
    assert [(s.step, s.value) for s in scalars] == [(15, 0.0), (30, 2.0)]
    assert acc.Tags()["images"] == ["returns"]
    from tensorboard.plugins.hparams import plugin_data_pb2

    content = acc.PluginTagToContent("hparams")
    experiment = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/experiment"])
    metrics = [m.name.tag for m in experiment.experiment.metric_infos]
    assert metrics == ["summary/fraction_of_oracle"]
    assert [h.name for h in experiment.experiment.hparam_infos] == ["seed"]
    assert acc.Scalars("summary/fraction_of_oracle")[0].value == 0.75


def test_unknown_logger_is_named(tmp_path):
    with pytest.raises(ValueError, match="'mlflow' is not one of none, wandb, csv, tensorboard"):
        Recorder(tmp_path, "mlflow", "test", None, {})


# --- files that cannot be written ----------------------------------------------------------


def test_a_run_dir_that_cannot_be_made_is_one_line_and_exit_2(tmp_path, monkeypatch, run_main):
    """A run dir under a folder that refuses writes (permissions, a read-only disk) fails at
    start naming the path and the OS error, before Hydra's log file does, with nothing made."""
    from pathlib import Path

    from mbrl_delan.train import main

    locked = tmp_path / "locked"
    real_mkdir = Path.mkdir

    def mkdir(self, *args, **kwargs):
        if locked in (self, *self.parents):
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", mkdir)
    run_dir = locked / "run"
    code, text = run_main(main, *TINY_TRAIN, f"hydra.run.dir={run_dir}")
    assert code == 2 and "Traceback" not in text, text
    assert f"cannot write {run_dir}" in text and "Permission denied (errno 13)" in text, text
    assert not locked.exists()
    from mbrl_delan.fit import main as fit_main

    code, text = run_main(fit_main, "data=arrays", "data.path=x.npz", f"hydra.run.dir={run_dir}")
    assert code == 2 and "Traceback" not in text and f"cannot write {run_dir}" in text, text
    from mbrl_delan.bench import main as bench_main

    code, text = run_main(bench_main, "quick=true", f"hydra.run.dir={run_dir}")
    assert code == 2 and "Traceback" not in text and f"cannot write {run_dir}" in text, text
