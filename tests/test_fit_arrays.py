"""Fit your own robot: `python -m mbrl_delan.fit data=arrays`, its Python API, `load_run` and
`python -m mbrl_delan.evaluate`, on arm data logged from MuJoCo by the tests themselves."""

from __future__ import annotations

import errno
import importlib.util
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.data.arrays import (
    ArrayFormatError,
    DerivativeSettings,
    load_arrays,
    save_arrays,
    split_trajectories,
)
from mbrl_delan.data.inverse_data import FitSystem, array_inverse_data
from mbrl_delan.data.synthetic import reference_terms, trajectory_dataset
from mbrl_delan.evaluate import evaluate_run
from mbrl_delan.evaluate import main as evaluate_main
from mbrl_delan.fit_run import fit_inverse_dynamics
from mbrl_delan.models.inverse import MLPInverse
from mbrl_delan.runs import load_run
from mbrl_delan.systems.system import layout_from_names, load_system
from mbrl_delan.training.inverse_fit import (
    InverseFitSettings,
    fit_inverse_model,
    generalisation_gap,
)

ROOT = Path(__file__).parents[1]
SMALL = ("epochs=4", "threads=1", "model.hidden=16", "batch_size=64")


@pytest.fixture(scope="module")
def arm2_data() -> TensorDict:
    """6 trajectories of 40 steps (1 s) of the two-link arm, with MuJoCo's parts of tau."""
    return trajectory_dataset(load_system("arm2"), 6, 40, torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def arm2_file(arm2_data, tmp_path_factory) -> Path:
    return save_arrays(arm2_data, tmp_path_factory.mktemp("data") / "arm2.npz")


@pytest.fixture(scope="module")
def fitted(arm2_file, tmp_path_factory) -> Path:
    """A small DeLaN fit from the .npz through the Python API (the MJCF's joints)."""
    run_dir = tmp_path_factory.mktemp("fits") / "delan"
    fit_inverse_dynamics(arm2_file, "arm2", run_dir, "delan", SMALL)
    return run_dir


# ---------------------------------------------------------------- the data


def test_logged_torques_are_mujocos_parts(arm2_data) -> None:
    """tau = M qdd + c + g + D qd with MuJoCo's M, c, g and the MJCF's damping."""
    damping = load_system("arm2").damping
    parts = sum(arm2_data[k] for k in (keys.TAU_INERTIAL, keys.TAU_CORIOLIS, keys.TAU_GRAVITY))
    torch.testing.assert_close(arm2_data[keys.TAU], parts + damping * arm2_data[keys.QD])
    gravity = reference_terms(load_system("arm2"), arm2_data[keys.Q][:5]).gravity
    torch.testing.assert_close(arm2_data[keys.TAU_GRAVITY][:5], gravity)


@pytest.mark.parametrize("suffix", [".pt", ".csv"])
def test_every_file_type_reads_as_the_npz(arm2_data, arm2_file, tmp_path, suffix) -> None:
    layout = load_system("arm2").layout
    other = load_arrays(save_arrays(arm2_data, tmp_path / f"arm2{suffix}"), layout)
    reference = load_arrays(arm2_file, layout)
    for key in (keys.Q, keys.QD, keys.QDD, keys.TAU, keys.TRAJECTORY, keys.TIME):
        torch.testing.assert_close(other[key], reference[key], rtol=1e-12, atol=1e-12)


def test_qdd_is_computed_from_qd_when_the_file_has_none(tmp_path) -> None:
    """Sampled at MuJoCo's own 2.5 ms, central differences of qd give MuJoCo's qacc."""
    xml = (ROOT / "mbrl_delan" / "systems" / "assets" / "arm2.xml").read_text()
    (tmp_path / "arm2_fine.xml").write_text(xml.replace('timestep="0.025"', 'timestep="0.0025"'))
    system = load_system(tmp_path / "arm2_fine.xml")
    data = trajectory_dataset(system, 2, 200, torch.Generator().manual_seed(1))
    fields = {k: data[k] for k in ("q", "qd", "tau", "trajectory")} | {"dt": np.array(0.0025)}
    loaded = load_arrays(save_arrays(fields, tmp_path / "noqdd.npz"), system.layout)
    inner = torch.cat([torch.arange(2, 198), 200 + torch.arange(2, 198)])  # away from the ends
    error = (loaded[keys.QDD][inner] - data[keys.QDD][inner]).norm()
    assert error / data[keys.QDD][inner].norm() < 0.05
    low_passed = load_arrays(tmp_path / "noqdd.npz", system.layout, DerivativeSettings(20.0))
    assert low_passed[keys.QDD].shape == data[keys.QDD].shape


def test_trajectories_are_never_cut() -> None:
    ids = torch.arange(10).repeat_interleave(7)
    masks = split_trajectories(ids, 0.1, 0.2, seed=3, val_by="trajectories")
    for name, mask in masks.items():
        held = ids[mask].unique()
        assert bool(torch.isin(ids, held).eq(mask).all()), name  # whole trajectories only
    assert [int(masks[n].sum()) // 7 for n in ("train", "val", "test")] == [7, 1, 2]
    assert bool((masks["train"] ^ masks["val"] ^ masks["test"]).all())


def test_segments_hold_out_one_block_of_each_training_trajectory() -> None:
    ids = torch.arange(10).repeat_interleave(20)
    masks = split_trajectories(ids, 0.1, 0.2, seed=3, val_by="segments")
    test_ids = ids[masks["test"]].unique()
    assert bool(torch.isin(ids, test_ids).eq(masks["test"]).all()) and test_ids.numel() == 2
    for i in set(range(10)) - set(test_ids.tolist()):
        rows = torch.nonzero(masks["val"] & (ids == i)).reshape(-1)
        assert rows.numel() == 2 and int(rows[1] - rows[0]) == 1  # one contiguous block
    assert bool((masks["train"] ^ masks["val"] ^ masks["test"]).all())


def test_whole_trajectories_validate_by_default() -> None:
    ids = torch.arange(10).repeat_interleave(20)
    masks = split_trajectories(ids, 0.1, 0.2, seed=3)
    held = {name: set(ids[masks[name]].tolist()) for name in ("train", "val", "test")}
    assert (len(held["val"]), len(held["test"]), len(held["train"])) == (1, 2, 7)
    for name, trajectories in held.items():  # every trajectory wholly in one split
        assert int(torch.isin(ids, torch.tensor(sorted(trajectories))).sum()) == 20 * len(
            trajectories
        ), name


def test_one_trajectory_holds_out_its_end() -> None:
    masks = split_trajectories(torch.zeros(100, dtype=torch.long), 0.1, 0.2, seed=0)
    assert masks["train"][:70].all() and masks["val"][70:80].all() and masks["test"][80:].all()


def test_joint_list_layout_is_the_mjcfs_for_unlimited_hinges() -> None:
    assert layout_from_names(["hinge", "hinge"]) == load_system("arm2").layout
    layout = layout_from_names(["free", "ball", "hinge", "slide"])
    assert (layout.nq, layout.nv, layout.qpos_adr, layout.dof_adr) == (
        13,
        11,
        (0, 7, 11, 12),
        (0, 6, 9, 10),
    )


# ---------------------------------------------------------------- fitting


def test_fit_from_an_npz_learns_the_arm(fitted, arm2_file) -> None:
    summary = json.loads((fitted / "summary.json").read_text())
    assert summary["data"] == "arrays"
    # 6 trajectories of 40: 1 for test, 1 for validation (whole ones)
    assert summary["samples"] == {"train": 4 * 40, "val": 40, "test": 40}
    assert summary["splits"]["val"] == "whole training trajectories"
    assert set(summary["final"]) == {"train", "val", "test"}
    assert set(summary["final"]["test"]["trajectories"]) | set(
        summary["final"]["val"]["trajectories"]
    ) | set(summary["final"]["train"]["trajectories"]) == {str(i) for i in range(6)}
    assert set(summary["final"]["test"]["groups"]) == {"shoulder", "elbow"}
    assert summary["positive_definite_fraction"] == 1.0
    assert summary["mass_matrix_random_poses"]["positive_definite_fraction"] == 1.0
    first = json.loads((fitted / "metrics.jsonl").read_text().splitlines()[0])
    assert summary["final"]["train"]["mse"] < first["train_mse"]  # it learned
    provenance = json.loads((fitted / "dataset_provenance.json").read_text())
    assert provenance["path"] == str(arm2_file.resolve()) and provenance["qdd"] == "from the file"


def test_fit_from_a_plain_joint_list_without_mjcf(arm2_data, tmp_path) -> None:
    fields = {k: arm2_data[k] for k in ("q", "qd", "qdd", "tau", "t", "trajectory")}
    result = fit_inverse_dynamics(fields, ["hinge", "hinge"], tmp_path / "run", "delan", SMALL)
    assert result.summary["dof_groups"] == {"joint0": 1, "joint1": 1}
    assert "mass_matrix_random_poses" not in result.summary  # no MJCF: no joint ranges to draw
    run = load_run(tmp_path / "run")
    assert run.kind == "fit" and run.config.data.joints == ["hinge", "hinge"]
    assert not run.model.training  # loaded for evaluation
    q = arm2_data[keys.Q][:8]
    with torch.no_grad():
        torch.testing.assert_close(run.model.mass_matrix(q), result.model.mass_matrix(q))


def test_early_stopping_keeps_the_lowest_validation_error(arm2_data) -> None:
    torch.manual_seed(0)
    model = MLPInverse(load_system("arm2").layout, hidden=8).double()
    train, val = arm2_data[:160], arm2_data[160:]
    settings = InverseFitSettings(epochs=12, batch_size=32, stop_on="val", patience=3)
    optimizer = torch.optim.Adam(model.parameters(), lr=0.3)  # large: the error goes up and down
    results = fit_inverse_model(
        model, optimizer, train, {"val": val}, settings, torch.Generator().manual_seed(0)
    )
    best = min(r.errors["val"].mse for r in results)
    from mbrl_delan.training.inverse_fit import evaluate_torques

    assert evaluate_torques(model, val).mse == pytest.approx(best, rel=1e-9)


@pytest.mark.parametrize("rule", ["min_delta", "min_rel_delta"])
def test_min_delta_stops_on_small_gains_and_keeps_the_best(arm2_data, rule: str) -> None:
    """Gains under min_delta (or the share min_rel_delta of the best error) do not restart
    the patience; the lowest error is still kept."""
    from mbrl_delan.training.inverse_fit import evaluate_torques

    def fit(**threshold: float) -> tuple[MLPInverse, list]:
        torch.manual_seed(0)
        model = MLPInverse(load_system("arm2").layout, hidden=8).double()
        settings = InverseFitSettings(
            epochs=30, batch_size=32, stop_on="val", patience=2, **threshold
        )
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)  # small: it keeps improving
        results = fit_inverse_model(
            model, optimizer, arm2_data[:160], {"val": arm2_data[160:]}, settings,
            torch.Generator().manual_seed(0),
        )  # fmt: skip
        return model, results

    _, plain = fit()
    first = plain[0].errors["val"].mse
    # only an error below a tenth of the first (of the best) counts
    model, strict = fit(**{rule: 0.9 * first if rule == "min_delta" else 0.9})
    errors = [r.errors["val"].mse for r in strict]
    assert len(strict) == 3 < len(plain)  # the first epoch, then two without that gain
    assert errors[2] < errors[0]  # it did improve, by less than the threshold
    assert evaluate_torques(model, arm2_data[160:]).mse == pytest.approx(min(errors), rel=1e-9)
    with pytest.raises(ValueError, match=rule):
        InverseFitSettings(**{rule: -1.0})


def test_the_relative_threshold_is_scale_free() -> None:
    """The same relative gains count at any error level (precise data's 1e-6 as noisy data's
    1e-2); an absolute threshold counts them at one level only."""
    relative, absolute = InverseFitSettings(min_rel_delta=0.01), InverseFitSettings(min_delta=1e-3)
    for scale in (1e-6, 1e-2, 1.0):
        assert relative.improves(0.98 * scale, scale)  # a 2% gain
        assert not relative.improves(0.995 * scale, scale)  # a 0.5% gain
    assert absolute.improves(0.98, 1.0) and not absolute.improves(0.98e-2, 1e-2)


# ---------------------------------------------------------------- reading a run back


def test_load_run_and_evaluate_reproduce_the_summary(fitted) -> None:
    summary = json.loads((fitted / "summary.json").read_text())
    result = evaluate_run(fitted)
    for name, part in summary["final"].items():
        again = result["splits"][name]
        assert again["mse"] == pytest.approx(part["mse"], rel=1e-12)
        assert again["r2"] == pytest.approx(part["r2"], rel=1e-12)
        for trajectory, errors in part["trajectories"].items():
            assert again["trajectories"][trajectory] == pytest.approx(errors, rel=1e-12)
        assert set(again["components"]) == {"tau_inertial", "tau_coriolis", "tau_gravity"}
        assert again["rollout"]["median_rollout_s"] >= 0.0


def test_evaluate_on_another_file_from_the_command_line(fitted, arm2_data, tmp_path) -> None:
    other = save_arrays(arm2_data[:80], tmp_path / "other.csv")
    out = tmp_path / "eval.json"
    assert evaluate_main([str(fitted), f"data={other}", f"out={out}"]) == 0
    result = json.loads(out.read_text())
    assert list(result["splits"]) == ["data"] and result["splits"]["data"]["n"] == 80
    assert set(result["splits"]["data"]["trajectories"]) == {"0", "1"}
    assert evaluate_main([str(fitted), "data=nowhere.npz"]) == 2
    with pytest.raises(SystemExit) as bad_option:
        evaluate_main([str(fitted), "colour=red"])
    assert bad_option.value.code == 2


def test_evaluate_out_that_cannot_be_written_is_exit_2_naming_it(
    fitted, tmp_path, monkeypatch, caplog
) -> None:
    """out= under a file (no folder can be made there) fails before the work; a full disk at
    the write names the file and leaves its earlier content."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert evaluate_main([str(fitted), f"out={blocker / 'eval.json'}"]) == 2
    assert f"cannot write {blocker}" in caplog.text and "Traceback" not in caplog.text
    out = tmp_path / "eval.json"
    out.write_text("earlier")

    calls = []

    def full_after_the_probe(fd: int) -> None:  # the disk fills during the work
        calls.append(fd)
        if len(calls) > 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full_after_the_probe)
    caplog.clear()
    assert evaluate_main([str(fitted), f"out={out}"]) == 2
    assert f"cannot write {out}: No space left on device (errno 28)" in caplog.text
    assert out.read_text() == "earlier"


def test_component_errors_are_zero_for_the_true_parts(fitted, arm2_data) -> None:
    """The figure compares the model's M qdd, c and g with the logged ones: fed the model's own
    parts as data, every error is 0."""
    from mbrl_delan.evaluate import component_errors

    model = load_run(fitted).model
    data = arm2_data[:20].clone()
    with torch.no_grad():
        terms = model.dynamics.terms(data[keys.Q], data[keys.QD])
    data[keys.TAU_CORIOLIS] = terms.coriolis
    data[keys.TAU_GRAVITY] = terms.gravity
    errors = component_errors(model.dynamics, data)
    assert errors["tau_coriolis"]["rel_error"] == 0.0 and errors["tau_gravity"]["rel_error"] == 0.0
    assert errors["tau_inertial"]["rel_error"] > 0.0  # not fitted to convergence


# ---------------------------------------------------------------- bad files


def _fields(arm2_data) -> dict[str, np.ndarray]:
    return {k: arm2_data[k].numpy().copy() for k in ("q", "qd", "tau", "t", "trajectory")}


def _missing_tau(f):
    del f["tau"]


def _short_qd(f):
    f["qd"] = f["qd"][:-3]


def _nan_q(f):
    f["q"][17, 1] = np.nan


def _inf_tau(f):
    f["tau"][5, 0] = np.inf


def _three_joints(f):
    f["qd"] = np.concatenate([f["qd"], f["qd"][:, :1]], axis=1)


BAD = {
    "missing": (_missing_tau, "'tau': missing"),
    "lengths": (_short_qd, "'qd': 237 rows, but q has 240"),
    "nan": (_nan_q, "'q': 1 NaN or inf values (first: row 17)"),
    "inf": (_inf_tau, "'tau': 1 NaN or inf values (first: row 5)"),
    "joints": (_three_joints, "'qd': 3 columns; the joints give 2"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_malformed_file_names_the_file_and_the_field(arm2_data, tmp_path, case) -> None:
    spoil, expected = BAD[case]
    fields = _fields(arm2_data)
    spoil(fields)
    path = tmp_path / "bad.npz"
    np.savez(path, **fields)
    with pytest.raises(ArrayFormatError) as err:
        array_inverse_data(path, FitSystem.of("arm2"))
    assert str(err.value).startswith(f"{path}: field ") and expected in str(err.value)


def test_malformed_file_exits_2_and_leaves_no_run_folder(arm2_data, tmp_path, run_main) -> None:
    """At start, before the run writes anything: Hydra's record, the log and the lock go with
    the folder; a folder that held a file of the user's before keeps it. (A run dir that holds
    a run is refused before the data are read:
    test_fit_mocap.py::test_new_fit_in_a_used_run_dir_is_refused_and_leaves_it_as_it_was.)"""
    from mbrl_delan.fit import main

    fields = _fields(arm2_data)
    _nan_q(fields)
    path = tmp_path / "bad.npz"
    np.savez(path, **fields)
    args = [f"data.path={path}", "data=arrays", "data.joints=[hinge,hinge]", "logger=none"]
    run_dir = tmp_path / "new"
    code, text = run_main(main, *args, f"hydra.run.dir={run_dir}")
    assert code == 2 and "Traceback" not in text, text
    assert f"bad data file: {path}: field 'q': 1 NaN or inf values (first: row 17)" in text
    assert not run_dir.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine")
    code, text = run_main(main, *args, f"hydra.run.dir={kept}")
    assert code == 2 and (kept / "notes.txt").read_text() == "mine", text


def test_a_fit_into_a_folder_another_process_writes_exits_2(arm2_data, tmp_path) -> None:
    """A fit whose run dir another live process holds (here the test) stops before writing,
    naming that process."""
    from mbrl_delan.training.run_lock import RunLock

    path = tmp_path / "arm2.npz"
    np.savez(path, **_fields(arm2_data))
    run_dir = tmp_path / "run"
    holder = RunLock(run_dir)
    run_dir.mkdir()
    holder.acquire()
    try:
        cmd = [sys.executable, "-m", "mbrl_delan.fit", "data=arrays", f"data.path={path}"]
        cmd += ["data.joints=[hinge,hinge]", "logger=none", f"hydra.run.dir={run_dir}"]
        env = {**os.environ, "WANDB_MODE": "disabled"}
        out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300, cwd=ROOT)
    finally:
        holder.release()
    text = out.stdout + out.stderr
    assert out.returncode == 2 and "Traceback" not in text, text
    assert f"is in use by another process (pid {os.getpid()})" in text, text
    assert {p.name for p in run_dir.iterdir()} == {".lock"}


# ---------------------------------------------------------------- the docs' worked example


def _log_arm():
    spec = importlib.util.spec_from_file_location("log_arm", ROOT / "examples/own_robot/log_arm.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_worked_example(tmp_path) -> None:
    """docs/own_robot.md's three commands, smaller: log, fit from the command line, evaluate."""
    log_arm = _log_arm()
    data = log_arm.main(
        ["arm3", str(tmp_path / "arm3.npz"), "--trajectories", "6", "--steps", "30"]
    )
    more = log_arm.main(
        [
            "arm3",
            str(tmp_path / "more.npz"),
            "--trajectories",
            "2",
            "--steps",
            "30",
            "--seed",
            "1",
            "--no-qdd",
        ]
    )
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "mbrl_delan.fit", "data=arrays", f"data.path={data}"]
    cmd += [
        "data.joints=[hinge,hinge,hinge]",
        "epochs=3",
        "logger=none",
        f"hydra.run.dir={run_dir}",
    ]
    env = {**os.environ, "WANDB_MODE": "disabled"}
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["samples"] == {"train": 120, "val": 30, "test": 30}  # 6 x 30: 4/1/1
    report = tmp_path / "eval.json"
    assert evaluate_main([str(run_dir), f"data={more}", f"out={report}"]) == 0
    result = json.loads(report.read_text())["splits"]["data"]
    assert result["n"] == 60 and set(result["rollout"]["trajectories"]) == {"0", "1"}
    assert set(result["components"]) == {"tau_inertial", "tau_coriolis", "tau_gravity"}


