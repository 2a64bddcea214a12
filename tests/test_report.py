"""`python -m mbrl_delan.report`: statistics over seeds, incomplete runs listed, not dropped."""

import csv
import json
import math
from pathlib import Path

import pytest

from mbrl_delan.report import (
    _oracles,
    curves,
    find_runs,
    group_label,
    main,
    mcnemar_exact,
    mean_ci,
    run_dirs,
    steps_to_fraction,
    table,
    wilson_interval,
)
from mbrl_delan.sweep import write_crash


def make_run(root: Path, name: str, summary: dict | None) -> Path:
    run = root / name
    run.mkdir(parents=True)
    (run / "config.yaml").write_text("seed: 0\n")
    if summary is not None:
        (run / "summary.json").write_text(json.dumps(summary))
    return run


def summary(seed: int, ret: float, oracle: float) -> dict:
    return {
        "env": "pendulum",
        "model": "delan",
        "planner": "mppi",
        "seed": seed,
        "env_steps": 700,
        "eval_return_mean": ret,
        "oracle_return_mean": oracle,
        "fraction_of_oracle": ret / oracle,
        "wall_time_s": 100.0,
    }


def test_table_gives_mean_and_ci_over_seeds(tmp_path: Path) -> None:
    make_run(tmp_path, "a", summary(0, 40.0, 40.0))
    make_run(tmp_path, "b", summary(1, 30.0, 40.0))
    runs, incomplete = find_runs([tmp_path])
    assert not incomplete
    row = table(runs).splitlines()[2]
    assert "| pendulum | delan | mppi | scratch |  | 0,1 | 2 |" in row
    # returns 40, 30: s = 7.071, t_{0.975, 1} = 12.706, half-width 12.706 * 7.071 / sqrt(2) = 63.5
    assert "35 ± 64" in row
    # fractions 1.0, 0.75: s = 0.1768, half-width 12.706 * 0.1768 / sqrt(2) = 1.59
    assert "0.875 ± 1.6" in row


def test_wilson_and_mcnemar_of_worked_cases() -> None:
    """0 of 20: the Wilson interval's upper end z^2 / (n + z^2) = 3.8415 / 23.8415 = 0.1611;
    10 of 20: 0.5 +- z sqrt(n / 4) / (n + z^2) = 0.5 +- 0.2005. McNemar on 20 discordant
    episodes all one way: 2 * 0.5^20; on 3 against 1: 2 * (1 + 4) / 16 = 0.625."""
    low, high = wilson_interval(0, 20)
    assert low == pytest.approx(0.0, abs=1e-12) and high == pytest.approx(0.16113, abs=1e-4)
    low, high = wilson_interval(10, 20)
    assert (low, high) == pytest.approx((0.2995, 0.7005), abs=1e-3)
    assert mcnemar_exact(20, 0) == pytest.approx(2 * 0.5**20)
    assert mcnemar_exact(3, 1) == pytest.approx(0.625)
    assert mcnemar_exact(0, 0) == 1.0


def test_paired_runs_pool_their_falls_over_seeds(tmp_path: Path) -> None:
    """Two seeds of 4 paired episodes (episode length 100): the model fell in 1 and 2 of
    them, the oracle in 0 and 2 (one of them with the model); pooled 3/8 against 2/8, the
    model alone fell in 2, the oracle alone in 1."""
    for seed, ours, theirs in ((0, [100, 40, 100, 100], [100] * 4),
                               (1, [10, 100, 20, 100], [100, 100, 50, 30])):  # fmt: skip
        run = make_run(tmp_path, f"s{seed}", summary(seed, 1.0, 1.0))
        (run / "config.yaml").write_text(f"seed: {seed}\nenv:\n  episode_len: 100\n")
        record = {"iteration": 1, "eval_episode_steps": ours, "oracle_episode_steps": theirs}
        (run / "metrics.jsonl").write_text(json.dumps(record) + "\n")
    runs, _ = find_runs([tmp_path])
    row = table(runs).splitlines()[2]
    low, high = wilson_interval(3, 8)
    assert f"3/8 ({low:.0%}-{high:.0%})" in row and "2/8" in row
    assert f"{mcnemar_exact(2, 1):.2g} (2 / 1)" in row


def _paired_run(root: Path, name: str, seed: int, ours: list[int], theirs: list[int]) -> None:
    run = make_run(root, name, summary(seed, 1.0, 1.0))
    (run / "config.yaml").write_text(f"seed: {seed}\nenv:\n  episode_len: 100\n")
    record = {"iteration": 1, "eval_episode_steps": ours, "oracle_episode_steps": theirs}
    (run / "metrics.jsonl").write_text(json.dumps(record) + "\n")


