"""Mocap pipeline: AMC/ASF reading, retargeting onto humanoid_CMU, inverse dynamics, dataset.

The test clip in tests/data is CMU 09_06 (a run, 141 frames) with its skeleton 09.asf; see
tests/data/CMU_TERMS.txt for the source and terms.
"""

from __future__ import annotations

import functools
import http.server
import os
import socket
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan import keys
from mbrl_delan.data.mocap import (
    VAL_CLIP,
    VAL_TIME,
    ClipNotFoundError,
    FilterSettings,
    MocapFormatError,
    amc_to_qpos,
    build_dataset,
    find_clip,
    humanoid_cmu_xml,
    inverse_dynamics,
    load_dataset,
    read_amc,
    read_asf,
    retarget,
    retarget_files,
    save_dataset,
    split_dataset,
)
from mbrl_delan.data.mocap.inverse import dynamics_model
from mbrl_delan.data.mocap.retarget import joint_layout
from mbrl_delan.systems.posarith import differentiate_pos, integrate_pos

DATA = Path(__file__).parent / "data"
CLIP, SUBJECT = "09_06", "09"
AMC, ASF = DATA / f"{CLIP}.amc", DATA / f"{SUBJECT}.asf"
SHARED = Path(
    os.environ.get("MBRL_DELAN_MOCAP_DIR", Path(__file__).parents[2] / "shared/data/cmu_mocap")
)


def _xml_or_skip() -> Path:
    try:
        return humanoid_cmu_xml()
    except (ModuleNotFoundError, FileNotFoundError) as err:
        pytest.skip(f"humanoid_CMU.xml unavailable: {err}")


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(_xml_or_skip()))


@pytest.fixture(scope="module")
def clip(model):
    skeleton = read_asf(ASF)
    return retarget(read_amc(AMC, skeleton), skeleton, model)


@pytest.fixture(scope="module")
def forces(model, clip):
    return inverse_dynamics(model, clip.q, clip.qd, clip.qdd)


# ---------------------------------------------------------------- conversion and retargeting


def test_conversion_matches_dm_control_parse_amc(model) -> None:
    """Frame by frame, amc_to_qpos equals dm_control's Amcvals2qpos (except the held fingers)."""
    with warnings.catch_warnings():  # dm_control's import looks for a display
        warnings.simplefilter("ignore")
        parse_amc = pytest.importorskip("dm_control.suite.utils.parse_amc")
    index2joint = {}
    for j in range(model.njnt):
        width = 7 if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE else 1
        for i in range(model.jnt_qposadr[j], model.jnt_qposadr[j] + width):
            index2joint[int(i)] = model.joint(j).name
    convert = parse_amc.Amcvals2qpos(index2joint, parse_amc._CMU_MOCAP_JOINT_ORDER)
    reference = np.stack([convert(v) for v in parse_amc.parse(str(AMC))])  # (K, nq)
    skeleton = read_asf(ASF)
    mocap = amc_to_qpos(read_amc(AMC, skeleton), skeleton, model)
    assert mocap.qpos.shape == reference.shape == (141, 63)
    held = [model.jnt_qposadr[model.joint(n).id] for n in mocap.held]
    assert sorted(n[:-2] for n in mocap.held) == [
        "lfingers",
        "lthumb",
        "lthumb",
        "rfingers",
        "rthumb",
        "rthumb",
    ]
    rest = np.setdiff1d(np.arange(model.nq), held)
    # root position: dm_control rounds 0.0254 / 0.45 to 0.056444 (1e-5 m here)
    np.testing.assert_allclose(mocap.qpos[:, :3], reference[:, :3], atol=5e-5)
    np.testing.assert_allclose(mocap.qpos[:, rest[3:]], reference[:, rest[3:]], atol=1e-12)
    assert np.all(mocap.qpos[:, held] == 0.0)
    assert not mocap.missing and not mocap.unused


