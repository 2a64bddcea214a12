"""MJCF models shipped by other packages: gymnasium's Humanoid-v5 and dm_control's CMU humanoid;
and Humanoid-v5 in an exoskeleton (`humanoid_v5_exo_xml`), written from it.

Both are loaded with plain mujoco; the packages are located, not imported (dm_control's
simulator does not work with mujoco 4, and importing gymnasium's envs is not needed).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np


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


@dataclass(frozen=True)
class Exoskeleton:
    """What `humanoid_v5_exo_xml` adds to Humanoid-v5: springs at the hips and knees (each
    joint's `stiffness` in N m/rad pulling towards `rest`, rad, MuJoCo's ``springref``), on
    top of the MJCF's own springs, and Coulomb friction at every hinge (MuJoCo's
    ``frictionloss``, N m)."""

    stiffness: tuple[tuple[str, float, float], ...] = (
        ("hip_x", 20.0, 0.0), ("hip_z", 20.0, 0.0), ("hip_y", 100.0, -1.0), ("knee", 60.0, -1.2),
    )  # (joint suffix, added stiffness, rest)  # fmt: skip
    frictionloss: float = 5.0


EXOSKELETON = Exoskeleton()


def add_exoskeleton(
    spec: mujoco.MjSpec, exo: Exoskeleton = EXOSKELETON, springs: bool = True,
    friction: bool = True,
) -> None:  # fmt: skip
    """`exo`'s springs and hinge friction added to a Humanoid-v5 spec in place (either alone
    where the other is off)."""
    unit = 180.0 / np.pi if spec.compiler.degree else 1.0  # the MJCF's angles: Humanoid-v5 degrees
    for joint in spec.joints:
        if joint.type != mujoco.mjtJoint.mjJNT_HINGE:
            continue
        if friction:
            joint.frictionloss = exo.frictionloss
        for suffix, stiffness, rest in exo.stiffness if springs else ():
            if joint.name.endswith(suffix):
                coefficients = np.array(joint.stiffness, dtype=float)  # [linear, higher orders]
                own, reference = float(coefficients[0]), float(joint.springref)
                total = own + stiffness  # both springs as one about their weighted rest
                coefficients[0] = total
                joint.stiffness = coefficients
                joint.springref = (own * reference + stiffness * rest * unit) / total


def humanoid_v5_exo_xml(exo: Exoskeleton = EXOSKELETON) -> Path:
    """Humanoid-v5 in an exoskeleton (`Exoskeleton`): its MJCF written once per content to the
    system's temporary folder, for the env's physics; models of it get the plain MJCF, so no
    inertial parameter can express the difference."""
    spec = mujoco.MjSpec.from_file(str(humanoid_v5_xml()))
    add_exoskeleton(spec, exo)
    text = spec.to_xml()
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    path = Path(tempfile.gettempdir()) / "mbrl_delan" / f"humanoid_exo_{digest}.xml"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(text)
        os.replace(tmp, path)
    return path