def test_page_gets_the_paired_and_other_runs_tables_between_its_markers(tmp_path: Path) -> None:
    """`--page`: the paired runs' falls (1 of 4 against 0 of 4), the unpaired run's fraction of
    the oracle (0.5) in a table of its own, and the command replace what lies between the
    markers; the text around them stays."""
    _paired_run(tmp_path / "runs", "s0", 0, [100, 40, 100, 100], [100] * 4)
    make_run(tmp_path / "runs", "unpaired", summary(1, 0.5, 1.0))
    page = tmp_path / "page.md"
    page.write_text("# Results\n\n<!-- report:begin -->\nold\n<!-- report:end -->\n\nafter\n")
    assert main([str(tmp_path / "runs"), "--page", str(page)]) == 0
    text = page.read_text()
    low, high = wilson_interval(1, 4)
    assert text.startswith(
        "# Results\n\n<!-- report:begin -->\n```bash\npython -m mbrl_delan.report"
    )
    assert f"| pendulum | delan |  | 0 | 1/4 ({low:.0%}-{high:.0%}) | 0/4 " in text
    assert "old" not in text and text.endswith("<!-- report:end -->\n\nafter\n")
    assert "| pendulum | delan | mppi |  | 1 | 0.5 ± n/a | 0.5 ± n/a | 700 |" in text
    assert len([line for line in text.splitlines() if line.startswith("| pendulum")]) == 2


def test_page_without_markers_is_one_line_and_left_as_it_was(tmp_path: Path, caplog) -> None:
    _paired_run(tmp_path / "runs", "s0", 0, [100] * 4, [100] * 4)
    page = tmp_path / "page.md"
    page.write_text("# Results\n")
    assert main([str(tmp_path / "runs"), "--page", str(page)]) == 2
    assert page.read_text() == "# Results\n" and "no <!-- report:begin -->" in caplog.text


def test_the_results_pages_hold_what_the_records_give(tmp_path: Path) -> None:
    """The docs' tables made from the records (docs/humanoid_results.md's, docs/results.md's)
    are what their own command makes of the records under docs/records/loops/ now (rerun on
    a copy of the page, from the repository)."""
    repo = Path(__file__).resolve().parents[1]
    for page in ("humanoid_results.md", "results.md"):
        _check_page(repo, repo / "docs" / page, tmp_path)


def _check_page(repo: Path, page: Path, tmp_path: Path) -> None:
    import os
    import shlex

    text = page.read_text(encoding="utf-8")
    block = text[text.index("<!-- report:begin -->") : text.index("<!-- report:end -->")]
    command = shlex.split(block.split("```bash\n")[1].split("\n")[0])
    roots = command[3 : command.index("--page")]
    copy = tmp_path / "page.md"
    copy.write_text(text, encoding="utf-8")
    cwd = os.getcwd()
    try:
        os.chdir(repo)
        assert main([*roots, "--page", str(copy)]) == 0
    finally:
        os.chdir(cwd)
    made = copy.read_text(encoding="utf-8").replace(str(copy), f"docs/{page.name}")
    assert made == text, f"rerun the command in docs/{page.name}'s table from the records"


def test_repeated_runs_of_a_seed_count_once(tmp_path: Path, caplog) -> None:
    """Four identical runs of seed 0 and one of seed 1 are two samples, not five: the row is
    the two seeds' (n 2, the same interval), and a warning names the repeats."""
    for name in "abcd":
        make_run(tmp_path / "repeats", name, summary(0, 40.0, 40.0))
    make_run(tmp_path / "repeats", "e", summary(1, 30.0, 40.0))
    make_run(tmp_path / "two", "a", summary(0, 40.0, 40.0))
    make_run(tmp_path / "two", "b", summary(1, 30.0, 40.0))
    repeated, _ = find_runs([tmp_path / "repeats"])
    two, _ = find_runs([tmp_path / "two"])
    assert len(repeated) == 5
    assert table(repeated) == table(two)
    assert "| 0,1 | 2 |" in table(repeated)
    assert "seed 0 x4" in caplog.text