def test_clip_end_to_end_is_a_plausible_run(model, clip, forces) -> None:
    """09_06 is a run: about 1 s, upright, several metres travelled; tau has the body's weight."""
    assert clip.dt == model.opt.timestep == 0.002
    n = len(clip)
    assert n == round((140 / 120 - 2 * 0.1) / 0.002) - 1
    assert clip.q.shape == (n, 63) and clip.qd.shape == clip.qdd.shape == (n, 62)
    assert forces.tau.shape == (n, 62)
    assert forces.joint_tau.shape == (n, 56) and forces.root_residual.shape == (n, 6)
    assert torch.equal(forces.root_residual, forces.tau[:, :6])
    height = clip.q[:, 2]
    assert 0.8 < float(height.min()) and float(height.max()) < 1.2
    travel = torch.linalg.vector_norm(clip.q[-1, :2] - clip.q[0, :2])
    assert 2.5 < float(travel) < 5.0  # a run: ~3.5 m/s
    # frames: sample k is mocap frame 1 + 120 t
    np.testing.assert_allclose(clip.frame.numpy(), 1 + 120 * clip.time.numpy())
    # The joint torques are internal: the root residual and gravity alone change the
    # body's linear momentum (impulse-momentum over the whole clip).
    mass = float(model.body_mass.sum())
    data = mujoco.MjData(model)

    def momentum(q: torch.Tensor, qd: torch.Tensor) -> np.ndarray:
        data.qpos[:], data.qvel[:] = q.numpy(), qd.numpy()
        mujoco.mj_forward(model, data)
        mujoco.mj_subtreeVel(model, data)
        return mass * data.subtree_linvel[0].copy()

    force = forces.root_residual[:, :3].numpy() - np.array([0.0, 0.0, mass * 9.81])
    impulse = force.sum(axis=0) * clip.dt
    change = momentum(clip.next_q[-1], clip.next_qd[-1]) - momentum(clip.q[0], clip.qd[0])
    np.testing.assert_allclose(impulse, change, atol=0.5)  # N s, of M g T ~ 490 N s
    assert abs(float(forces.root_residual[:, 2].mean()) / (mass * 9.81) - 1) < 0.15


def test_root_quaternion_is_unit_and_sign_continuous(model, clip) -> None:
    quat = clip.q[:, 3:7]
    np.testing.assert_allclose(torch.linalg.vector_norm(quat, dim=1).numpy(), 1.0, atol=1e-12)
    assert bool(((quat[1:] * quat[:-1]).sum(1) > 0.99).all())
    skeleton = read_asf(ASF)
    raw = amc_to_qpos(read_amc(AMC, skeleton), skeleton, model).qpos[:, 3:7]
    np.testing.assert_allclose(np.linalg.norm(raw, axis=1), 1.0, atol=1e-12)
    assert np.all(np.einsum("ij,ij->i", raw[1:], raw[:-1]) > 0.9)


def test_wrapped_euler_channels_give_the_same_motion(model, clip) -> None:
    """Adding 360 deg to channels mid-clip (same pose, q -> -q for the root) changes nothing."""
    skeleton = read_asf(ASF)
    motion = read_amc(AMC, skeleton)
    wrapped = motion.values.copy()
    for name in ("rootry", "rootrx", "lhumerusrz", "rfemurrx"):
        col = motion.channels.index(name)
        wrapped[60:, col] += 360.0
        wrapped[100:, col] -= 720.0
    shifted = type(motion)(motion.path, motion.channels, wrapped, motion.frames, motion.degrees)
    again = retarget(shifted, skeleton, model)
    torch.testing.assert_close(again.q, clip.q, atol=1e-9, rtol=0)
    torch.testing.assert_close(again.qdd, clip.qdd, atol=1e-5, rtol=0)


