"""`python -m mbrl_delan.fit`: inverse dynamics from mocap with DeLaN, the MLP and the ensemble.

End to end on the small CMU clip in tests/data (09_06, a run; see tests/data/CMU_TERMS.txt),
held out a second time under another name as the validation clip.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig
from tensordict import TensorDict
from torch import nn

from mbrl_delan import keys
from mbrl_delan.conf.builders import build_model
from mbrl_delan.conf.checks import CONFIG_DIR, ConfigError
from mbrl_delan.conf.fitting import FIT_CONFIG_DIR, validate_fit_config
from mbrl_delan.conf.loop import start_mechanics, with_fit_structure
from mbrl_delan.data.buffer import NonFiniteDataError
from mbrl_delan.data.mocap import (
    ClipNotFoundError,
    MocapFormatError,
    build_dataset,
    humanoid_cmu_xml,
    random_poses,
    save_dataset,
)
from mbrl_delan.data.mocap.retarget import joint_layout
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.fit_report import main as report_main
from mbrl_delan.fit_report import seed_table
from mbrl_delan.fit_run import run
from mbrl_delan.models.field import tree_entries
from mbrl_delan.models.inverse import (
    INVERSE_STRUCTURE,
    DeLaNInverse,
    MLPEnsembleInverse,
    MLPInverse,
)
from mbrl_delan.runs import load_fit_model
from mbrl_delan.systems.system import FREE, HINGE, JointLayout
from mbrl_delan.training.fit import TrainingDivergedError
from mbrl_delan.training.inverse_fit import evaluate_torques

ROOT = Path(__file__).parents[1]

DATA = Path(__file__).parent / "data"
CLIP, HELD_OUT, TEST = "09_06", "09_99", "09_98"
TEST_CLIP = {"clip": CLIP, "folders": [str(DATA)], "download": False}  # env=cmu_track
GROUP_SIZES = {"root": 6, "legs": 14, "spine_neck_head": 18, "arms": 14, "hands": 10}
SPLITS = ("train", "val_time", "val_clip")


@pytest.fixture(scope="module")
def clip_folder(tmp_path_factory) -> Path:
    """09_06 under its own name (training) and as 09_99 (the held-out clip)."""
    try:
        humanoid_cmu_xml()
    except (ModuleNotFoundError, FileNotFoundError) as err:
        pytest.skip(f"humanoid_CMU.xml unavailable: {err}")
    folder = tmp_path_factory.mktemp("clips")
    for name in (CLIP, HELD_OUT, TEST):
        (folder / f"{name}.amc").write_bytes((DATA / f"{CLIP}.amc").read_bytes())
    (folder / "09.asf").write_bytes((DATA / "09.asf").read_bytes())
    return folder


def small_overrides(folder: Path) -> list[str]:
    return [
        "logger=none",
        "threads=1",
        "epochs=2",
        "batch_size=32",
        "lr=0.003",
        f"data.clips=[{CLIP},{HELD_OUT}]",
        f"data.val_clips=[{HELD_OUT}]",
        f"data.folders=[{folder}]",
        "data.download=false",
        "data.samples_per_clip=120",
        "data.split.gap_s=0.1",
        "model.hidden=16",
    ]


def config(*overrides: str) -> DictConfig:
    with initialize_config_dir(config_dir=str(FIT_CONFIG_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.fixture(scope="module")
def fitted(clip_folder, tmp_path_factory) -> dict[str, Path]:
    """Two epochs of each model through `run` (the entry point's body)."""
    out = {}
    for name in ("delan", "mlp", "ensemble"):
        run_dir = tmp_path_factory.mktemp(f"fit_{name}")
        run(config(*small_overrides(clip_folder), f"model={name}"), run_dir)
        out[name] = run_dir
    return out


def records(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


# ---------------------------------------------------------------- end to end


@pytest.mark.parametrize("name", ["delan", "mlp", "ensemble"])
def test_fit_writes_per_epoch_metrics_summary_and_figure(fitted, name: str) -> None:
    run_dir = fitted[name]
    recs = records(run_dir)
    assert [r["epoch"] for r in recs] == [1, 2]
    for r in recs:
        for split in SPLITS:
            for metric in ("mse", "mse_si", "r2"):
                assert math.isfinite(r[f"{split}_{metric}"]), (split, metric)
            assert r[f"{split}_mse"] > 0 and r[f"{split}_mse_si"] > 0
    assert recs[1]["train_mse"] < recs[0]["train_mse"]  # it learns
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["model"] == name and summary["epochs"] == 2
    assert set(summary["final"]) == set(SPLITS)
    assert summary["samples"]["val_clip"] == 120 and summary["samples"]["train"] > 50
    for split in SPLITS:
        part = summary["final"][split]
        assert part["mse"] == pytest.approx(recs[-1][f"{split}_mse"])
        assert {g: None for g in part["groups"]}.keys() == GROUP_SIZES.keys()
        assert math.isfinite(part["joint_mse_si"]) and part["r2"] <= 1.0
    assert summary["dof_groups"] == GROUP_SIZES
    assert 0 < summary["train_s"] <= summary["wall_time_s"] and summary["cpu_time_s"] > 0
    for file in ("loss_curves.png", "model.pt", "config.yaml", "dataset_provenance.json"):
        assert (run_dir / file).is_file(), file
    if name == "delan":
        assert summary["positive_definite_fraction"] == 1.0
        assert summary["mass_matrix"]["n"] == sum(summary["samples"].values())
        assert summary["mass_matrix"]["min_eigenvalue"] > 0
    else:
        assert "positive_definite_fraction" not in summary


def test_fit_report_table_and_shared_figure(fitted, tmp_path: Path, capsys) -> None:
    png = tmp_path / "img" / "mocap_loss.png"
    code = report_main([str(fitted["delan"]), str(fitted["mlp"]), "--figure", str(png), "--table"])
    assert code == 0 and png.is_file() and png.stat().st_size > 1000
    text = capsys.readouterr().out
    rows = [line for line in text.splitlines() if line.startswith(("| delan", "| mlp"))]
    assert len(rows) == 6  # two models x three splits
    assert all(any(f"| {s} |" in r for r in rows) for s in SPLITS)
    assert report_main([str(tmp_path)]) == 2  # no runs there
    assert report_main([str(fitted["delan"]), "--clips"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| delan")]
    assert [row.split(" | ")[2:4] for row in rows] == [
        ["train", CLIP], ["val_time", CLIP], ["val_clip", HELD_OUT]
    ]  # fmt: skip


def test_seed_table_means_and_paired_differences() -> None:
    """Worked example: DeLaN 0.5, 0.7 and MLP 0.6, 0.6 on seeds 0, 1: means 0.6 and 0.6,
    paired differences -0.1, +0.1 -> mean 0 +- t(0.975, 1) * 0.1414 / sqrt(2) = 1.27."""

    def run(model: str, seed: int, mse: float) -> dict:
        groups = {"root": {"mse": 2 * mse}}
        part = {"mse": mse, "joint_mse_si": 10 * mse, "r2": 1 - mse, "groups": groups}
        return {"model": model, "seed": seed, "final": {s: part for s in SPLITS}}

    runs = [run("delan", 0, 0.5), run("delan", 1, 0.7), run("mlp", 0, 0.6), run("mlp", 1, 0.6)]
    text = seed_table(runs)
    assert "| delan | val_clip | 2 | 0.6 ± 1.3 | 6 ± 13 | 1.2 ± 2.5 | 0.4 ± 1.3 |" in text
    assert "| mlp | val_clip | 2 | 0.6 ± 0 | 6 ± 0 | 1.2 ± 0 | 0.4 ± 0 |" in text
    diff = text.split("Difference to mlp")[1]
    assert "| delan | val_clip | 2 | 0 ± 1.3 |" in diff


# ---------------------------------------------------------------- models


def delan_inverse(layout: JointLayout, **options: object) -> DeLaNInverse:
    """The fit's DeLaN with its default structure changed by `options`."""
    return DeLaNInverse(layout, replace(INVERSE_STRUCTURE, **options))


def humanoid_layout() -> JointLayout:
    """A free root and 56 limited hinges, as humanoid_CMU."""
    n = 56
    return JointLayout(
        types=(FREE,) + (HINGE,) * n,
        qpos_adr=(0,) + tuple(range(7, 7 + n)),
        dof_adr=(0,) + tuple(range(6, 6 + n)),
        limited=(False,) + (True,) * n,
    )


def random_batch(layout: JointLayout, n: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, layout.nq, generator=g, dtype=torch.float64)
    q[:, 3:7] /= q[:, 3:7].norm(dim=1, keepdim=True)
    qd = torch.randn(n, layout.nv, generator=g, dtype=torch.float64)
    qdd = torch.randn(n, layout.nv, generator=g, dtype=torch.float64)
    return q, qd, qdd


def test_mlp_is_three_linear_layers_and_sees_what_delan_sees() -> None:
    layout = humanoid_layout()
    mlp = MLPInverse(layout, hidden=8)
    linear = [m for m in mlp.modules() if isinstance(m, nn.Linear)]
    assert len(linear) == 3
    delan = delan_inverse(layout, hidden=8)
    n_features = delan.mechanics.features.n_features
    assert n_features == 1 + 9 + 56  # root height, root rotation matrix, hinge angles
    assert linear[0].in_features == n_features + 2 * layout.nv  # phi(q), qd, qdd
    assert linear[-1].out_features == layout.nv == 62  # tau incl. the root residual


def test_ensemble_is_vectorised_members() -> None:
    """Batched weights compute exactly what E separate three-layer MLPs would."""
    layout = humanoid_layout()
    ens = MLPEnsembleInverse(layout, ensemble_size=3, hidden=8).double()
    q, qd, qdd = random_batch(layout, 5)
    members = ens.member_predictions(q, qd, qdd)  # (E, B, nv)
    assert members.shape == (3, 5, 62)
    x = ens.standardised_inputs(q, qd, qdd)
    for e in range(3):
        h = x
        for i, layer in enumerate(ens.layers):
            h = h @ layer.weight[e] + layer.bias[e]
            h = ens.act(h) if i < 2 else h
        torch.testing.assert_close(members[e], h * ens.tau_scale + ens.tau_mean)
    torch.testing.assert_close(ens.predict_torque(q, qd, qdd), members.mean(0))
    assert len(ens.layers) == 3


def test_delan_inverse_is_the_lagrangian_equations_in_data_units() -> None:
    """tau = M qdd + c + g + d with M = D L~ L~^T D positive definite, whatever the units."""
    layout = humanoid_layout()
    torch.manual_seed(0)
    model = delan_inverse(layout, hidden=16, coulomb=True).double()
    q, qd, qdd = random_batch(layout, 4)
    field = model.mechanics
    with torch.no_grad():  # leave the zero initialisation: test general weights and units
        for p in model.parameters():
            p.normal_(0.0, 0.05)
        inner = model.mass_matrix(q)  # unit scales still 1
        field.row_scale.copy_(torch.logspace(-1, 1, 62))
        field.energy_scale.fill_(50.0)
    terms = model.dynamics.terms(q, qd)
    expected = (terms.mass_matrix @ qdd.unsqueeze(-1)).squeeze(-1) + terms.bias
    torch.testing.assert_close(model.predict_torque(q, qd, qdd), expected)
    d = field.row_scale
    torch.testing.assert_close(model.mass_matrix(q), d[:, None] * inner * d)
    assert bool((torch.linalg.cholesky_ex(model.mass_matrix(q)).info == 0).all())


def test_delan_inverse_units_come_from_delan(clip_folder) -> None:
    """fit_normalization on mocap data (tau as the action, no next state) sets DeLaN's units:
    finite and positive, the held-still clavicles and fingers (whose qdd std is round-off or
    0) at the others' geometric mean and their features only centred."""
    data = build_dataset(
        clips=(CLIP,), val_clips=(), folders=[clip_folder], download=False, samples_per_clip=200
    ).data.select(keys.Q, keys.QD, keys.QDD, keys.TAU)
    torch.manual_seed(0)
    model = delan_inverse(humanoid_layout(), hidden=16).double()
    model.fit_normalization(data)
    field, friction = model.mechanics, model.dynamics.dissipation
    qdd_std, tau_std = data[keys.QDD].std(0), data[keys.TAU].std(0)
    held = qdd_std < 1e-9 * qdd_std.max()  # clavicles, fingers
    assert int(held.sum()) == 10
    for units in (field.row_scale, friction.viscous_scale, friction.coulomb_scale):
        assert torch.isfinite(units).all() and (units > 0).all()
    moving = ~held
    torch.testing.assert_close(field.row_scale[moving] ** 2, (tau_std / qdd_std)[moving])
    # held still against gravity: the torque's std over the moving DoFs' typical acceleration
    typical_qdd = qdd_std[moving].log().mean().exp()
    torch.testing.assert_close(field.row_scale[held] ** 2, tau_std[held] / typical_qdd)
    fingers = held & (tau_std < 0.5)  # fingers and thumbs: inertia units near their armature
    assert int(fingers.sum()) == 6 and float(field.row_scale[fingers].max() ** 2) < 0.05
    assert float(field.energy_scale) == pytest.approx(float(data[keys.TAU].std(0).max()))
    assert float(field.row_scale.max()) < 10.0  # sqrt of the root's ~55 kg, not round-off
    features = field.features  # held-still hinges: only centred, not divided by ~0
    plain_v = features.plain_v.tolist()
    held_plain = [plain_v.index(i) for i in held.nonzero().flatten().tolist()]
    assert (features.plain_std[held_plain] == 1.0).all()
    with torch.no_grad():
        assert math.isfinite(float(model.loss(data).loss))


def test_translation_invariant_models_do_not_see_the_root_position() -> None:
    """With `translation_invariant`, DeLaN's tau does not change when the root moves
    anywhere (x, y and z): its height enters only gravity's potential w z, whose force along
    the height is the constant w; the MLP loses its root-height input."""
    layout = humanoid_layout()
    torch.manual_seed(0)
    model = delan_inverse(layout, hidden=16, translation_invariant=True).double()
    plain = delan_inverse(layout, hidden=16).double()
    assert model.mechanics.features.n_features == plain.mechanics.features.n_features - 1
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0.0, 0.05)
        model.mechanics.height_weight.fill_(3.0)
        model.mechanics.energy_scale.fill_(50.0)
    q, qd, qdd = random_batch(layout, 4)
    moved = q.clone()
    moved[:, :3] += torch.tensor([10.0, -3.0, 0.7], dtype=q.dtype)
    tau = model.predict_torque(q, qd, qdd)
    torch.testing.assert_close(model.predict_torque(moved, qd, qdd), tau)
    terms = model.dynamics.terms(q, qd)
    V_moved = model.dynamics.terms(moved, qd).potential_energy
    torch.testing.assert_close(V_moved - terms.potential_energy, q.new_full((4,), 0.7 * 150.0))
    # the gravity force along the height: 150 from w z plus the network's V (no z input)
    without_w = terms.gravity[:, 2] - 150.0
    with torch.no_grad():
        model.mechanics.height_weight.zero_()
    torch.testing.assert_close(model.dynamics.terms(q, qd).gravity[:, 2], without_w)
    mlp = MLPInverse(layout, hidden=8, root_height=False)
    assert mlp.n_in == MLPInverse(layout, hidden=8).n_in - 1


def test_height_weight_starts_at_the_bodys_weight(clip_folder) -> None:
    """w starts at the mean vertical root force (m g for a body whose mean vertical
    acceleration is ~0), once: a second fit_normalization keeps the learned w."""
    data = build_dataset(
        clips=(CLIP,), val_clips=(), folders=[clip_folder], download=False, samples_per_clip=200
    ).data.select(keys.Q, keys.QD, keys.QDD, keys.TAU)
    model = delan_inverse(humanoid_layout(), hidden=16, translation_invariant=True).double()
    model.fit_normalization(data)
    field = model.mechanics
    w = float(field.height_weight.detach() * field.energy_scale)
    assert w == pytest.approx(float(data[keys.TAU][:, 2].mean()))
    with torch.no_grad():
        field.height_weight.add_(0.25)
    learned = float(field.height_weight.detach())
    model.fit_normalization(data)
    assert float(field.height_weight.detach()) == learned


def test_tree_sparse_mass_matrix_couples_only_one_branch() -> None:
    """With humanoid_CMU's dof_parentid, M = U U^T has MuJoCo's own sparsity: every entry
    that is nonzero in mj_fullM is allowed, entries between two branches are exactly 0; M is
    positive definite and forward dynamics inverts inverse dynamics."""
    mj = mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml()))
    parents = mj.dof_parentid.tolist()
    rows, cols = tree_entries(parents)
    assert bool((rows < cols).all())
    same_branch = torch.eye(mj.nv, dtype=torch.bool)
    same_branch[rows, cols] = True
    same_branch |= same_branch.clone().T
    data = mujoco.MjData(mj)
    data.qpos[7:] = np.random.default_rng(0).normal(0.0, 0.3, mj.nq - 7)
    mujoco.mj_forward(mj, data)
    true_m = np.zeros((mj.nv, mj.nv))
    mujoco.mj_fullM(mj, data, true_m)
    assert not (np.abs(true_m) > 1e-12)[~same_branch.numpy()].any()
    assert int(same_branch.sum()) < mj.nv * mj.nv / 2  # a real restriction (hands, feet apart)
    torch.manual_seed(0)
    model = delan_inverse(humanoid_layout(), hidden=16, dof_parents=parents).double()
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0.0, 0.05)
    q, qd, qdd = random_batch(humanoid_layout(), 3)
    M = model.mass_matrix(q).detach()
    assert float(M[:, ~same_branch].abs().max()) == 0.0
    assert bool((torch.linalg.cholesky_ex(M).info == 0).all())
    tau = model.predict_torque(q, qd, qdd)
    torch.testing.assert_close(model.dynamics.forward_dynamics(q, qd, tau), qdd)