def test_run_dirs_behind_links_are_found_once(tmp_path: Path) -> None:
    real = make_run(tmp_path / "elsewhere", "a", summary(0, 40.0, 40.0))
    (tmp_path / "sweep").mkdir()
    (tmp_path / "sweep" / "linked").symlink_to(real.parent, target_is_directory=True)
    (tmp_path / "sweep" / "loop").symlink_to(tmp_path / "sweep", target_is_directory=True)
    found = run_dirs([tmp_path / "sweep"])
    assert [p.resolve() for p in found] == [real.resolve()]


def test_runs_started_from_a_fit_are_their_own_group(tmp_path: Path) -> None:
    """Runs of one env, model and planner, from scratch and from a mocap fit, are two rows
    (not one pooled over repeated seeds), the fit's row and line named after it."""
    for seed, ret in ((0, 40.0), (1, 30.0)):
        make_run(tmp_path, f"scratch{seed}", summary(seed, ret, 40.0))
        prior = make_run(tmp_path, f"prior{seed}", summary(seed, ret / 2, 40.0))
        (prior / "config.yaml").write_text("seed: 0\nmodel:\n  init_from: runs/fit/walks\n")
    runs, _ = find_runs([tmp_path])
    lines = table(runs).splitlines()[2:]
    assert len(lines) == 2
    assert "| delan | mppi | from walks |  | 0,1 | 2 | 17.5 ± 32 |" in lines[0]
    assert "| delan | mppi | scratch |  | 0,1 | 2 | 35 ± 64 |" in lines[1]
    label = group_label(("pendulum", "delan", "mppi", "from walks", ""))
    assert label == "delan + mppi, from walks"
    assert group_label(("pendulum", "delan", "mppi", "scratch", "")) == "delan + mppi"


def test_runs_with_two_budgets_are_two_rows_named_by_the_budget(tmp_path: Path) -> None:
    """Seeds of different budgets are not pooled: each config value that differs between
    runs (here budget.env_steps) splits them and names the row; how a run ran (threads,
    logger) does not."""
    for seed, ret in ((0, 40.0), (1, 30.0)):
        for steps in (50, 400):
            run = make_run(tmp_path, f"s{steps}_{seed}", summary(seed, ret * steps / 400, 40.0))
            config = f"seed: {seed}\nthreads: {seed + 1}\nlogger:\n  backend: none\n"
            (run / "config.yaml").write_text(config + f"budget:\n  env_steps: {steps}\n")
    runs, _ = find_runs([tmp_path])
    lines = table(runs).splitlines()[2:]
    assert len(lines) == 2
    assert "| scratch | `budget.env_steps=400` | 0,1 | 2 | 35 ± 64 |" in lines[0]
    assert "| scratch | `budget.env_steps=50` | 0,1 | 2 | 4.38 ± 7.9 |" in lines[1]
    assert {group_label(g) for g in curves(runs, "eval_return_mean")} == {
        "delan + mppi, budget.env_steps=50",
        "delan + mppi, budget.env_steps=400",
    }


def test_confidence_interval_of_known_values() -> None:
    # 1, 2, 3: mean 2, s = 1; t_{0.975, 2} = 4.303 (t table), half-width 4.303 / sqrt(3) = 2.484
    mean, half = mean_ci([1.0, 2.0, 3.0])
    assert mean == 2.0 and half == pytest.approx(4.303 / math.sqrt(3), abs=1e-3)
    # 0.5 .. 0.8: s = 0.1291; t_{0.975, 3} = 3.182, half-width 3.182 * 0.1291 / 2 = 0.2054
    assert mean_ci([0.5, 0.6, 0.7, 0.8])[1] == pytest.approx(0.2054, abs=1e-4)
    assert mean_ci([5.0]) == (5.0, None)  # one seed: no interval
    assert mean_ci([]) == (None, None)


def test_steps_to_90_percent_of_the_oracle() -> None:
    records = [
        {"iteration": 1, "env_steps": 100, "eval_return_mean": 20.0},
        {"iteration": 2, "env_steps": 200, "train_return": 50.0},  # no evaluation this round
        {"iteration": 3, "env_steps": 300, "eval_return_mean": 44.9},  # below 0.9 x 50 = 45
        {"iteration": 4, "env_steps": 400, "eval_return_mean": 45.0},  # first at 45
        {"iteration": 5, "env_steps": 500, "eval_return_mean": 30.0},
    ]
    assert steps_to_fraction(records, 50.0) == 400
    assert steps_to_fraction(records, 60.0) is None  # 54 never reached
    assert steps_to_fraction(records, None) is None
    # a negative oracle -100: within 10 % means >= -110
    assert steps_to_fraction([{"env_steps": 7, "eval_return_mean": -105.0}], -100.0) == 7


