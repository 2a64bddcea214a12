"""Videos: MuJoCo offscreen frames of states, atomic MP4 files, backend errors, `video=true` runs.

Rendering tests need one OpenGL backend that works in this process: the default one (MUJOCO_GL,
else EGL, which Mesa provides on CPU-only machines). They skip only when no backend at all can
make a context (each is probed in its own process, since PyOpenGL binds one per process).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tiny import TINY_TRAIN

from mbrl_delan import keys
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.systems.system import asset_path
from mbrl_delan.training import video as video_mod
from mbrl_delan.training.recorder import Recorder
from mbrl_delan.training.video import (
    BACKENDS,
    VideoBackendError,
    VideoRecorder,
    check_backend,
    default_backend,
    resolve_backend,
    rollout_states,
    root_travels,
    write_mp4,
)

W, H = 64, 48


def _probe(backend: str) -> str | None:
    """None when `backend` renders in a fresh process, else the error it printed."""
    code = f"from mbrl_delan.training.video import check_backend; check_backend({backend!r})"
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300
    )
    return None if out.returncode == 0 else (out.stderr.strip().splitlines() or ["?"])[-1]


@pytest.fixture(scope="module")
def backend() -> str:
    """The default backend, checked in this process; skip only if no backend works anywhere."""
    try:
        return check_backend(None)
    except VideoBackendError as err:
        default_error = str(err)
    errors = {name: _probe(name) for name in BACKENDS}
    working = [name for name, error in errors.items() if error is None]
    if not working:
        pytest.skip(f"no MuJoCo OpenGL backend can make a context here: {errors}")
    pytest.fail(f"the default backend failed ({default_error}) but {working} work: set MUJOCO_GL")


@pytest.fixture
def pendulum() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(asset_path("pendulum")))


def test_frames_depend_on_the_state(backend: str, pendulum: mujoco.MjModel) -> None:
    with VideoRecorder(pendulum, W, H, fps=20.0, backend=backend) as rec:
        down = rec.frame_from_state(np.zeros(1), np.zeros(1))
        again = rec.frame_from_state(torch.zeros(1), torch.zeros(1))
        swung = rec.frame_from_state(np.array([2.0]), np.zeros(1))
    assert down.shape == (H, W, 3) and down.dtype == np.uint8
    assert down.any() and swung.any()  # the pendulum is drawn, not a black frame
    np.testing.assert_array_equal(down, again)  # same state, same picture
    assert np.abs(down.astype(int) - swung).sum() > 0  # another state, another picture


def test_frame_from_live_data_matches_the_state(backend: str, pendulum: mujoco.MjModel) -> None:
    data = mujoco.MjData(pendulum)
    data.qpos[:] = 1.0
    mujoco.mj_forward(pendulum, data)
    with VideoRecorder(pendulum, W, H, fps=20.0, backend=backend) as rec:
        from_data = rec.frame_from_data(data)
        from_state = rec.frame_from_state(np.ones(1), np.zeros(1))
    np.testing.assert_array_equal(from_data, from_state)


FREE_BOX = """<mujoco><worldbody><body pos="0 0 1"><freejoint/>
<geom type="box" size=".2 .1 .3" rgba="1 .2 .2 1"/></body></worldbody></mujoco>"""


def test_tracking_camera_follows_the_root_past_fixed_posts(backend: str) -> None:
    """With track_root the free camera follows a travelling root past a rail of fixed posts:
    moved by a whole number of post spacings the frame is the same (the body stays in view,
    the posts line up again), moved by half a spacing the posts shift, so travel is seen; a
    fixed camera loses the body."""
    box = mujoco.MjModel.from_xml_string(FREE_BOX)
    here = np.array([0, 0, 1, 1, 0, 0, 0], dtype=np.float64)
    still = np.zeros(6)
    with VideoRecorder(box, W, H, fps=20.0, backend=backend, track_root=True) as rec:
        assert rec.rail is not None
        shift = np.zeros(7)
        shift[0] = 12 * rec.rail.spacing
        whole = [rec.frame_from_state(q, still) for q in (here, here + shift)]
        half = rec.frame_from_state(here + shift / 24, still)
    with VideoRecorder(box, W, H, fps=20.0, backend=backend) as rec:
        assert rec.rail is None
        fixed = [rec.frame_from_state(q, still) for q in (here, here + shift)]
    assert whole[0].any()
    np.testing.assert_allclose(whole[1], whole[0], atol=2)
    assert (np.abs(half.astype(int) - whole[0]).sum(-1) > 30).any()
    assert np.abs(fixed[1].astype(int) - fixed[0]).mean() > 1.0


def test_a_reference_pose_is_drawn_as_a_translucent_ghost_in_the_frame(
    backend: str, pendulum: mujoco.MjModel, tmp_path: Path
) -> None:
    """The ghost changes the frame where the pendulum at the reference's angle would be (and
    not elsewhere), in blue; `record` passes one ghost pose per frame."""
    still = np.zeros(1)
    with VideoRecorder(pendulum, W, H, fps=20.0, backend=backend) as rec:
        plain = rec.frame_from_state(np.zeros(1), still).astype(int)
        ghosted = rec.frame_from_state(np.zeros(1), still, ghost_q=np.array([2.0])).astype(int)
        there = rec.frame_from_state(np.array([2.0]), still).astype(int)
        written = []
        rec.write = lambda path, frames: written.append(frames) or Path(path)  # type: ignore[method-assign]
        q = torch.zeros(3, 1, dtype=torch.float64)
        rec.record(tmp_path / "ghost.mp4", q, q, ghost_q=torch.full((3, 1), 2.0))
    changed = np.abs(ghosted - plain).sum(-1) > 30  # (H, W)
    moved = np.abs(there - plain).sum(-1) > 30  # where the pendulum at 2 rad differs
    assert changed.sum() > 20
    assert (changed & moved).sum() > 0.8 * changed.sum()  # the ghost lies where that pose is
    delta = (ghosted - plain)[changed]
    assert delta[:, 2].mean() > delta[:, 0].mean()  # bluer than before
    (frames,) = written
    np.testing.assert_array_equal(frames[0].astype(int), ghosted)


def test_mp4_round_trip(backend: str, pendulum: mujoco.MjModel, tmp_path: Path) -> None:
    q = torch.linspace(0.0, 3.0, 7, dtype=torch.float64)[:, None]
    with VideoRecorder(pendulum, W, H, fps=20.0, backend=backend) as rec:
        path = rec.record(tmp_path / "clip.mp4", q, torch.zeros_like(q))
    assert path == tmp_path / "clip.mp4"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4"]  # no temp file left
    reader = imageio.get_reader(path, format="FFMPEG")
    try:
        frames = [frame for frame in reader]
        fps = reader.get_meta_data()["fps"]
    finally:
        reader.close()
    assert len(frames) == 7 and fps == pytest.approx(20.0)
    assert all(frame.shape == (H, W, 3) for frame in frames)
    assert np.abs(frames[0].astype(int) - frames[-1]).mean() > 0.1


def test_rollout_states_are_the_first_then_every_reached_state() -> None:
    q = torch.arange(3.0)[:, None]
    rollout = TensorDict(
        {keys.Q: q, keys.QD: -q, "next": {keys.Q: q + 1, keys.QD: -(q + 1)}}, batch_size=[3]
    )
    states_q, states_qd = rollout_states(rollout)
    assert states_q.flatten().tolist() == [0.0, 1.0, 2.0, 3.0]
    assert states_qd.flatten().tolist() == [0.0, -1.0, -2.0, -3.0]


def test_failed_write_keeps_the_old_file_and_leaves_no_temp(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "clip.mp4"
    path.write_bytes(b"previous video")

    class BrokenWriter:
        def append_data(self, frame: np.ndarray) -> None:
            raise OSError("disk full")

        def close(self) -> None:
            pass

    monkeypatch.setattr(imageio, "get_writer", lambda *args, **kwargs: BrokenWriter())
    with pytest.raises(OSError, match="disk full"):
        write_mp4(path, np.zeros((3, H, W, 3), np.uint8), fps=10.0)
    assert path.read_bytes() == b"previous video"
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]
    with pytest.raises(ValueError, match="even"):
        write_mp4(path, np.zeros((3, 5, 6, 3), np.uint8), fps=10.0)


def test_backend_names() -> None:
    assert resolve_backend("OSMesa") == "osmesa"
    assert default_backend({"MUJOCO_GL": "osmesa"}) == "osmesa"
    assert default_backend({}) in ("egl", "glfw")
    with pytest.raises(VideoBackendError, match="egl, osmesa, glfw"):
        resolve_backend("vulkan")


def test_unusable_backend_gives_a_clear_error(
    pendulum: mujoco.MjModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_import = video_mod.importlib.import_module

    def missing(name: str, *args: object) -> object:
        if name.startswith("mujoco."):  # a backend module, as if its libraries were missing
            raise ImportError(f"no library for {name}")
        return real_import(name, *args)

    monkeypatch.setattr(video_mod.importlib, "import_module", missing)
    with pytest.raises(VideoBackendError) as info:
        VideoRecorder(pendulum, W, H, fps=20.0, backend="osmesa")
    message = str(info.value)
    assert "'osmesa'" in message and "no library for mujoco.osmesa" in message
    assert "video_backend=egl|osmesa|glfw" in message and "MUJOCO_GL" in message
    with pytest.raises(ValueError, match="even"):
        VideoRecorder(pendulum, 63, H, fps=20.0, backend="egl")


@pytest.mark.slow
def test_video_logged_to_offline_wandb(
    backend: str, pendulum: mujoco.MjModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    q = torch.zeros(4, 1)
    with VideoRecorder(pendulum, W, H, fps=20.0, backend=backend) as rec:
        path = rec.record(tmp_path / "videos" / "eval_iter1_ep0.mp4", q, q)
    with Recorder(tmp_path, "wandb", "test", None, {}) as recorder:
        assert recorder.wandb_active
        recorder.log({"x": 1.0}, 1)
        recorder.log_video("video/eval_ep0", path, 1)
    logged = list((tmp_path / "wandb").glob("offline-run-*/files/media/videos/**/*.mp4"))
    assert len(logged) == 1 and logged[0].read_bytes() == path.read_bytes()


# --- the entry point ---------------------------------------------------------------------

TINY = [*TINY_TRAIN, "video=true", f"video_width={W}", f"video_height={H}"]


def _train(
    run_dir: Path, *overrides: str, unset: tuple[str, ...] = ()
) -> subprocess.CompletedProcess:
    """A tiny `video=true` training run; `unset` names environment variables to remove."""
    cmd = [sys.executable, "-m", "mbrl_delan.train", *TINY, f"hydra.run.dir={run_dir}", *overrides]
    env = {k: v for k, v in os.environ.items() if k not in unset}
    env["WANDB_MODE"] = "disabled"
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)


@pytest.mark.slow
def test_train_with_video_writes_the_final_evaluation(backend: str, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    out = _train(run_dir, "budget.iterations=2", f"video_backend={backend}")
    assert out.returncode == 0, out.stdout + out.stderr
    videos = sorted(p.name for p in (run_dir / "videos").iterdir())
    # the final evaluation only (video_every_eval=false), and the oracle's episode
    assert videos == ["eval_iter2_ep0.mp4", "oracle_ep0.mp4"]
    reader = imageio.get_reader(run_dir / "videos" / videos[0], format="FFMPEG")
    try:
        frames = [frame for frame in reader]
    finally:
        reader.close()
    assert len(frames) == 15 + 1  # the first state, then one per control step
    assert frames[0].shape == (H, W, 3)
    assert (run_dir / "checkpoint.pt").is_file()
    assert json.loads((run_dir / "summary.json").read_text())["iterations"] == 2


@pytest.mark.slow
def test_train_with_an_unusable_backend_stops_before_training(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    out = _train(run_dir, "video_backend=glfw", unset=("DISPLAY", "WAYLAND_DISPLAY"))
    text = out.stdout + out.stderr
    assert out.returncode == 2, text
    assert "OpenGL backend 'glfw'" in text and "MUJOCO_GL" in text, text
    assert "Traceback" not in text
    assert not (run_dir / "checkpoint.pt").exists() and not (run_dir / "metrics.jsonl").exists()


def test_cart_stays_in_view_while_it_travels_two_metres(backend: str) -> None:
    """The cart-pole's video tracks its cart (a slide root): drawn magenta, the cart shows in
    every frame of an episode in which it travels 2 m; a fixed camera loses it."""
    from mbrl_delan.systems.system import load_system

    system = load_system("cartpole")
    model = system.mj_model()
    model.geom_rgba[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "cart")] = (1, 0, 1, 1)
    x = np.linspace(0.0, 2.0, 9)
    q = np.stack([x, np.pi * x / 2.0], axis=1)  # (T, 2): the cart moves, the pole turns
    qd = np.zeros_like(q)

    def cart_pixels(track_root: bool) -> list[int]:
        with VideoRecorder(model, W, H, fps=20.0, backend=backend, track_root=track_root) as rec:
            frames = rec.frames_from_states(q, qd).astype(int)  # (T, H, W, 3)
        magenta = (frames[..., 0] - frames[..., 1] > 60) & (frames[..., 2] - frames[..., 1] > 60)
        return magenta.sum(axis=(1, 2)).tolist()

    assert root_travels(system.layout.types)
    assert min(cart_pixels(True)) > 20
    assert min(cart_pixels(False)) == 0


def test_gym_env_renders_rgb_frames(backend: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """render_mode="rgb_array": gymnasium's render contract (uint8 (H, W, 3) frames at the
    control rate), the frame changes as the env steps."""
    import gymnasium as gym

    from mbrl_delan.envs.real import MujocoTaskEnv, gym_id, register_envs

    monkeypatch.setenv("MUJOCO_GL", backend)
    register_envs()
    env = gym.make(gym_id("pendulum"), render_mode="rgb_array", width=W, height=H)
    env.reset(seed=0)
    first = env.render()
    for _ in range(5):
        env.step(env.action_space.high)
    later = env.render()
    env.close()
    assert env.metadata["render_fps"] == pytest.approx(20.0)
    assert first.shape == (H, W, 3) and first.dtype == np.uint8
    assert np.abs(later.astype(int) - first).mean() > 0.5
    with pytest.raises(ValueError, match="render_mode='depth'"):
        MujocoTaskEnv("pendulum", render_mode="depth")


def test_gym_env_render_draws_the_task_markers(backend: str, monkeypatch) -> None:
    """gymnasium's render() of arm_reach draws its target as the green marker the loop's
    videos draw (a frame of the pendulum, without markers, has none)."""
    import gymnasium as gym

    from mbrl_delan.envs.real import gym_id, register_envs

    monkeypatch.setenv("MUJOCO_GL", backend)
    register_envs()

    def green_pixels(name: str) -> int:
        env = gym.make(gym_id(name), render_mode="rgb_array", width=160, height=120)
        env.reset(seed=0)
        frame = env.render().astype(int)
        env.close()
        green = (frame[..., 1] - frame[..., 0] > 80) & (frame[..., 1] - frame[..., 2] > 80)
        return int(green.sum())

    assert green_pixels("arm_reach") > 5
    assert green_pixels("pendulum") == 0


def test_gymnasium_record_video_writes_the_episode(
    backend: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """gymnasium's RecordVideo (the `video` extra: moviepy) on a registered env writes one MP4
    of the episode: a frame per step and the reset's."""
    import gymnasium as gym
    import imageio.v3 as iio

    pytest.importorskip("moviepy", reason="the video extra: pip install 'mbrl_delan[video]'")
    from gymnasium.wrappers import RecordVideo

    from mbrl_delan.envs.real import gym_id, register_envs

    monkeypatch.setenv("MUJOCO_GL", backend)
    register_envs()
    env = gym.make(gym_id("cartpole"), render_mode="rgb_array", width=W, height=H)
    env = RecordVideo(env, str(tmp_path), episode_trigger=lambda episode: True)
    env.reset(seed=0)
    for _ in range(6):
        env.step(env.action_space.high)
    env.close()
    (video,) = tmp_path.glob("*.mp4")
    frames = iio.imread(video)
    assert frames.shape == (7, H, W, 3)