def test_tree_entries_of_a_small_tree() -> None:
    """DoFs 0-1-2 in a chain and 3-4 a second branch off 0: U's entries are the ancestors."""
    rows, cols = tree_entries([-1, 0, 1, 0, 3])
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [
        (0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (3, 4)
    ]  # fmt: skip
    with pytest.raises(ValueError, match="parents first"):
        tree_entries([-1, 2, 0])


def test_still_joints_enter_to_first_order() -> None:
    """A coordinate held still in the data: M does not depend on it, V is linear in it, so
    its generalized force s G(q) is what the gravity of a finite difference of V says."""
    layout = humanoid_layout()
    torch.manual_seed(0)
    model = delan_inverse(layout, hidden=16, still_first_order=True).double()
    field = model.mechanics
    q, qd, qdd = random_batch(layout, 3)
    fit_q = q[:1].repeat(50, 1) + 0.2 * torch.randn(50, layout.nq, dtype=q.dtype)
    fit_q[:, 7 + 41], fit_q[:, 7 + 55] = 0.3, -0.1  # two hinges that never move (v = q - 1)
    field.features.standardize(fit_q)
    assert field.features.plain_still.sum() == 2
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0.0, 0.05)
        field.still_scale.uniform_(0.5, 2.0)
    moved = q.clone()
    moved[:, 7 + 41] += 0.4
    torch.testing.assert_close(model.mass_matrix(moved), model.mass_matrix(q))
    terms = model.dynamics.terms(q, qd)
    eps = 1e-6
    for v in (6 + 41, 6 + 55, 6 + 3):
        up, down = q.clone(), q.clone()
        up[:, v + 1] += eps
        down[:, v + 1] -= eps
        dv = model.dynamics.terms(up, qd).potential_energy
        dv = (dv - model.dynamics.terms(down, qd).potential_energy) / (2 * eps)
        torch.testing.assert_close(terms.gravity[:, v], dv, rtol=1e-6, atol=1e-8)
    second = model.dynamics.terms(moved, qd).gravity[:, 6 + 41]  # V linear in the held q
    torch.testing.assert_close(second, terms.gravity[:, 6 + 41])