def test_incomplete_runs_are_listed(tmp_path: Path, caplog) -> None:
    make_run(tmp_path, "done", summary(0, 40.0, 40.0))
    crashed = make_run(tmp_path, "crashed", None)
    runs, incomplete = find_runs([tmp_path])
    assert len(runs) == 1 and incomplete == [crashed]
    caplog.set_level("INFO")
    assert main([str(tmp_path)]) == 0
    assert "incomplete run" in caplog.text and "crashed" in caplog.text
    assert "no summary.json" in (tmp_path / "report.md").read_text()


def test_a_run_whose_hydra_record_another_program_rewrote_is_still_found(tmp_path: Path) -> None:
    """A refused `fit` launch in a training run's dir rewrites `.hydra/config.yaml`: the run's
    own config still marks the dir as a training run, and a fit dir stays out."""
    run = make_run(tmp_path, "train_run", summary(0, 40.0, 40.0))
    (run / "config.yaml").write_text("planner:\n  name: mppi\nbudget:\n  iterations: 6\n")
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text("data:\n  name: cmu_mocap\n")
    fit = make_run(tmp_path, "fit_run", None)
    (fit / "config.yaml").write_text("data:\n  name: cmu_mocap\n")
    (fit / ".hydra").mkdir()
    (fit / ".hydra" / "config.yaml").write_text("data:\n  name: cmu_mocap\n")
    runs, incomplete = find_runs([tmp_path])
    assert [r["run_dir"] for r in runs] == [str(run)] and incomplete == []


def test_missing_folder_is_an_error(tmp_path: Path) -> None:
    assert main([str(tmp_path / "nope")]) == 2


def test_a_folder_without_runs_is_one_line_and_writes_nothing(tmp_path: Path, caplog) -> None:
    (tmp_path / "notes").mkdir()
    assert main([str(tmp_path)]) == 2
    assert f"no runs: none in {tmp_path}" in caplog.text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes"]


def test_a_torn_metrics_line_is_named_once(tmp_path: Path, caplog) -> None:
    """A run whose metrics.jsonl has a cut line: the report (which reads the file for the
    table, both figures and the reach steps) warns once, naming the line."""
    run = make_run(tmp_path, "r0", summary(0, 40.0, 42.0))
    write_metrics(run, {200: 30.0, 400: 40.0}, 42.0)
    with (run / "metrics.jsonl").open("a") as f:
        f.write('{"iteration": 5, "env_st')
    assert main([str(tmp_path)]) == 0
    warnings = [r.getMessage() for r in caplog.records if "unreadable" in r.getMessage()]
    assert warnings == [f"skipping unreadable line 5 of {run / 'metrics.jsonl'}"]


def test_a_bare_figure_name_goes_into_the_reports_folder(tmp_path: Path, monkeypatch) -> None:
    runs, elsewhere = tmp_path / "runs", tmp_path / "cwd"
    make_run(runs, "r0", summary(0, 40.0, 42.0))
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main([str(runs), "--out", str(tmp_path / "rep"), "--figure", "fig.png"]) == 0
    assert (tmp_path / "rep" / "fig.png").is_file() and not any(elsewhere.iterdir())