def test_a_named_test_file_is_the_test_split(arm2_data, arm2_file, tmp_path) -> None:
    """data.test_path: the other file's trajectories are the test split and every trajectory
    of data.path trains or validates; the provenance records both files."""
    other = trajectory_dataset(load_system("arm2"), 2, 40, torch.Generator().manual_seed(5))
    test_file = save_arrays(other, tmp_path / "held_out.npz")
    result = fit_inverse_dynamics(
        arm2_file, "arm2", tmp_path / "run", "delan", [*SMALL, f"data.test_path={test_file}"]
    )
    assert result.summary["samples"] == {"train": 5 * 40, "val": 40, "test": 80}
    assert result.summary["splits"]["test"] == f"the trajectories of {test_file.resolve()}"
    assert set(result.summary["final"]["test"]["trajectories"]) == {"test:0", "test:1"}
    provenance = json.loads((tmp_path / "run" / "dataset_provenance.json").read_text())
    assert provenance["test"]["path"] == str(test_file.resolve())


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d: d / "missing.npz", "data.test_path='{}': no such file"),
        (lambda d: _three_joint_file(d), "field 'q'"),
    ],
)
def test_a_missing_or_mismatched_test_file_is_one_line_naming_it(
    arm2_file, tmp_path, make, message
) -> None:
    path = make(tmp_path)
    cmd = [sys.executable, "-m", "mbrl_delan.fit", "data=arrays", f"data.path={arm2_file}",
           "data.mjcf=arm2", f"data.test_path={path}", "logger=none", "epochs=1",
           f"hydra.run.dir={tmp_path / 'run'}"]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    text = out.stdout + out.stderr
    assert out.returncode == 2 and "Traceback" not in text, text
    assert message.format(path) in text and str(path) in text
    assert not (tmp_path / "run" / "model.pt").exists()


