"""What an inverse-dynamics fit needs from a dataset, whatever its source: `InverseData`.

Two sources build it: the CMU mocap dataset (`mocap_inverse_data`: splits ``train``,
``val_time``, ``val_clip`` and, with test clips, ``test``; groups are clips) and logged arrays
from a file (`array_inverse_data`, `mbrl_delan.data.arrays`: splits ``train``, ``val``,
``test``; groups are trajectories).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from hashlib import sha256
from pathlib import Path
from typing import Any

import mujoco
import torch
from tensordict import TensorDict
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.data.arrays import (
    COMPONENTS,
    DerivativeSettings,
    arrays_tensordict,
    read_arrays,
    split_trajectories,
)
from mbrl_delan.data.mocap import MocapDataset, dof_groups, humanoid_cmu_xml, split_dataset
from mbrl_delan.systems.arms import cad_spec
from mbrl_delan.systems.system import (
    FREE,
    JointLayout,
    layout_from_names,
    mjcf_path,
    mujoco_layout,
)

ARRAYS_FORMAT = "mbrl_delan.arrays/1"
_FIELDS = (keys.Q, keys.QD, keys.QDD, keys.TAU, keys.TIME, *COMPONENTS)


@dataclass
class FitSystem:
    """What the models need to know of the system.

    dof_groups: group of DoFs (body part, or joint) -> DoF indices, for per-group errors.
    dof_parents, armature: MuJoCo's ``dof_parentid`` and ``dof_armature`` (None without an
        MJCF). mj_model: the model, when there is one (random poses for the M check).
    """

    layout: JointLayout
    dof_groups: dict[str, tuple[int, ...]]
    source: dict[str, Any]  # {"mjcf": path} or {"joints": [types]}: how to build it again
    dof_parents: list[int] | None = None
    armature: list[float] | None = None
    mj_model: mujoco.MjModel | None = None

    @classmethod
    def of_mjcf(
        cls,
        xml: str | Path,
        groups: Callable[[mujoco.MjModel], dict[str, tuple[int, ...]]] | None = None,
    ) -> FitSystem:
        """An MJCF file's (or a shipped model's) joints, tree and armature; DoF groups by
        `groups` of the model, one per joint by default."""
        xml = mjcf_path(xml)
        model = mujoco.MjModel.from_xml_path(str(xml))
        return cls.of_model(model, {"mjcf": str(xml.resolve())}, groups)

    @classmethod
    def of_model(
        cls,
        model: mujoco.MjModel,
        source: dict[str, Any],
        groups: Callable[[mujoco.MjModel], dict[str, tuple[int, ...]]] | None = None,
    ) -> FitSystem:
        """`of_mjcf` of a model in memory; `source` says how to build it again."""
        return cls(
            layout=mujoco_layout(model),
            dof_groups=(groups or _joint_groups)(model),
            source=source,
            dof_parents=model.dof_parentid.tolist(),
            armature=model.dof_armature.tolist(),
            mj_model=model,
        )

    @classmethod
    def of_cad(cls, robot: str, seed: int) -> FitSystem:
        """A shipped arm's (or an MJCF file's) CAD file, its inertials off as drawn from
        `seed` (`mbrl_delan.systems.arms.cad_spec`)."""
        return cls.of_model(cad_spec(robot, seed).compile(), {"cad": robot, "cad_seed": seed})

    def mjcf_spec(self) -> mujoco.MjSpec | None:
        """The MJCF the system was read from, as a spec to edit (None: a joint list)."""
        if "cad" in self.source:
            return cad_spec(self.source["cad"], int(self.source["cad_seed"]))
        if "mjcf" in self.source:
            return mujoco.MjSpec.from_file(self.source["mjcf"])
        return None

    @classmethod
    def of_joints(cls, joints: Sequence[str]) -> FitSystem:
        """Joint types in order (``["hinge", "slide"]``); one DoF group per joint."""
        layout = layout_from_names(list(joints))
        ends = [*layout.dof_adr[1:], layout.nv]
        groups = {
            f"joint{j}": tuple(range(a, b))
            for j, (a, b) in enumerate(zip(layout.dof_adr, ends, strict=True))
        }
        return cls(layout=layout, dof_groups=groups, source={"joints": list(joints)})

    @classmethod
    def of(cls, joints: Sequence[str] | str) -> FitSystem:
        """`of_joints` for a list of types, `of_mjcf` for an MJCF file or a shipped model's
        stem (``"arm2"``)."""
        if isinstance(joints, str):
            return cls.of_mjcf(joints)
        return cls.of_joints(joints)


@dataclass
class InverseData:
    """Splits of (q, qd, qdd, tau) samples and their system.

    splits: name -> float64 TensorDict (N_s,) with q, qd, qdd, tau (and any of the tau parts
        of `mbrl_delan.data.arrays.COMPONENTS`); empty splits are kept.
    groups: name -> (N_s,) int64 index into `group_names`: each sample's clip or trajectory.
    group_kind: ``"clips"`` or ``"trajectories"`` (the summary's key for per-group errors).
    """

    splits: dict[str, TensorDict]
    groups: dict[str, Tensor]
    group_names: list[str]
    group_kind: str
    system: FitSystem
    provenance: dict[str, Any] = field(default_factory=dict)


def system_of(provenance: dict[str, Any]) -> FitSystem:
    """The system a dataset's provenance names: arrays' (a file's, generated excitation
    data's, any data kind's made by `fields_inverse_data`) MJCF, CAD file or joint list, else
    the model mocap data were retargeted onto (its DoFs grouped by body part)."""
    if "system" not in provenance:
        return FitSystem.of_mjcf(mocap_xml(provenance), dof_groups)
    system = provenance["system"]
    if "cad" in system:
        return FitSystem.of_cad(system["cad"], int(system["cad_seed"]))
    return FitSystem.of(system.get("mjcf") or system["joints"])


def mocap_xml(provenance: dict[str, Any]) -> Path:
    """The model mocap data were retargeted onto (from their provenance, else humanoid_CMU)."""
    xml = provenance.get("model", {}).get("xml")
    return Path(xml) if xml and Path(xml).is_file() else Path(humanoid_cmu_xml())


def mocap_inverse_data(dataset: MocapDataset, test_clips: Sequence[str] = ()) -> InverseData:
    """The mocap dataset's splits; the held-out clips named in `test_clips` form ``test``.

    Raises ValueError naming test clips that are not held-out clips of the dataset."""
    parts = split_dataset(dataset)
    clips = list(dataset.provenance["clips"])
    held_out = set(dataset.provenance.get("split", {}).get("val_clips", []))
    unknown = [c for c in test_clips if c not in held_out]
    if unknown:
        raise ValueError(f"test clips {unknown} are not held-out clips of the dataset")
    splits = {"train": parts.train, "val_time": parts.val_time, "val_clip": parts.val_clip}
    if test_clips:
        test_ids = torch.tensor([clips.index(c) for c in test_clips])
        in_test = torch.isin(parts.val_clip[keys.CLIP].reshape(-1), test_ids)
        splits["val_clip"], splits["test"] = parts.val_clip[~in_test], parts.val_clip[in_test]
    return InverseData(
        splits={name: td.select(*_present(td)) for name, td in splits.items()},
        groups={name: td[keys.CLIP].reshape(-1) for name, td in splits.items()},
        group_names=clips,
        group_kind="clips",
        system=system_of(dataset.provenance),
        provenance=dataset.provenance | {"test_clips": list(test_clips)},
    )


def _present(td: TensorDict) -> list[str]:
    return [k for k in _FIELDS if k in td.keys()]


def _joint_groups(model: mujoco.MjModel) -> dict[str, tuple[int, ...]]:
    """One group per joint, named as in the MJCF (``joint<j>`` when unnamed)."""
    groups = {}
    for j in range(model.njnt):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"
        width = {FREE: 6, int(mujoco.mjtJoint.mjJNT_BALL): 3}.get(int(model.jnt_type[j]), 1)
        start = int(model.jnt_dofadr[j])
        groups[name] = tuple(range(start, start + width))
    return groups


def _derivative_note(derivative: DerivativeSettings | None) -> str:
    derivative = derivative or DerivativeSettings()
    low_pass = (
        "no low-pass"
        if derivative.cutoff_hz is None
        else f"low-pass {derivative.cutoff_hz} Hz (order {derivative.order})"
    )
    return f"computed from qd: {low_pass}, central differences"


def array_inverse_data(
    path: str | Path,
    system: FitSystem,
    derivative: DerivativeSettings | None = None,
    val_fraction: float = 0.1,
    test_fraction: float = 0.2,
    seed: int = 0,
    val_by: str = "trajectories",
    test_path: str | Path | None = None,
) -> InverseData:
    """Logged arrays (`mbrl_delan.data.arrays`) on the joints of `system`, split by
    `split_trajectories`, or with `test_path` a file of held-out trajectories as the test
    split. Raises FileNotFoundError (a missing file) and ArrayFormatError (a malformed one,
    or a test file whose widths do not match the joints)."""
    path = Path(path)
    fields = read_arrays(path)
    source = {"format": ARRAYS_FORMAT, **_file_record(path)}
    test = None
    if test_path is not None:
        test = (Path(test_path), read_arrays(test_path))
        source["test"] = _file_record(Path(test_path))
    split = dict(val_fraction=val_fraction, test_fraction=test_fraction, seed=seed, val_by=val_by)
    return fields_inverse_data(path, fields, system, source, derivative, **split, test=test)


def _file_record(path: Path) -> dict[str, str]:
    return {"path": str(path.resolve()), "sha256": sha256(path.read_bytes()).hexdigest()}


def fields_inverse_data(
    origin: str | Path,
    fields: dict[str, Any],
    system: FitSystem,
    source: dict[str, Any],
    derivative: DerivativeSettings | None = None,
    val_fraction: float = 0.1,
    test_fraction: float = 0.2,
    seed: int = 0,
    val_by: str = "trajectories",
    test: tuple[str | Path, dict[str, Any]] | None = None,
) -> InverseData:
    """Arrays' fields in memory (the schema of `mbrl_delan.data.arrays`; `origin` in errors)
    on the joints of `system`, split by `split_trajectories`; `source` opens the provenance.
    `test`: (origin, fields) of held-out data that is the test split instead (its
    trajectories named ``test:<id>``; then none of `fields` is tested)."""
    data = arrays_tensordict(origin, fields, system.layout, derivative)
    share = 0.0 if test is not None else test_fraction
    masks = split_trajectories(data[keys.TRAJECTORY], val_fraction, share, seed, val_by)
    ids = data[keys.TRAJECTORY].reshape(-1)
    unique = ids.unique()
    names = [str(int(i)) for i in unique]
    index = torch.searchsorted(unique, ids)  # (N,) position of each sample's trajectory
    splits = {name: data[mask].select(*_present(data)) for name, mask in masks.items()}
    groups = {name: index[mask] for name, mask in masks.items()}
    if test is not None:
        held = arrays_tensordict(test[0], test[1], system.layout, derivative)
        held_ids = held[keys.TRAJECTORY].reshape(-1)
        held_unique = held_ids.unique()
        groups["test"] = len(names) + torch.searchsorted(held_unique, held_ids)
        names += [f"test:{int(i)}" for i in held_unique]
        splits["test"] = held.select(*_present(held))
    provenance = {
        **source,
        "samples": int(data.shape[0]),
        "trajectories": names,
        "system": system.source,
        "qdd": "from the file" if "qdd" in fields else _derivative_note(derivative),
        "split": {
            "val_fraction": val_fraction,
            "test_fraction": share,
            "seed": seed,
            "val_by": val_by,
        },
    }
    return InverseData(
        splits=splits,
        groups=groups,
        group_names=names,
        group_kind="trajectories",
        system=system,
        provenance=provenance,
    )