def test_figure_is_drawn_from_metrics(tmp_path: Path) -> None:
    for seed in (0, 1):
        run = make_run(tmp_path, f"r{seed}", summary(seed, 40.0, 42.0))
        lines = [
            {"iteration": k, "env_steps": 100 * k, "eval_return_mean": 10.0 * k + seed}
            for k in (1, 2, 3)
        ]
        (run / "metrics.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    out = tmp_path / "fig.png"
    assert main([str(tmp_path), "--figure", str(out)]) == 0
    assert out.is_file() and out.stat().st_size > 10_000
    assert (tmp_path / "returns.png").stat().st_size > 10_000


def write_metrics(run: Path, evals: dict[int, float], oracle: float) -> None:
    """Iterations at 100, 200, ... env steps; an evaluation at the steps given in ``evals``."""
    lines = []
    for k in range(1, 5):
        rec = {"iteration": k, "env_steps": 100 * k, "oracle_return_mean": oracle}
        rec |= {"model_error_1step": 1.0 / k, "model_error_hstep": 2.0 / k}
        if 100 * k in evals:
            rec["eval_return_mean"] = evals[100 * k]
        lines.append(json.dumps(rec))
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")


def test_curves_of_seeds_with_different_env_steps_share_one_grid(tmp_path: Path) -> None:
    """Episodes that end early put each seed's evaluations at other env steps; every seed
    then gives its value interpolated at the union of steps, within its own range."""
    for seed, evals in ((0, {100: 1.0, 300: 3.0}), (1, {200: 5.0, 400: 7.0})):
        write_metrics(make_run(tmp_path, f"r{seed}", summary(seed, 1.0, 10.0)), evals, 10.0)
    runs, _ = find_runs([tmp_path])
    (by_step,) = curves(runs, "eval_return_mean").values()
    assert by_step == {100: [1.0], 200: [2.0, 5.0], 300: [3.0, 6.0], 400: [7.0]}


def test_report_with_a_crashed_and_an_unfinished_run(tmp_path: Path, caplog) -> None:
    sweep = tmp_path / "sweep"
    for seed, (ret, evals) in enumerate(
        [(48.0, {200: 46.0, 400: 48.0}), (50.0, {200: 30.0, 400: 50.0}), (40.0, {400: 40.0})]
    ):
        run = make_run(sweep, f"{seed}_pendulum_delan_mppi_s{seed}", summary(seed, ret, 50.0))
        write_metrics(run, evals, 50.0)
    one = make_run(sweep, "3_pendulum_delan_cem_s0", {**summary(0, 20.0, 40.0), "planner": "cem"})
    crashed = make_run(sweep, "4_pendulum_ensemble_mppi_s0", None)
    write_metrics(crashed, {}, 50.0)
    try:
        raise ValueError("model exploded")
    except ValueError as err:
        write_crash(crashed, err)
    unfinished = make_run(sweep, "5_pendulum_ensemble_mppi_s1", None)
    (one / "wandb" / "offline-run-x" / "files").mkdir(parents=True)  # not a run of its own
    (one / "wandb" / "offline-run-x" / "files" / "config.yaml").write_text("a: 1\n")
    fit_run = tmp_path / "sweep" / "fit_run" / ".hydra"  # another program's Hydra run dir
    fit_run.mkdir(parents=True)
    (fit_run / "config.yaml").write_text("data:\n  name: x\n")

    caplog.set_level("INFO")
    out = tmp_path / "out"
    assert main([str(sweep), "--out", str(out)]) == 0

    text = (out / "report.md").read_text()
    assert f"`{crashed}`: crashed: ValueError: model exploded (after iteration 4)" in text
    assert f"`{unfinished}`: no summary.json" in text
    assert "2 incomplete" in text and "4 finished" in text and "fit_run" not in text
    assert "crashed: ValueError: model exploded" in caplog.text
    assert "| pendulum | delan | cem | scratch |  | 0 | 1 | 20 ± n/a | 0.5 ± n/a |" in text
    # steps to 45: seed 0 at 200, seed 1 at 400, seed 2 never -> mean 300 over 2 of 3
    assert " / 300 (2/3) |" in text

    with (out / "report.csv").open(newline="") as f:
        rows = {r["planner"]: r for r in csv.DictReader(f)}
    assert set(rows) == {"cem", "mppi"}
    mppi, cem = rows["mppi"], rows["cem"]
    assert mppi["seeds"] == "0 1 2" and mppi["n"] == "3" and mppi["start"] == "scratch"
    # returns 48, 50, 40: mean 46, s = 5.292, t_{0.975, 2} = 4.303 -> half-width 13.15
    assert float(mppi["eval_return_mean"]) == pytest.approx(46.0)
    assert float(mppi["eval_return_ci95"]) == pytest.approx(4.303 * 5.2915 / math.sqrt(3), 1e-3)
    assert float(mppi["fraction_of_oracle_mean"]) == pytest.approx(0.92)
    assert float(mppi["oracle_return_mean"]) == 50.0 and float(mppi["oracle_return_ci95"]) == 0
    assert float(mppi["steps_to_90_mean"]) == 300 and mppi["steps_to_90_reached"] == "2"
    assert cem["eval_return_ci95"] == "" and cem["steps_to_90_mean"] == ""
    for png in ("returns.png", "model_error.png"):
        assert (out / png).stat().st_size > 10_000


def test_report_without_finished_runs_still_writes_the_table(tmp_path: Path) -> None:
    crashed = make_run(tmp_path, "crashed", None)
    try:
        raise RuntimeError("out of memory")
    except RuntimeError as err:
        write_crash(crashed, err)
    assert main([str(tmp_path)]) == 0
    text = (tmp_path / "report.md").read_text()
    assert "| env | model | planner |" in text and "crashed: RuntimeError: out of memory" in text
    header = (tmp_path / "report.csv").read_text().splitlines()[0]
    assert header.startswith("env,model,planner,start,config,seeds,n,")


def test_report_of_a_single_run_dir_goes_to_its_report_folder(tmp_path: Path) -> None:
    run = make_run(tmp_path, "run", summary(0, 40.0, 42.0))
    assert main([str(run)]) == 0
    assert (run / "report" / "report.md").is_file() and not (run / "report.md").exists()


def test_the_oracle_line_names_the_runs_oracle_planner(tmp_path: Path) -> None:
    """An iLQR oracle (`budget.oracle_planner: ilqr` in the run's config.yaml) is drawn as iLQR,
    not as the loop's planner; without a readable config, the run's planner."""
    ilqr_run, plain_run = tmp_path / "walk", tmp_path / "stand"
    ilqr_run.mkdir()
    (ilqr_run / "config.yaml").write_text("budget:\n  oracle_planner: ilqr\n")
    runs = [
        {**summary(0, 10.0, 600.0), "env": "walk", "run_dir": str(ilqr_run)},
        {**summary(0, 10.0, 900.0), "env": "stand", "run_dir": str(plain_run)},
    ]
    assert _oracles(runs, "walk") == {"iLQR": 600.0}
    assert _oracles(runs, "stand") == {"mppi": 900.0}


def test_report_figures_have_a_panel_per_task_and_page_width_type(tmp_path: Path) -> None:
    """Two envs give two stacked panels (the figure grows in height, not width); every text
    is at least the style's minimum, written into the PNG with the figure's width."""
    from PIL import Image

    from mbrl_delan.figure_style import FONT_KEY, MIN_FONT_PT, PAGE_WIDTH_IN, WIDTH_KEY
    from mbrl_delan.report import model_error_figure, returns_figure

    for env in ("pendulum", "cartpole"):
        for seed in (0, 1):
            run = make_run(tmp_path, f"{env}{seed}", {**summary(seed, 8.0, 10.0), "env": env})
            write_metrics(run, {200: 5.0 + seed, 400: 8.0}, 10.0)
    runs, _ = find_runs([tmp_path])
    one = returns_figure([r for r in runs if r["env"] == "pendulum"], tmp_path / "one.png")
    both = returns_figure(runs, tmp_path / "r.png"), model_error_figure(runs, tmp_path / "e.png")
    for path in both:
        image = Image.open(path)
        assert float(image.info[FONT_KEY]) >= MIN_FONT_PT
        assert float(image.info[WIDTH_KEY]) == PAGE_WIDTH_IN
        assert image.width == Image.open(one).width and image.height > Image.open(one).height


def test_the_figure_legend_lies_outside_every_panel() -> None:
    from mbrl_delan.figure_style import legend_below, page_figure

    fig, axes = page_figure(4.0, 2, 1)
    for ax in axes[:, 0]:
        ax.plot([0, 1], [0, 1], label="delan + mppi")
        ax.plot([0, 1], [1, 0], label="ensemble + mppi")
    legend_below(fig)
    fig.canvas.draw()
    (legend,) = fig.legends
    assert [t.get_text() for t in legend.get_texts()] == ["delan + mppi", "ensemble + mppi"]
    box = legend.get_window_extent()
    assert all(not box.overlaps(ax.get_window_extent()) for ax in axes[:, 0])


def test_figure_titles_name_an_interval_only_where_one_is_drawn() -> None:
    """Two seeds at every step: mean and CI; at some steps: says where; one seed: no interval."""
    from mbrl_delan.report import spread_note

    group = ("pendulum", "delan", "mppi", "scratch", "")
    assert (
        spread_note({group: {15: [1.0, 2.0], 30: [2.0, 3.0]}})
        == "solid: mean and 95% CI over seeds"
    )
    assert "where two or more seeds share a step" in spread_note(
        {group: {15: [1.0, 2.0], 45: [3.0]}}
    )
    assert spread_note({group: {15: [1.0], 30: [2.0]}}) == "one run per point, no interval"


def test_the_table_goes_to_standard_output_and_the_notes_to_the_log(tmp_path: Path, capsys) -> None:
    make_run(tmp_path / "runs", "a", summary(0, 40.0, 40.0))
    make_run(tmp_path / "runs", "b", summary(1, 30.0, 40.0))
    assert main([str(tmp_path / "runs")]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("| ") and "| 0,1 | 2 |" in out
    assert "| 0,1 | 2 |" not in err