def test_qd_is_position_differencing_and_samples_chain_by_euler(model, clip) -> None:
    layout = joint_layout(model)
    dt = clip.dt
    torch.testing.assert_close(clip.qd[1:], differentiate_pos(layout, clip.q[:-1], clip.q[1:], dt))
    torch.testing.assert_close(clip.next_qd, differentiate_pos(layout, clip.q, clip.next_q, dt))
    torch.testing.assert_close(clip.qdd, (clip.next_qd - clip.qd) / dt)
    # semi-implicit Euler (MuJoCo's integrator) maps every sample exactly onto the next one
    qd_next = clip.qd + dt * clip.qdd
    torch.testing.assert_close(integrate_pos(layout, clip.q, qd_next, dt), clip.next_q)
    torch.testing.assert_close(clip.q[1:], clip.next_q[:-1])


def test_filtering_shrinks_accelerations_by_orders_of_magnitude(model, clip) -> None:
    skeleton = read_asf(ASF)
    raw = retarget(read_amc(AMC, skeleton), skeleton, model, FilterSettings(cutoff_hz=None))
    assert raw.q.shape == clip.q.shape
    peak_raw, peak = raw.qdd.abs().max(), clip.qdd.abs().max()
    rms_raw, rms = raw.qdd.square().mean().sqrt(), clip.qdd.square().mean().sqrt()
    assert float(peak_raw) > 20 * float(peak)  # ~50x on this clip
    assert float(rms_raw) > 5 * float(rms)  # ~12x
    # the filter leaves the motion itself alone (6 Hz vs a ~1.4 Hz stride): the typical
    # hinge moves by < 1 deg rms, the root by < 1 cm (the largest changes are spikes of the toes)
    hinge_rms = (raw.q[:, 7:] - clip.q[:, 7:]).square().mean(0).sqrt()
    assert float(hinge_rms.median()) < 0.02
    assert float((raw.q[:, :3] - clip.q[:, :3]).abs().max()) < 0.01


def test_mj_inverse_round_trip(model, clip, forces) -> None:
    """qfrc_applied = joint torques + root residual in mj_forward reproduces qdd."""
    m = dynamics_model(model)  # contacts and limits off, as in inverse_dynamics
    assert m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    assert m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    data = mujoco.MjData(m)
    joint_dofs, root_dofs = list(forces.joint_dofs), list(forces.root_dofs)
    assert root_dofs == list(range(6)) and len(joint_dofs) == 56
    worst = 0.0
    for i in range(0, len(clip), 7):
        data.qpos[:], data.qvel[:] = clip.q[i].numpy(), clip.qd[i].numpy()
        data.qfrc_applied[:] = 0.0
        data.qfrc_applied[joint_dofs] = forces.joint_tau[i].numpy()
        data.qfrc_applied[root_dofs] = forces.root_residual[i].numpy()
        mujoco.mj_forward(m, data)
        worst = max(worst, float(np.abs(data.qacc - clip.qdd[i].numpy()).max()))
    assert worst < 1e-6
    # springs and dampers: passive=False leaves exactly the model's passive forces out
    rigid = inverse_dynamics(model, clip.q[:50], clip.qd[:50], clip.qdd[:50], passive=False)
    assert torch.equal(rigid.root_residual, forces.root_residual[:50])
    assert float((rigid.joint_tau - forces.joint_tau[:50]).abs().max()) > 1.0


# ---------------------------------------------------------------- malformed files


def _amc_lines() -> list[str]:
    return AMC.read_text().splitlines()


def _line_of(lines: list[str], prefix: str, occurrence: int = 1) -> int:
    """1-based number of the occurrence-th line starting with prefix."""
    hits = [i + 1 for i, line in enumerate(lines) if line.startswith(prefix)]
    return hits[occurrence - 1]


def _truncate_last_frame(lines: list[str]) -> tuple[list[str], int]:
    end = _line_of(lines, "lfemur ", 141)  # keep the last frame up to its lfemur line
    return lines[:end], end