def test_overlay_writes_step_and_reward_in_the_top_left_corner(
    backend: str, pendulum: mujoco.MjModel
) -> None:
    """Each frame can carry its step and reward: text in the top-left corner, nothing else
    of the picture changed; the texts come from the rollout's rewards."""
    from tensordict import TensorDict

    from mbrl_delan.training.video import step_reward_overlays

    rollout = TensorDict({"next": {"reward": torch.tensor([[0.5], [0.25]])}}, batch_size=[2])
    overlays = step_reward_overlays(rollout)
    assert overlays == [("step\nreward", "0\n-"), ("step\nreward", "1\n0.500"),
                        ("step\nreward", "2\n0.250")]  # fmt: skip
    q, qd = np.zeros((3, 1)), np.zeros((3, 1))
    with VideoRecorder(pendulum, 320, 240, fps=20.0, backend=backend) as rec:
        plain = rec.frames_from_states(q, qd).astype(int)
        marked = rec.frames_from_states(q, qd, overlays).astype(int)
        with pytest.raises(ValueError, match="2 overlays for 3 frames"):
            rec.frames_from_states(q, qd, overlays[:2])
    changed = np.abs(marked - plain).sum(axis=-1) > 0  # (T, H, W)
    rows, cols = np.nonzero(changed[1])
    assert rows.size > 20 and rows.max() < 240 // 2 and cols.max() < 320 // 2
    assert (changed[1] != changed[2]).any()  # "0.500" and "0.250" differ


def test_arm_reach_videos_show_the_target(backend: str) -> None:
    """Task markers (`Task.markers`: arm_reach's target) are drawn as green spheres; the
    other tasks have none."""
    parts = make_env_parts("arm_reach")
    assert parts.task.markers() == ((0.6, 0.0, 0.4),)
    assert make_env_parts("pendulum").task.markers() == ()
    model = parts.system.mj_model()
    q, qd = np.zeros((1, 2)), np.zeros((1, 2))
    frames = []
    for markers in ((), parts.task.markers()):
        with VideoRecorder(model, 320, 240, 20.0, backend=backend, markers=markers) as rec:
            frames.append(rec.frames_from_states(q, qd)[0].astype(int))
    plain, marked = frames
    changed = np.abs(marked - plain).sum(axis=-1) > 0
    green = (marked[..., 1] - marked[..., 0] > 50) & (marked[..., 1] - marked[..., 2] > 50)
    assert changed.sum() > 50 and green[changed].mean() > 0.8
