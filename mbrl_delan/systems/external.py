"""MJCF models shipped by other packages: gymnasium's Humanoid-v5 and dm_control's CMU humanoid;
and Humanoid-v5 in an exoskeleton (`humanoid_v5_exo_xml`) and with elastic bands over two
joints each (`humanoid_v5_tendon_xml`), written from it.

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
    return _written(spec, "humanoid_exo")


@dataclass(frozen=True)
class Band:
    """An elastic band over two or more joints: MuJoCo's fixed tendon of length
    L = sum_j c_j q_j (rad) with a spring, force -k (L - rest) along it, so each joint's
    torque depends on all of its joints' angles. `joints`: (name, c_j) pairs."""

    joints: tuple[tuple[str, float], ...]
    stiffness: float  # N m/rad
    rest: float  # rad


def _leg_bands(side: str) -> tuple[Band, ...]:
    """A hamstring-like band over the hip's flexion and the knee, and one over the abdomen's
    flexion and that hip's: both stretched in the standing pose (q = 0)."""
    return (
        Band(((f"{side}_hip_y", 1.0), (f"{side}_knee", -1.0)), 60.0, -0.6),
        Band((("abdomen_y", 1.0), (f"{side}_hip_y", 1.0)), 40.0, -0.4),
    )


BANDS = (*_leg_bands("right"), *_leg_bands("left"))


def add_bands(spec: mujoco.MjSpec, bands: tuple[Band, ...] = BANDS) -> None:
    """`bands` added to a Humanoid-v5 spec in place, as fixed tendons with springs."""
    for band in bands:
        tendon = spec.add_tendon()
        tendon.name = "band_" + "_".join(name for name, _ in band.joints)
        for name, coefficient in band.joints:
            tendon.wrap_joint(name, coefficient)
        stiffness = np.zeros_like(np.array(tendon.stiffness, dtype=float))
        stiffness[0] = band.stiffness
        tendon.stiffness = stiffness
        tendon.springlength = [band.rest, band.rest]


def humanoid_v5_tendon_xml(bands: tuple[Band, ...] = BANDS) -> Path:
    """Humanoid-v5 with elastic bands over two joints each (`BANDS`), written as
    `humanoid_v5_exo_xml` is, for the env's physics; models of it get the plain MJCF, in
    which no joint's own spring can express a coupling."""
    spec = mujoco.MjSpec.from_file(str(humanoid_v5_xml()))
    add_bands(spec, bands)
    return _written(spec, "humanoid_tendon")


def _written(spec: mujoco.MjSpec, stem: str) -> Path:
    """`spec`'s MJCF written once per content to the system's temporary folder."""
    text = spec.to_xml()
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    path = Path(tempfile.gettempdir()) / "mbrl_delan" / f"{stem}_{digest}.xml"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(text)
        os.replace(tmp, path)
    return path
