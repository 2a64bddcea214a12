"""MJCF models shipped by other packages: gymnasium's Humanoid-v5 and dm_control's CMU humanoid.

Both are loaded with plain mujoco; the packages are located, not imported (dm_control's
simulator does not work with mujoco 4, and importing gymnasium's envs is not needed).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path


class MissingPackageError(ModuleNotFoundError):
    """A package that ships a model file is not installed; the message says how to add it."""


def _package_dir(package: str, hint: str) -> Path:
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise MissingPackageError(f"{package} is not installed; {hint}")
    return Path(next(iter(spec.submodule_search_locations)))


def _existing(path: Path, package: str) -> Path:
    if not path.is_file():
        raise FileNotFoundError(f"{package} has no {path}")
    return path


def humanoid_cmu_xml() -> Path:
    """dm_control's `suite/humanoid_CMU.xml` (free root + 56 hinges, nv = 62)."""
    hint = "it ships humanoid_CMU.xml: pip install 'mbrl_delan[mocap]'"
    return _existing(_package_dir("dm_control", hint) / "suite" / "humanoid_CMU.xml", "dm_control")


def humanoid_v5_xml() -> Path:
    """gymnasium's Humanoid-v5 `envs/mujoco/assets/humanoid.xml` (free root + 17 hinges)."""
    hint = "it ships humanoid.xml (pip install gymnasium==1.4.0)"
    base = _package_dir("gymnasium", hint)
    return _existing(base / "envs" / "mujoco" / "assets" / "humanoid.xml", "gymnasium")