def _truncate_middle_frame(lines: list[str]) -> tuple[list[str], int]:
    cut = _line_of(lines, "rtoes ", 50)  # frame 50 loses rtoes .. ltoes
    nxt = lines.index("51")
    return lines[: cut - 1] + lines[nxt:], cut - 1


def _cut_line(lines: list[str]) -> tuple[list[str], int]:
    no = len(lines)  # the file ends inside its last line
    return lines[:-1] + [lines[-1][:6]], no


def _wrong_count(lines: list[str]) -> tuple[list[str], int]:
    no = _line_of(lines, "lhumerus ", 30)
    out = list(lines)
    out[no - 1] = " ".join(out[no - 1].split()[:-1])
    return out, no


def _extra_value(lines: list[str]) -> tuple[list[str], int]:
    no = _line_of(lines, "root ", 7)
    out = list(lines)
    out[no - 1] += " 0.5"
    return out, no


def _non_numeric(lines: list[str]) -> tuple[list[str], int]:
    no = _line_of(lines, "rtibia ", 90)
    out = list(lines)
    out[no - 1] = "rtibia 1O8.2"
    return out, no


def _nan_value(lines: list[str]) -> tuple[list[str], int]:
    no = _line_of(lines, "head ", 3)
    out = list(lines)
    out[no - 1] = "head 1 nan 2"
    return out, no


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (_truncate_last_frame, "frame 141 (from line"),
        (_truncate_middle_frame, "frame 50 (from line"),
        (_cut_line, "has 0 values"),
        (_wrong_count, "'lhumerus' has 2 values, the skeleton 09.asf declares 3 (rx ry rz)"),
        (_extra_value, "'root' has 7 values"),
        (_non_numeric, "non-numeric value '1O8.2'"),
        (_nan_value, "non-finite value 'nan'"),
    ],
)
def test_malformed_amc_names_file_and_line(tmp_path, mutate, message) -> None:
    lines, line_no = mutate(_amc_lines())
    path = tmp_path / "broken.amc"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MocapFormatError) as info:
        read_amc(path, read_asf(ASF))
    assert str(info.value).startswith(f"{path}:{line_no}: ")
    assert message in str(info.value)
    assert info.value.path == path and info.value.line == line_no


def test_malformed_asf_names_file_and_line(tmp_path) -> None:
    lines = ASF.read_text().splitlines()
    no = _line_of(lines, "    dof rx ry rz", 2)
    lines[no - 1] = "    dof rx ry rq"
    path = tmp_path / "broken.asf"
    path.write_text("\n".join(lines))
    with pytest.raises(MocapFormatError, match=rf"^{path}:{no}: bad dof list"):
        read_asf(path)


# ---------------------------------------------------------------- finding and downloading


def test_missing_clip_lists_every_place_looked(tmp_path) -> None:
    folders = [tmp_path / "a", tmp_path / "b"]
    cache = tmp_path / "cache"
    with pytest.raises(ClipNotFoundError) as info:
        find_clip("99_01", folders=folders, cache_dir=cache, download=False)
    text = str(info.value)
    for root in [*folders, cache]:
        for where in (root, root / "99", root / "subjects" / "99"):
            assert str(where / "99_01.amc") in text
    # the AMC is there but its subject's ASF is not: the ASF places are listed too
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "99_01.amc").write_text("1\n")
    with pytest.raises(ClipNotFoundError, match="99.asf"):
        find_clip("99_01", folders=folders, cache_dir=cache, download=False)
    with pytest.raises(ValueError, match="subject_trial"):
        find_clip("../etc", folders=folders, cache_dir=cache, download=False)