def test_evaluation_keeps_no_autograd_graph(clip_folder) -> None:
    """Per-epoch errors are kept for every epoch: they must not hold the evaluation's graph
    (that leaked ~0.8 GB per epoch on the default mocap set)."""
    data = build_dataset(
        clips=(CLIP,), val_clips=(), folders=[clip_folder], download=False, samples_per_clip=50
    ).data
    model = delan_inverse(humanoid_layout(), hidden=8).double()
    model.fit_normalization(data)
    errors = evaluate_torques(model, data.select(keys.Q, keys.QD, keys.QDD, keys.TAU))
    for t in (errors.dof_mse, errors.dof_mse_si, errors.dof_var):
        assert not t.requires_grad and t.grad_fn is None


# ---------------------------------------------------------------- errors


def fit_cli(clip_folder: Path, run_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    """`python -m mbrl_delan.fit` on the small setting with an MLP, in `run_dir`."""
    cmd = [sys.executable, "-m", "mbrl_delan.fit", *small_overrides(clip_folder), "model=mlp"]
    cmd += [*overrides, f"hydra.run.dir={run_dir}"]
    env = {**os.environ, "WANDB_MODE": "disabled"}
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300, cwd=ROOT)


def test_bad_config_value_exits_2_naming_the_key(clip_folder, tmp_path: Path) -> None:
    out = fit_cli(clip_folder, tmp_path / "bad", "model.hidden=0")
    assert out.returncode == 2, out.stdout + out.stderr
    assert "model.hidden=0" in out.stdout + out.stderr
    assert "Traceback" not in out.stdout + out.stderr
    assert not (tmp_path / "bad" / "metrics.jsonl").exists()


