"""PD tracking of a retargeted clip in MuJoCo (`mbrl_delan.data.mocap.tracking`).

On CMU 09_06 (a run, tests/data; see tests/data/CMU_TERMS.txt).
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import pytest
import torch

from mbrl_delan import keys
from mbrl_delan.data.mocap import (
    TrackingSettings,
    TrackingUnstableError,
    build_dataset,
    humanoid_cmu_xml,
    inverse_dynamics,
    read_amc,
    read_asf,
    retarget,
    track_clip,
)

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    try:
        return mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml()))
    except (ModuleNotFoundError, FileNotFoundError) as err:
        pytest.skip(f"humanoid_CMU.xml unavailable: {err}")


@pytest.fixture(scope="module")
def clip(model):
    skeleton = read_asf(DATA / "09.asf")
    return retarget(read_amc(DATA / "09_06.amc", skeleton), skeleton, model)


def test_pd_tracking_follows_the_clip_closely(model, clip) -> None:
    result = track_clip(model, clip, TrackingSettings())  # PD alone, no feed-forward
    err = result.errors()
    assert err.hinge_rms_deg < 3.0 and err.hinge_max_deg < 30.0
    assert err.root_position_rms_m < 0.01 and err.root_rotation_rms_deg < 3.0
    assert err.pd_share == pytest.approx(1.0)
    assert torch.equal(result.q[0], clip.q[0])


def test_recorded_torques_are_the_inverse_dynamics_of_the_achieved_motion(model, clip) -> None:
    result = track_clip(model, clip, TrackingSettings())
    check = inverse_dynamics(model, result.q, result.qd, result.qdd)
    torch.testing.assert_close(check.tau, result.tau, rtol=0, atol=1e-8)
    # semi-implicit Euler chains the samples exactly: next qd = qd + dt qdd
    torch.testing.assert_close(result.next_qd, result.qd + clip.dt * result.qdd)
    torch.testing.assert_close(result.q[1:], result.next_q[:-1])


def test_with_feedforward_the_pd_part_is_negligible(model, clip) -> None:
    result = track_clip(model, clip, TrackingSettings(feedforward=True))
    err = result.errors()
    assert err.pd_share < 1e-6
    assert err.hinge_max_deg < 1e-6 and err.root_position_rms_m < 1e-8
    ff = inverse_dynamics(model, clip.q, clip.qd, clip.qdd).tau
    torch.testing.assert_close(result.tau, ff, rtol=0, atol=1e-6)


def test_mass_matrix_gains_track_better_than_diagonal_ones(model, clip) -> None:
    """1/diag(M^-1) leaves coaxial hinge triplets (spine, neck, shoulders) soft."""
    full = track_clip(model, clip, TrackingSettings(omega=40.0)).errors()
    diag = track_clip(model, clip, TrackingSettings(omega=40.0, gains="diagonal")).errors()
    assert full.hinge_rms_deg < diag.hinge_rms_deg
    assert full.root_rotation_rms_deg < 0.5 * diag.root_rotation_rms_deg


def test_too_stiff_gains_fail_loudly(model, clip) -> None:
    with pytest.raises(TrackingUnstableError, match="lower omega"):
        track_clip(model, clip, TrackingSettings(omega=400.0))
    with pytest.raises(ValueError, match="gains"):
        TrackingSettings(gains="magic")


def test_dataset_with_pd_torques(model, tmp_path: Path) -> None:
    folder = tmp_path / "clips"
    folder.mkdir()
    for name in ("09_06.amc", "09.asf"):
        (folder / name).write_bytes((DATA / name).read_bytes())
    ds = build_dataset(
        clips=("09_06",),
        val_clips=(),
        folders=[folder],
        download=False,
        samples_per_clip=50,
        torques="pd",
    )
    data = ds.data
    check = inverse_dynamics(model, data[keys.Q], data[keys.QD], data[keys.QDD])
    torch.testing.assert_close(check.tau, data[keys.TAU], rtol=0, atol=1e-8)
    torch.testing.assert_close(data[keys.ROOT_RESIDUAL], data[keys.TAU][:, :6])
    assert ds.provenance["torques"]["source"] == "pd"
    assert ds.provenance["torques"]["tracking"]["gains"] == "mass_matrix"
    assert ds.provenance["clip_info"]["09_06"]["tracking_errors"]["hinge_rms_deg"] < 3.0