def test_local_folder_layouts(tmp_path) -> None:
    nested = tmp_path / "subjects" / SUBJECT
    nested.mkdir(parents=True)
    for f in (AMC, ASF):
        (nested / f.name).write_bytes(f.read_bytes())
    files = find_clip(
        CLIP, folders=[tmp_path / "empty", tmp_path], cache_dir=tmp_path / "c", download=False
    )
    assert (files.amc, files.asf, files.source) == (nested / AMC.name, nested / ASF.name, "local")


def test_skeleton_is_found_in_another_folder_than_the_clip(tmp_path) -> None:
    """The subject's ASF beside the AMC first, else in any folder's layouts or the cache."""
    clips, skeletons, cache = tmp_path / "clips", tmp_path / "skeletons", tmp_path / "cache"
    clips.mkdir()
    (clips / AMC.name).write_bytes(AMC.read_bytes())
    (skeletons / SUBJECT).mkdir(parents=True)
    (skeletons / SUBJECT / ASF.name).write_bytes(ASF.read_bytes())
    files = find_clip(CLIP, folders=[clips, skeletons], cache_dir=cache, download=False)
    assert (files.amc, files.asf, files.source) == (
        clips / AMC.name,
        skeletons / SUBJECT / ASF.name,
        "local",
    )
    cache.mkdir()  # the cache's skeleton serves a local clip too
    (cache / ASF.name).write_bytes(ASF.read_bytes())
    files = find_clip(CLIP, folders=[clips], cache_dir=cache, download=False)
    assert (files.amc, files.asf) == (clips / AMC.name, cache / ASF.name)
    (clips / ASF.name).write_bytes(ASF.read_bytes())  # one beside the clip comes first
    assert find_clip(CLIP, folders=[clips, skeletons], cache_dir=cache, download=False).asf == (
        clips / ASF.name
    )


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: object) -> None:  # noqa: A002
        pass


@pytest.fixture
def server() -> Iterator[str]:
    """An HTTP server on 127.0.0.1 serving tests/data; yields the URL template."""
    handler = functools.partial(_QuietHandler, directory=str(DATA))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}/{{file}}"
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join()


def test_download_into_cache(tmp_path, server) -> None:
    cache = tmp_path / "cache"
    files = find_clip(CLIP, folders=[tmp_path / "none"], cache_dir=cache, url_template=server)
    assert files.source == server.format(subject=SUBJECT, file=AMC.name)
    assert files.amc == cache / AMC.name and files.asf == cache / ASF.name
    assert files.amc.read_bytes() == AMC.read_bytes()
    assert files.asf.read_bytes() == ASF.read_bytes()
    assert not [p for p in cache.iterdir() if p.name.startswith(".")]  # no partial files
    again = find_clip(CLIP, cache_dir=cache, url_template="http://127.0.0.1:9/{file}")
    assert again.source == "cache"
    with pytest.raises(ClipNotFoundError, match=r"(?s)looked in.*09_07\.amc.*HTTP 404"):
        find_clip("09_07", cache_dir=cache, url_template=server)


def test_download_fails_clearly_when_the_server_is_down(tmp_path) -> None:
    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    url = f"http://127.0.0.1:{port}/{{subject}}/{{file}}"
    with pytest.raises(ClipNotFoundError) as info:
        find_clip(CLIP, cache_dir=tmp_path / "cache", url_template=url, timeout=5)
    text = str(info.value)
    assert f"http://127.0.0.1:{port}/09/09.asf failed" in text
    assert "offline?" in text and str(tmp_path / "cache" / AMC.name) in text
    assert not (tmp_path / "cache" / ASF.name).exists()


# ---------------------------------------------------------------- dataset