def test_new_fit_in_a_used_run_dir_is_refused_and_leaves_it_as_it_was(
    fitted, clip_folder, tmp_path: Path
) -> None:
    run_dir = tmp_path / "used"
    shutil.copytree(fitted["mlp"], run_dir)
    own = [p for p in run_dir.rglob("*") if p.is_file() and ".hydra" not in p.parts]
    before = {p: p.read_bytes() for p in own if p.suffix != ".log"}
    out = fit_cli(clip_folder, run_dir)
    text = out.stdout + out.stderr
    assert out.returncode == 2, text
    assert f"{run_dir} already holds a run (config.yaml" in text and "Traceback" not in text
    assert {p: p.read_bytes() for p in before} == before
    assert run_dir / "model.pt" in before


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("data.torques=magic", "data.torques='magic' is not valid; choose one of: inverse, pd"),
        ("dtype=float16", "choose one of: float32, float64"),
        ("device=tpu", "device='tpu'"),
        ("epochs=0", "epochs=0"),
        ("loss.std_floor=2", "loss.std_floor=2"),
        ("data.val_clips=[02_01]", "not in data.clips"),
        ("data.clips=[131_03]", "quote names like '131_03'"),
        ("data.pd.gains=magic", "data.pd.gains='magic'"),
        ("model.activation=sigmoid", "model.activation='sigmoid'"),
        ("translation_invariant=maybe", "translation_invariant: Value 'maybe' is not a valid bool"),
        ("lr_schedule=linear", "lr_schedule='linear' is not valid; choose one of: constant"),
        ("model.tree_sparse=maybe", "model.tree_sparse: Value 'maybe' is not a valid bool"),
        ("seed=abc", "seed: Value 'abc' of type 'str' could not be converted to Integer"),
        ("seed=-1", "seed=-1 is not valid; it must be a whole number >= 0"),
        ("threads=1.5", "threads: Value '1.5' of type 'float' could not be converted"),
        ("lr=nan", "lr=nan is not valid"),
        ("eval_every=-1", "eval_every=-1 is not valid"),
        ("data.skip_bad_clips=maybe", "data.skip_bad_clips: Value 'maybe' is not a valid bool"),
    ],
)
def test_config_values_are_checked(clip_folder, override: str, expected: str) -> None:
    cfg = config(*small_overrides(clip_folder), "data.torques=pd", override)
    with pytest.raises(ConfigError, match=None) as err:
        validate_fit_config(cfg)
    assert expected in str(err.value)


