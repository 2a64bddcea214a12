"""The installed package: console scripts, each entry point's --help, the optional extras.

(The wheel itself is built, installed in a fresh venv outside the repository and run by
`.ci/run`; these tests run in the editable install.)
"""

from __future__ import annotations

import importlib
import inspect
import re
import sys
import tomllib
from pathlib import Path

import pytest

from mbrl_delan import bench, fit, train

ROOT = Path(__file__).resolve().parents[1]


def test_console_scripts_name_the_entry_points_mains() -> None:
    """Each script is an entry point's `main`, which takes no required argument and returns
    None or an exit code (a script's return value becomes its exit status)."""
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == {
        f"mbrl-delan-{n}" for n in ("train", "fit", "bench", "report", "evaluate", "rescore")
    }
    for name, target in scripts.items():
        module, function = target.split(":")
        main = getattr(importlib.import_module(module), function)
        assert module == f"mbrl_delan.{name.removeprefix('mbrl-delan-')}" and function == "main"
        params = inspect.signature(main).parameters.values()
        assert all(p.default is not inspect.Parameter.empty for p in params), name
        assert inspect.signature(main).return_annotation in ("None", "int"), name


def _groups(help_text: str) -> dict[str, list[str]]:
    """The 'Configuration groups' section of Hydra's --help: group -> options."""
    section = help_text.split("== Configuration groups ==")[1].split("== Config ==")[0]
    found = re.findall(r"^(\w[\w/]*): (.*)$", section, flags=re.MULTILINE)
    return {group: options.split(", ") for group, options in found}


@pytest.mark.parametrize(
    ("main", "groups"),
    [
        (train.main, {"env", "logger", "model", "plan", "planner", "tuning", "plan_tuning"}),
        (fit.main, {"data", "logger", "model"}),
        (bench.main, {"suite"}),
    ],
    ids=["train", "fit", "bench"],
)
def test_help_lists_only_the_entry_points_own_groups_and_real_choices(
    main, groups: set[str], run_main
) -> None:
    code, text = run_main(main, "--help")
    assert code == 0, text
    listed = _groups(text)
    assert set(listed) == groups, listed
    for group, options in listed.items():
        assert options and not any(o.startswith("base_") for o in options), (group, options)
    if "env" in listed:
        assert {"pendulum", "humanoid_stand", "cmu_track"} <= set(listed["env"])


def test_without_the_mocap_extra_cmu_runs_stop_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, run_main
) -> None:
    """dm_control (the `mocap` extra) ships humanoid_CMU.xml: without it, env=cmu_track and
    the mocap fit end with one line naming the extra, exit 2, and leave no folder."""
    monkeypatch.setitem(sys.modules, "dm_control", None)  # find_spec: not installed
    hint = "dm_control is not installed; it ships humanoid_CMU.xml: pip install 'mbrl_delan[mocap]'"
    code, text = run_main(
        train.main, "env=cmu_track", "logger=none", f"hydra.run.dir={tmp_path / 't'}"
    )
    assert code == 2 and f"missing package: {hint}" in text and "Traceback" not in text, text
    assert not (tmp_path / "t").exists()
    code, text = run_main(fit.main, "logger=none", f"hydra.run.dir={tmp_path / 'f'}")
    assert code == 2 and f"missing package: {hint}" in text and "Traceback" not in text, text
    assert not (tmp_path / "f").exists()