def _three_joint_file(folder: Path) -> Path:
    data = trajectory_dataset(load_system("arm3"), 1, 20, torch.Generator().manual_seed(0))
    return save_arrays(data, folder / "arm3.npz")


def test_a_test_error_far_above_the_validation_error_is_warned_about(caplog) -> None:
    final = {"val": {"r2": 0.999}, "test": {"r2": 0.95}}
    with caplog.at_level(logging.WARNING, logger="mbrl_delan.training.inverse_fit"):
        assert generalisation_gap(final, "val") == pytest.approx(0.049)
    assert "test R2 0.9500 is 0.0490 below val R2 0.9990" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="mbrl_delan.training.inverse_fit"):
        assert generalisation_gap({"val": {"r2": 0.999}, "test": {"r2": 0.995}}, "val") < 0.01
        assert generalisation_gap(final, None) is None  # nothing stops the training
    assert not caplog.text


@pytest.mark.parametrize("damage", ["truncated", "text"])
def test_a_damaged_or_foreign_npz_exits_2_in_one_line(
    arm2_data, tmp_path, run_main, damage
) -> None:
    """A truncated archive and a text file named .npz: one line naming the file, exit 2,
    no run folder (not zipfile's traceback, not a reason about pickled data)."""
    from mbrl_delan.fit import main

    good = tmp_path / "good.npz"
    np.savez(good, **_fields(arm2_data))
    path = tmp_path / "bad.npz"
    if damage == "truncated":
        path.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    else:
        path.write_text("t,q0,q1\n0,1,2\n")
    with pytest.raises(ArrayFormatError, match="is not a readable .npz archive"):
        array_inverse_data(path, FitSystem.of("arm2"))
    run_dir = tmp_path / "new"
    args = [f"data.path={path}", "data=arrays", "data.joints=[hinge,hinge]", "logger=none"]
    code, text = run_main(main, *args, f"hydra.run.dir={run_dir}")
    assert code == 2 and "Traceback" not in text and "pickled" not in text, text
    assert f"bad data file: {path}: field '<file>': is not a readable .npz archive" in text
    assert not run_dir.exists()


def test_the_fit_arrays_suite_records_each_fits_stopping_rule_and_tables_it() -> None:
    """Suite fit_arrays (quick) records the stopping rule each fit ran under, and its table
    (``python -m mbrl_delan.benchmarks.fit_arrays FILES``) has one row per arm and run."""
    from dataclasses import replace

    from mbrl_delan.benchmarks.fit_arrays import FitArraysConfig, results_table, run_fit_arrays

    quick = FitArraysConfig.quick()
    cfg = replace(quick, overrides=(*quick.overrides, "min_rel_delta=0.25"))
    records = [r.to_dict() for r in run_fit_arrays(cfg)]
    delan = [r for r in records if r["setting"] == "delan"]
    assert delan and all(r["stopping"]["min_rel_delta"] == 0.25 for r in delan)
    table = results_table(records)
    row = "| arm2 | min_delta 0, min_rel_delta 0.25 | 0 |"
    assert len(table) == 3 and table[2].startswith(row), table