def test_dataset_splits_provenance_and_round_trip(tmp_path, model) -> None:
    _xml_or_skip()
    folder = tmp_path / "clips"
    folder.mkdir()
    for name in (CLIP, "09_99"):  # the test clip twice: one for training, one held out
        (folder / f"{name}.amc").write_bytes(AMC.read_bytes())
    (folder / ASF.name).write_bytes(ASF.read_bytes())
    ds = build_dataset(
        clips=(CLIP, "09_99"),
        val_clips=("09_99",),
        folders=[folder],
        download=False,
        samples_per_clip=150,
        val_time_fraction=0.25,
        gap_s=0.1,
        seed=3,
    )
    data = ds.data
    assert ds.clips == (CLIP, "09_99") and data.batch_size == (300,)
    assert data[keys.Q].dtype == torch.float64 and data[keys.CLIP].shape == (300, 1)
    parts = split_dataset(ds)
    assert len(parts.train) + len(parts.val_time) + len(parts.val_clip) == 300
    assert len(parts.val_clip) == 150 and bool((parts.val_clip[keys.CLIP] == 1).all())
    assert 20 < len(parts.val_time) < 75 and bool((parts.val_time[keys.CLIP] == 0).all())
    # the held-out segment is one contiguous block, with a gap to every training sample
    t_val = parts.val_time[keys.TIME].flatten()
    t_train = parts.train[keys.TIME].flatten()
    gap = (t_train[:, None] - t_val[None, :]).abs().min()
    assert float(gap) >= 0.1
    inside = (t_train > t_val.min()) & (t_train < t_val.max())
    assert not bool(inside.any())
    # the forces are the inverse dynamics of the stored states
    check = inverse_dynamics(model, data[keys.Q][:20], data[keys.QD][:20], data[keys.QDD][:20])
    torch.testing.assert_close(check.tau, data[keys.TAU][:20], rtol=0, atol=1e-9)
    torch.testing.assert_close(data[keys.ROOT_RESIDUAL], data[keys.TAU][:, :6])
    prov = ds.provenance
    assert prov["filter"]["cutoff_hz"] == 6.0 and prov["timestep"] == 0.002
    assert prov["inverse_dynamics"] == {"contacts": False, "limits": False, "passive": True}
    info = prov["clip_info"][CLIP]
    assert info["amc"] == str(folder / AMC.name) and info["source"] == "local"
    assert info["samples"] == {
        "train": len(parts.train),
        "val_time": len(parts.val_time),
        "val_clip": 0,
    }
    path = save_dataset(ds, tmp_path / "saved")
    with pytest.raises(FileExistsError):
        save_dataset(ds, path)
    loaded = load_dataset(path)
    assert loaded.provenance == ds.provenance
    assert (loaded.data == data).all()
    assert int((loaded.data[keys.SPLIT] == VAL_TIME).sum()) == len(parts.val_time)
    assert int((loaded.data[keys.SPLIT] == VAL_CLIP).sum()) == 150


# ---------------------------------------------------------------- every shared clip


def _shared_clips() -> list[Path]:
    return sorted(SHARED.glob("*.amc")) if SHARED.is_dir() else []


@pytest.mark.skipif(not SHARED.is_dir(), reason=f"shared CMU clips not found at {SHARED}")
def test_every_shared_clip_retargets(model) -> None:
    """All clips in ../shared/data/cmu_mocap go through, finite, with unit quaternions."""
    xml = _xml_or_skip()
    amcs = _shared_clips()
    assert len(amcs) >= 15
    for amc in amcs:
        asf = SHARED / f"{amc.stem.split('_')[0]}.asf"
        clip = retarget_files(amc, asf, xml_path=xml)
        assert len(clip) > 300, amc.name
        norms = torch.linalg.vector_norm(clip.q[:, 3:7], dim=1)
        assert float((norms - 1).abs().max()) < 1e-12, amc.name
        assert bool(((clip.q[1:, 3:7] * clip.q[:-1, 3:7]).sum(1) > 0).all()), amc.name
        every = slice(None, None, 25)
        forces = inverse_dynamics(model, clip.q[every], clip.qd[every], clip.qdd[every])
        for x in (clip.q, clip.qd, clip.qdd, forces.tau):
            assert bool(torch.isfinite(x).all()), amc.name
