"""Reading Acclaim skeletons (ASF) and motions (AMC), as the CMU database ships them.

Both readers validate as they go and raise `MocapFormatError` naming the file and the line of
the first problem: an AMC frame that lacks bones (a truncated frame), a bone line whose number
of values differs from the skeleton's ``dof`` list (wrong channel count), a value that is not
a finite number, an unknown or repeated bone, frame numbers that do not count up by one.

Values are returned as they are in the file (ASF length units, degrees or radians); the
conversion to MuJoCo coordinates is `mbrl_delan.data.mocap.retarget`'s job.

Channel names are the bone name followed by the lower-case dof, ``"lfemurrx"``,
``"roottx"``, which is also how dm_control's ``humanoid_CMU.xml`` names its hinges.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

_DOFS = ("rx", "ry", "rz", "tx", "ty", "tz", "l")
_ROOT_CHANNELS = ("tx", "ty", "tz", "rx", "ry", "rz")
_ENCODING = "latin-1"  # any byte decodes; numbers are ASCII


class MocapFormatError(ValueError):
    """A malformed ASF or AMC file; the message starts with ``path:line:``."""

    def __init__(self, path: str | Path, line: int, message: str) -> None:
        self.path = Path(path)
        self.line = line
        super().__init__(f"{path}:{line}: {message}")


@dataclass(frozen=True)
class AsfBone:
    """One ``begin ... end`` block of an ASF ``:bonedata`` section."""

    name: str
    dof: tuple[str, ...]  # e.g. ("rx", "ry", "rz"); empty for bones without motion channels
    axis: tuple[float, float, float]  # orientation of the bone's local frame (ASF angle units)
    axis_order: str  # e.g. "XYZ"
    line: int  # line of the block's ``begin``


@dataclass(frozen=True)
class AsfSkeleton:
    """What the retargeting needs from an ASF file."""

    path: Path
    length_unit: float  # ``:units length``: one ASF length unit is this many inches
    degrees: bool  # ``:units angle`` is deg (True) or rad (False)
    root_order: tuple[str, ...]  # lower-case, e.g. ("tx", "ty", "tz", "rx", "ry", "rz")
    root_axis: str  # rotation order of the root's Euler angles, e.g. "XYZ"
    root_position: tuple[float, float, float]
    root_orientation: tuple[float, float, float]
    bones: dict[str, AsfBone]  # in file order

    def channels(self) -> dict[str, tuple[str, ...]]:
        """Bone -> dof names of every bone with channels, root first, as an AMC frame lists them."""
        out = {"root": self.root_order}
        out.update({name: bone.dof for name, bone in self.bones.items() if bone.dof})
        return out


@dataclass(frozen=True)
class AmcMotion:
    """The frames of an AMC file, one row per frame.

    ``values[:, i]`` is channel ``channels[i]``, in file units (ASF length units; degrees when
    ``degrees`` else radians).
    """

    path: Path
    channels: tuple[str, ...]  # (C,) "roottx", ..., "lfemurrx", ...
    values: np.ndarray  # (T, C) float64
    frames: np.ndarray  # (T,) int64 frame numbers as written in the file
    degrees: bool

    @property
    def n_frames(self) -> int:
        return int(self.values.shape[0])


def _floats(path: Path, lineno: int, tokens: list[str], what: str) -> list[float]:
    """Tokens as finite floats, or a MocapFormatError naming the bad token."""
    out = []
    for token in tokens:
        try:
            value = float(token)
        except ValueError:
            raise MocapFormatError(path, lineno, f"non-numeric value {token!r} in {what}") from None
        if not math.isfinite(value):
            raise MocapFormatError(path, lineno, f"non-finite value {token!r} in {what}")
        out.append(value)
    return out


def _axis_order(path: Path, lineno: int, token: str) -> str:
    order = token.upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise MocapFormatError(
            path, lineno, f"rotation order {token!r} is not a permutation of XYZ"
        )
    return order


def _lines(path: Path) -> list[str]:
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    return path.read_text(encoding=_ENCODING).splitlines()


def read_asf(path: str | Path) -> AsfSkeleton:
    """Read the units, the root and the bones (name, dof, axis) of an ASF skeleton."""
    path = Path(path)
    section = ""
    units: dict[str, str] = {}
    root: dict[str, list[str]] = {}
    root_line = 0
    bones: dict[str, AsfBone] = {}
    block: dict[str, object] | None = None
    for lineno, raw in enumerate(_lines(path), start=1):
        tokens = raw.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if tokens[0].startswith(":"):
            if block is not None:
                raise MocapFormatError(path, lineno, f"{tokens[0]} inside an unfinished bone block")
            section = tokens[0].lower()
            if section == ":root":
                root_line = lineno
            continue
        key = tokens[0].lower()
        if section == ":units" and len(tokens) >= 2:
            units[key] = tokens[1]
        elif section == ":root":
            root[key] = tokens[1:]
        elif section == ":bonedata":
            if key == "begin":
                if block is not None:
                    raise MocapFormatError(path, lineno, "'begin' before the previous bone's 'end'")
                block = {"line": lineno}
            elif key == "end":
                if block is None:
                    raise MocapFormatError(path, lineno, "'end' without 'begin'")
                bone = _finish_bone(path, block, lineno)
                if bone.name in bones or bone.name == "root":
                    raise MocapFormatError(path, lineno, f"bone {bone.name!r} defined twice")
                bones[bone.name] = bone
                block = None
            elif block is None:
                raise MocapFormatError(path, lineno, f"{tokens[0]!r} outside a begin/end block")
            elif key == "name":
                if len(tokens) != 2:
                    raise MocapFormatError(path, lineno, "'name' needs exactly one value")
                block["name"] = tokens[1]
            elif key == "dof":
                dof = tuple(t.lower() for t in tokens[1:])
                bad = [d for d in dof if d not in _DOFS]
                if bad or len(set(dof)) != len(dof):
                    raise MocapFormatError(path, lineno, f"bad dof list {tokens[1:]}")
                block["dof"] = dof
            elif key == "axis":
                if len(tokens) != 5:
                    raise MocapFormatError(path, lineno, "'axis' needs three angles and an order")
                block["axis"] = tuple(_floats(path, lineno, tokens[1:4], "axis"))
                block["axis_order"] = _axis_order(path, lineno, tokens[4])
    if block is not None:
        raise MocapFormatError(path, int(block["line"]), "bone block without 'end'")
    if section == "" or root_line == 0:
        raise MocapFormatError(path, 1, "no :root section; is this an ASF file?")
    return _skeleton(path, units, root, root_line, bones)


def _finish_bone(path: Path, block: dict[str, object], lineno: int) -> AsfBone:
    if "name" not in block:
        raise MocapFormatError(path, lineno, "bone block without a name")
    return AsfBone(
        name=str(block["name"]),
        dof=tuple(block.get("dof", ())),  # type: ignore[arg-type]
        axis=tuple(block.get("axis", (0.0, 0.0, 0.0))),  # type: ignore[arg-type]
        axis_order=str(block.get("axis_order", "XYZ")),
        line=int(block["line"]),  # type: ignore[arg-type]
    )


def _skeleton(
    path: Path,
    units: dict[str, str],
    root: dict[str, list[str]],
    root_line: int,
    bones: dict[str, AsfBone],
) -> AsfSkeleton:
    order = tuple(t.lower() for t in root.get("order", []))
    if sorted(order) != sorted(_ROOT_CHANNELS):
        raise MocapFormatError(
            path, root_line, f"root 'order' must list TX TY TZ RX RY RZ, got {root.get('order')}"
        )
    axis = root.get("axis", ["XYZ"])
    if len(axis) != 1:
        raise MocapFormatError(path, root_line, f"root 'axis' needs one order, got {axis}")
    position = _floats(path, root_line, root.get("position", ["0", "0", "0"]), "root position")
    orientation = _floats(
        path, root_line, root.get("orientation", ["0", "0", "0"]), "root orientation"
    )
    if len(position) != 3 or len(orientation) != 3:
        raise MocapFormatError(path, root_line, "root position and orientation need 3 values")
    try:
        length = float(units.get("length", "1.0"))
    except ValueError:
        raise MocapFormatError(path, 1, f"bad ':units length' {units['length']!r}") from None
    angle = units.get("angle", "deg").lower()
    if angle not in ("deg", "rad") or not length > 0:
        raise MocapFormatError(path, 1, f"bad :units (length {length}, angle {angle!r})")
    if any(orientation):
        log.warning("%s: root orientation %s ignored (CMU skeletons have 0 0 0)", path, orientation)
    return AsfSkeleton(
        path=path,
        length_unit=length,
        degrees=angle == "deg",
        root_order=order,
        root_axis=_axis_order(path, root_line, axis[0]),
        root_position=(position[0], position[1], position[2]),
        root_orientation=(orientation[0], orientation[1], orientation[2]),
        bones=bones,
    )


def read_amc(path: str | Path, skeleton: AsfSkeleton) -> AmcMotion:
    """Read and validate every frame of an AMC file against its skeleton.

    Every frame must list each bone with channels exactly once, with as many finite numbers
    as the skeleton's ``dof`` list; frame numbers must count up by one.
    """
    path = Path(path)
    expected = skeleton.channels()  # bone -> dofs, root first
    channels = tuple(bone + dof for bone, dofs in expected.items() for dof in dofs)
    offset: dict[str, int] = {}
    start = 0
    for bone, dofs in expected.items():
        offset[bone] = start
        start += len(dofs)
    degrees = skeleton.degrees
    rows: list[np.ndarray] = []
    frames: list[int] = []
    current: np.ndarray | None = None
    seen: set[str] = set()
    frame_line = 0
    last_line = 0

    def finish(at_line: int) -> None:
        missing = [bone for bone in expected if bone not in seen]
        if missing:
            raise MocapFormatError(
                path,
                at_line,
                f"frame {frames[-1]} (from line {frame_line}) is truncated: "
                f"no values for {', '.join(missing)}",
            )
        rows.append(current)  # type: ignore[arg-type]

    for lineno, raw in enumerate(_lines(path), start=1):
        tokens = raw.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if tokens[0].startswith(":"):
            if current is not None:
                raise MocapFormatError(path, lineno, f"keyword {tokens[0]} after the first frame")
            keyword = tokens[0].upper()
            if keyword in (":DEGREES", ":RADIANS"):
                degrees = keyword == ":DEGREES"
            continue
        if len(tokens) == 1 and tokens[0].isdigit():
            number = int(tokens[0])
            if current is not None:
                finish(last_line)
                if number != frames[-1] + 1:
                    raise MocapFormatError(
                        path, lineno, f"frame {number} follows frame {frames[-1]}"
                    )
            frames.append(number)
            current = np.empty(len(channels))
            seen = set()
            frame_line = lineno
            last_line = lineno
            continue
        bone = tokens[0]
        if current is None:
            raise MocapFormatError(path, lineno, f"{bone!r} before the first frame number")
        if bone not in expected:
            raise MocapFormatError(
                path, lineno, f"bone {bone!r} is not in the skeleton {skeleton.path.name}"
            )
        if bone in seen:
            raise MocapFormatError(path, lineno, f"bone {bone!r} twice in frame {frames[-1]}")
        dofs = expected[bone]
        if len(tokens) - 1 != len(dofs):
            raise MocapFormatError(
                path,
                lineno,
                f"bone {bone!r} has {len(tokens) - 1} values, the skeleton "
                f"{skeleton.path.name} declares {len(dofs)} ({' '.join(dofs)})",
            )
        values = _floats(path, lineno, tokens[1:], f"bone {bone!r}")
        current[offset[bone] : offset[bone] + len(dofs)] = values
        seen.add(bone)
        last_line = lineno
    if current is None:
        raise MocapFormatError(path, max(last_line, 1), "no frames")
    finish(last_line)
    return AmcMotion(
        path=path,
        channels=channels,
        values=np.stack(rows),
        frames=np.asarray(frames, dtype=np.int64),
        degrees=degrees,
    )
