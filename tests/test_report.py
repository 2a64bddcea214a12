"""`python -m mbrl_delan.report`: statistics over seeds, incomplete runs listed, not dropped."""

import json
from pathlib import Path

from mbrl_delan.report import find_runs, main, table


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


def test_table_gives_mean_and_std_over_seeds(tmp_path: Path) -> None:
    make_run(tmp_path, "a", summary(0, 40.0, 40.0))
    make_run(tmp_path, "b", summary(1, 30.0, 40.0))
    runs, incomplete = find_runs([tmp_path])
    assert not incomplete
    row = table(runs).splitlines()[2]
    assert "| pendulum | delan | mppi | 0,1 |" in row
    assert "35 ± 5" in row  # mean and population std of 40 and 30
    assert "0.875 ± 0.12" in row


def test_incomplete_runs_are_listed(tmp_path: Path, caplog) -> None:
    make_run(tmp_path, "done", summary(0, 40.0, 40.0))
    crashed = make_run(tmp_path, "crashed", None)
    runs, incomplete = find_runs([tmp_path])
    assert len(runs) == 1 and incomplete == [crashed]
    caplog.set_level("INFO")
    assert main([str(tmp_path)]) == 0
    assert "incomplete run" in caplog.text and "crashed" in caplog.text


def test_missing_folder_is_an_error(tmp_path: Path) -> None:
    assert main([str(tmp_path / "nope")]) == 2


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
