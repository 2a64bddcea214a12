"""CMU motion capture -> humanoid_CMU inverse-dynamics data (see docs/mocap.md).

- `clips`: find clips locally or download them into a cache;
- `amc`: validated ASF / AMC readers;
- `retarget`: AMC -> q on humanoid_CMU, filtering, resampling, qd, qdd;
- `inverse`: joint torques and root residual by ``mj_inverse`` (contacts and limits off);
- `tracking`: torques by PD tracking of the reference in simulation (the alternative source);
- `groups`: the hinges grouped by body part, for per-group errors;
- `dataset`: the dataset TensorDict with provenance and its two validation splits.
"""

from mbrl_delan.data.mocap.amc import (
    AmcMotion,
    AsfBone,
    AsfSkeleton,
    MocapFormatError,
    read_amc,
    read_asf,
)
from mbrl_delan.data.mocap.clips import (
    CMU_URL_TEMPLATE,
    ClipFiles,
    ClipNotFoundError,
    clip_subject,
    default_cache_dir,
    download_clip,
    find_clip,
)
from mbrl_delan.data.mocap.dataset import (
    DEFAULT_CLIPS,
    DEFAULT_VAL_CLIPS,
    SPLIT_NAMES,
    TORQUE_SOURCES,
    TRAIN,
    VAL_CLIP,
    VAL_TIME,
    DatasetSplits,
    MocapDataset,
    build_dataset,
    load_dataset,
    save_dataset,
    split_dataset,
)
from mbrl_delan.data.mocap.groups import BODY_PARTS, ROOT_GROUP, dof_groups
from mbrl_delan.data.mocap.inverse import (
    InverseDynamics,
    dynamics_model,
    forward_accelerations,
    inverse_dynamics,
    random_poses,
)
from mbrl_delan.data.mocap.retarget import (
    UNCAPTURED_BONES,
    ClipTooShortError,
    FilterSettings,
    MocapQpos,
    RetargetedClip,
    amc_to_qpos,
    humanoid_cmu_xml,
    retarget,
    retarget_files,
)
from mbrl_delan.data.mocap.tracking import (
    GAINS,
    TrackingErrors,
    TrackingResult,
    TrackingSettings,
    TrackingUnstableError,
    track_clip,
)

__all__ = [
    "BODY_PARTS",
    "CMU_URL_TEMPLATE",
    "DEFAULT_CLIPS",
    "DEFAULT_VAL_CLIPS",
    "GAINS",
    "ROOT_GROUP",
    "SPLIT_NAMES",
    "TORQUE_SOURCES",
    "TRAIN",
    "UNCAPTURED_BONES",
    "VAL_CLIP",
    "VAL_TIME",
    "AmcMotion",
    "AsfBone",
    "AsfSkeleton",
    "ClipFiles",
    "ClipNotFoundError",
    "DatasetSplits",
    "ClipTooShortError",
    "FilterSettings",
    "InverseDynamics",
    "MocapDataset",
    "MocapFormatError",
    "MocapQpos",
    "RetargetedClip",
    "TrackingErrors",
    "TrackingResult",
    "TrackingSettings",
    "TrackingUnstableError",
    "amc_to_qpos",
    "build_dataset",
    "clip_subject",
    "default_cache_dir",
    "dof_groups",
    "download_clip",
    "dynamics_model",
    "find_clip",
    "forward_accelerations",
    "humanoid_cmu_xml",
    "inverse_dynamics",
    "random_poses",
    "load_dataset",
    "read_amc",
    "read_asf",
    "retarget",
    "retarget_files",
    "save_dataset",
    "split_dataset",
    "track_clip",
]