def test_missing_clip_names_every_place_looked(clip_folder, tmp_path: Path) -> None:
    cfg = config(*small_overrides(clip_folder), f"data.clips=[{CLIP},09_77]", "data.val_clips=[]")
    with pytest.raises(ClipNotFoundError) as err:
        run(cfg, tmp_path / "run")
    assert str(clip_folder / "09_77.amc") in str(err.value)
    assert "downloading is off" in str(err.value)


def test_nan_in_a_saved_dataset_is_named(clip_folder, tmp_path: Path) -> None:
    ds = build_dataset(
        clips=(CLIP,), val_clips=(), folders=[clip_folder], download=False, samples_per_clip=40
    )
    ds.data[keys.QDD][7, 3] = float("nan")
    path = save_dataset(ds, tmp_path / "dataset")
    cfg = config(*small_overrides(clip_folder), f"data.dataset_dir={path}")
    with pytest.raises(NonFiniteDataError) as err:
        run(cfg, tmp_path / "run")
    assert "'qdd'" in str(err.value) and "(7, 3)" in str(err.value)


def test_eval_every_zero_evaluates_the_splits_after_the_last_epoch_only(
    clip_folder, tmp_path: Path
) -> None:
    overrides = [*small_overrides(clip_folder), "model=mlp", "epochs=3", "eval_every=0"]
    run(config(*overrides), tmp_path / "run")
    recs = records(tmp_path / "run")
    assert [r["epoch"] for r in recs] == [1, 2, 3]
    assert all("train_loss" in r for r in recs)
    assert [f"{split}_mse" in r for r in recs for split in SPLITS] == [False] * 6 + [True] * 3
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["final"]["val_clip"]["mse"] == pytest.approx(recs[-1]["val_clip_mse"])


def test_test_clips_form_a_split_of_their_own(clip_folder, tmp_path: Path) -> None:
    overrides = [*small_overrides(clip_folder), "model=mlp", "epochs=1"]
    clips = [f"data.clips=[{CLIP},{HELD_OUT},{TEST}]", f"data.test_clips=[{TEST}]"]
    summary = run(config(*overrides, *clips), tmp_path / "run")
    assert summary["val_clips"] == [HELD_OUT] and summary["test_clips"] == [TEST]
    assert set(summary["final"]) == {"train", "val_time", "val_clip", "test"}
    assert list(summary["final"]["test"]["clips"]) == [TEST]
    assert list(summary["final"]["val_clip"]["clips"]) == [HELD_OUT]
    assert summary["samples"]["test"] == summary["samples"]["val_clip"] > 0  # the same clip
    assert summary["final"]["test"]["mse"] == pytest.approx(summary["final"]["val_clip"]["mse"])
    with pytest.raises(ConfigError, match="also in data.val_clips"):
        validate_fit_config(config(*overrides, *clips, f"data.val_clips=[{HELD_OUT},{TEST}]"))


def test_a_chain_gets_the_dense_factor_and_a_tree_the_sparse_one() -> None:
    from mbrl_delan.conf.inverse import branches

    humanoid = mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml())).dof_parentid.tolist()
    assert branches(humanoid) and branches([-1, -1])  # a tree; a forest
    assert not branches([-1, 0, 1, 2]) and not branches(None)  # a chain; no tree known


def test_bad_clips_are_left_out_and_listed_when_asked(clip_folder, tmp_path: Path) -> None:
    """data.skip_bad_clips=true: a malformed clip and one too short to filter are left out
    and listed with their errors in summary.json; without it the first one stops the fit."""
    folder = tmp_path / "clips"
    shutil.copytree(clip_folder, folder)
    lines = (DATA / f"{CLIP}.amc").read_text(encoding="latin-1").splitlines()
    (folder / "09_97.amc").write_text("\n".join(lines[:60]) + "\nlfemur 1.0\n")  # cut mid-frame
    first = [i for i, line in enumerate(lines) if line.strip() == "4"][0]  # frames 1-3 kept
    (folder / "09_96.amc").write_text("\n".join(lines[:first]) + "\n")
    overrides = [
        *small_overrides(folder),
        "model=mlp",
        f"data.clips=[{CLIP},09_97,09_96,{HELD_OUT}]",
    ]
    with pytest.raises(MocapFormatError, match="09_97.amc"):
        run(config(*overrides), tmp_path / "strict")
    run(config(*overrides, "data.skip_bad_clips=true"), tmp_path / "run")
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    skipped = summary["skipped_clips"]
    assert sorted(skipped) == ["09_96", "09_97"]
    assert "09_97.amc" in skipped["09_97"] and "too few" in skipped["09_96"]
    assert summary["samples"]["val_clip"] == 120 and summary["samples"]["train"] > 50


@pytest.mark.parametrize(("frames", "why"), [(3, "3 frames are too few"), (20, "too short")])
def test_a_clip_too_short_is_one_line_and_exit_2(
    clip_folder, tmp_path: Path, run_main, frames: int, why: str
) -> None:
    """A clip of 3 or 20 frames: `file: why` in one line, exit 2, as other malformed clips."""
    from mbrl_delan.fit import main

    folder = tmp_path / "clips"
    shutil.copytree(clip_folder, folder)
    lines = (DATA / f"{CLIP}.amc").read_text(encoding="latin-1").splitlines()
    cut = [i for i, line in enumerate(lines) if line.strip() == str(frames + 1)][0]
    (folder / "09_96.amc").write_text("\n".join(lines[:cut]) + "\n")
    args = [*small_overrides(folder), "model=mlp", f"data.clips=[{CLIP},09_96,{HELD_OUT}]"]
    code, text = run_main(main, *args, f"hydra.run.dir={tmp_path / 'run'}")
    assert code == 2 and "Traceback" not in text, text
    assert f"bad data: {folder / '09_96.amc'}: " in text and why in text, text


def test_divergence_is_named(clip_folder, tmp_path: Path) -> None:
    cfg = config(*small_overrides(clip_folder), "model=mlp", "lr=1e30", "max_grad_norm=null")
    with pytest.raises(TrainingDivergedError) as err:
        run(cfg, tmp_path / "run")
    assert err.value.metric in ("train_loss", "grad_norm")


# ---------------------------------------------------------------- the loop starts from a fit


def loop_model_config(*overrides: str) -> DictConfig:
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=["env=cmu_track", *overrides])


def test_mocap_fit_keeps_its_mass_matrix_conditioned_off_its_data(fitted) -> None:
    """The default fit's M = L L^T + humanoid_CMU's rotor inertia stays positive definite,
    its eigenvalues near the hinges' armature of 0.01 kg m^2 or above (the root's 6 DoFs
    have none, so not exactly: half of it is the bound), and about as well conditioned as
    MuJoCo's own M at random poses far from the one clip it saw (without the armature:
    smallest eigenvalue ~3e-5, condition ~1e6 here); the summary reports the same check."""
    fit_cfg, inverse = load_fit_model(fitted["delan"])
    assert fit_cfg.model.armature  # the default
    mj_model = mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml()))
    q = random_poses(mj_model, 64)
    eigenvalues = torch.linalg.eigvalsh(inverse.double().mass_matrix(q))  # (64, 62)
    assert eigenvalues[:, 0].min() >= 0.005
    data, full = mujoco.MjData(mj_model), np.zeros((mj_model.nv, mj_model.nv))
    mujoco_condition = []
    for pose in q.numpy():
        data.qpos[:] = pose
        mujoco.mj_forward(mj_model, data)
        mujoco.mj_fullM(mj_model, data, full)
        values = np.linalg.eigvalsh(full)
        mujoco_condition.append(values[-1] / values[0])
    condition = eigenvalues[:, -1] / eigenvalues[:, 0]
    assert condition.max() <= 10 * max(mujoco_condition)
    check = json.loads((fitted["delan"] / "summary.json").read_text())["mass_matrix_random_poses"]
    assert check["positive_definite_fraction"] == 1.0 and check["min_eigenvalue"] >= 0.005
    assert check["max_condition"] <= 10 * max(mujoco_condition)


def test_loop_delan_starts_from_the_mocap_fit_and_keeps_it(fitted) -> None:
    """model.init_from alone: the loop's DeLaN (56 motors, a residual force) takes the fit's
    structure and gives the mocap DeLaN's inverse dynamics, M, c, g and friction at round 0
    (every generalized force as its action), and its first refit's normalisation leaves
    them as they are."""
    _, inverse = load_fit_model(fitted["delan"])
    layout = joint_layout(mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml())))
    cfg = with_fit_structure(loop_model_config(f"model.init_from={fitted['delan']}"))
    assert (cfg.model.hidden, cfg.model.armature, cfg.model.tree_sparse) == (16, True, True)
    system = make_env_parts("cmu_track", task_options=TEST_CLIP).system
    model = build_model(cfg.model, system).double()
    start_mechanics(cfg.model, model, system)
    q, qd, qdd = random_batch(layout, 16)
    expected, got = inverse.delan.double().terms(q, qd), model.terms(q, qd)
    for name in ("mass_matrix", "coriolis", "gravity", "dissipation"):
        torch.testing.assert_close(getattr(got, name), getattr(expected, name), msg=name)
    torch.testing.assert_close(
        model.dynamics.inverse_dynamics(q, qd, qdd), inverse.predict_torque(q, qd, qdd)
    )
    assert model.dynamics.actuation.shape == (62, 56)  # its own B: the 56 motors
    # the loop's first refit sets loss scales and the residual's statistics, not M or V
    n = 32
    data = TensorDict(
        {
            keys.Q: q.repeat(2, 1), keys.QD: qd.repeat(2, 1),
            keys.ACTION: torch.randn(n, 56, dtype=torch.float64),
            keys.NEXT: {keys.Q: q.repeat(2, 1), keys.QD: 1.1 * qd.repeat(2, 1)},
        },
        batch_size=[n],
    )  # fmt: skip
    model.fit_normalization(data)
    after = model.terms(q, qd)
    torch.testing.assert_close(after.mass_matrix, expected.mass_matrix)
    torch.testing.assert_close(after.gravity, expected.gravity)


def test_init_from_names_what_does_not_fit(fitted, tmp_path: Path) -> None:
    cases = [
        ((f"model.init_from={fitted['mlp']}",), "that fit is model=mlp"),
        ((f"model.init_from={tmp_path}",), "no config.yaml in"),
        (("model=ensemble", f"+model.init_from={fitted['delan']}"), "for model=delan"),
    ]  # fmt: skip
    for overrides, expected in cases:
        with pytest.raises(ConfigError, match=re.escape(expected)):
            with_fit_structure(loop_model_config(*overrides))
    # a DeLaN built with another structure than the fit's is named, with the overrides
    system = make_env_parts("cmu_track", task_options=TEST_CLIP).system
    cfg = loop_model_config(f"model.init_from={fitted['delan']}")
    with pytest.raises(ConfigError, match=re.escape("add model.hidden=16 model.coulomb=false")):
        start_mechanics(cfg.model, build_model(cfg.model, system), system)
