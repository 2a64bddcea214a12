"""Videos of episodes: MuJoCo's offscreen renderer to RGB frames, frames to MP4.

The OpenGL backend is chosen per process by name (`egl`, `osmesa` or `glfw`, see `BACKENDS`):
`VideoRecorder` builds its GL context from MuJoCo's module of that name (`mujoco.egl`, ...)
rather than from the one `import mujoco` picked from ``MUJOCO_GL``, so a config value works
whatever was imported first. `resolve_backend` turns a configured name (or None) into one:
the configured name, else ``MUJOCO_GL`` when it names one of `BACKENDS`, else `egl` on Linux
(headless: a GPU's EGL, or Mesa's software EGL on CPU-only machines) and `glfw` elsewhere.
PyOpenGL binds one platform per process, so a process renders with one backend only.

MP4 files are written atomically: frames go to a hidden temporary ``.mp4`` in the destination
folder, which is fsynced and then renamed onto the destination, so a failed render or encode
never leaves a broken file under the final name (nor touches any other file of the run).
"""

from __future__ import annotations

import copy
import importlib
import logging
import math
import os
import platform
import uuid
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import mujoco
import numpy as np
import torch
from tensordict import TensorDictBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.systems.system import FREE, SLIDE

log = logging.getLogger(__name__)

BACKENDS: tuple[str, ...] = ("egl", "osmesa", "glfw")
DEFAULT_ELEVATION = -10.0  # degrees; nearly side-on, which suits the planar (x-z) systems
_FIT_MARGIN = 1.15  # free camera: room around the reach of the chain, as a factor

_HINT = (
    "Choose another backend with video_backend=egl|osmesa|glfw (or, with video_backend=null, "
    "the MUJOCO_GL environment variable), or turn videos off with video=false. EGL works on "
    "GPU machines and, through Mesa (libegl1), on CPU-only ones; OSMesa needs libOSMesa "
    "(e.g. apt-get install libosmesa6); glfw needs a display. See docs/videos.md"
)


class VideoBackendError(RuntimeError):
    """No OpenGL context can be made (or used) with the requested backend."""


# What rendering or encoding a video can raise at run time, for callers that carry on without
# the video (e.g. a training run whose checkpoints and logs matter more than its pictures).
RENDER_ERRORS: tuple[type[Exception], ...] = (
    VideoBackendError,
    mujoco.FatalError,
    RuntimeError,
    OSError,
    ValueError,
)


def default_backend(environ: Mapping[str, str] | None = None) -> str:
    """``MUJOCO_GL`` when it names one of `BACKENDS`, else `egl` on Linux and `glfw` elsewhere."""
    environ = os.environ if environ is None else environ
    value = environ.get("MUJOCO_GL", "").strip().lower()
    if value in BACKENDS:
        return value
    if value:
        log.warning(
            "MUJOCO_GL=%r is not one of %s for videos; using the default backend",
            value,
            ", ".join(BACKENDS),
        )
    return "egl" if platform.system() == "Linux" else "glfw"


def resolve_backend(backend: str | None, environ: Mapping[str, str] | None = None) -> str:
    """The backend to render with: `backend` itself, or `default_backend` when it is None.

    Raises:
        VideoBackendError: `backend` is not one of `BACKENDS`.
    """
    if backend is None:
        return default_backend(environ)
    name = str(backend).strip().lower()
    if name not in BACKENDS:
        raise VideoBackendError(
            f"video_backend={backend!r} is not a MuJoCo OpenGL backend; use one of "
            f"{', '.join(BACKENDS)} (or null to follow MUJOCO_GL)"
        )
    return name


def _with_notes(message: str, notes: Sequence[str]) -> str:
    return message + "".join(f" [{note}]" for note in dict.fromkeys(notes))


def _backend_error(
    backend: str, err: BaseException, notes: Sequence[str] = ()
) -> VideoBackendError:
    cause = _with_notes(f"{type(err).__name__}: {err}", notes)
    return VideoBackendError(
        f"MuJoCo cannot render with the OpenGL backend {backend!r} ({cause}). {_HINT}"
    )


def make_gl_context(backend: str, width: int, height: int) -> Any:
    """A current OpenGL context of `backend` (`mujoco.<backend>.GLContext`) of at least this size.

    Raises:
        VideoBackendError: the backend's libraries are missing or no context can be made.
    """
    name = resolve_backend(backend)
    try:
        module = importlib.import_module(f"mujoco.{name}")
        context = module.GLContext(width, height)
        context.make_current()
    # Missing libraries surface as ImportError, AttributeError (PyOpenGL without its platform
    # library), OSError, RuntimeError or PyOpenGL's own errors; all mean "not this backend".
    except Exception as err:  # noqa: BLE001
        raise _backend_error(name, err) from err
    return context


def root_travels(types: Sequence[int]) -> bool:
    """Whether a system with these joint types (`JointLayout.types`) moves its root through
    space: a free or slide first joint (a humanoid, the cart-pole's cart). Its videos track
    the root (`VideoRecorder`'s ``track_root``); a fixed base keeps a fixed view."""
    return bool(types) and types[0] in (FREE, SLIDE)


Overlay = tuple[str, str]  # the text of a frame's corner: (titles, values), one line each
MARKER_RADIUS = 0.05  # a task marker's sphere, as a fraction of the model's extent
MARKER_RGBA = np.array([0.1, 0.9, 0.2, 1.0], dtype=np.float32)  # green
GHOST_RGBA = np.array([0.3, 0.6, 1.0, 0.4], dtype=np.float32)  # a reference pose: translucent blue
RAIL_RGBA = np.array([0.55, 0.55, 0.55, 1.0], dtype=np.float32)  # the posts behind a tracked root
RAIL_SPACING = 0.25  # between two posts, as a fraction of the model's extent


@dataclass(frozen=True)
class Rail:
    """Fixed grey posts along the world x axis behind a tracked root: the camera follows the
    root, so without something fixed in view (the cart-pole has no floor) its travel would
    not be seen. Posts every `spacing` m, drawn within `reach` of the root's x."""

    spacing: float
    reach: float
    y: float  # behind the bodies, as the side-on camera looks along +y
    z: float  # the posts' centre height
    half_height: float
    half_width: float

    @classmethod
    def behind(cls, model: mujoco.MjModel, root: int) -> Rail:
        """Posts from the lowest geom to the root body's height at ``qpos0``."""
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        extent = max(float(model.stat.extent), 1e-3)
        top = float(data.xpos[root][2])
        low = float(data.geom_xpos[:, 2].min()) if model.ngeom else top - 0.5 * extent
        half = max(0.5 * (top - low), 0.1 * extent)
        return cls(
            RAIL_SPACING * extent, 3.0 * extent, 0.6 * extent, top - half, half, 0.01 * extent
        )

    def add_to(self, scene: mujoco.MjvScene, root_x: float) -> None:
        """Append the posts within `reach` of `root_x` to `scene`."""
        first = math.ceil((root_x - self.reach) / self.spacing)
        last = math.floor((root_x + self.reach) / self.spacing)
        size = np.array([self.half_width, self.half_width, self.half_height])
        for k in range(first, last + 1):
            if scene.ngeom >= scene.maxgeom:
                return
            pos = np.array([k * self.spacing, self.y, self.z])
            mujoco.mjv_initGeom(
                scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_BOX, size, pos,
                np.eye(3).reshape(-1), RAIL_RGBA,
            )  # fmt: skip
            scene.ngeom += 1


class VideoRecorder:
    """Renders a MuJoCo model to RGB frames and writes them to MP4.

    Frames come from generalized states (`frame_from_state`, `frames_from_states`) or from a
    live `MjData` (`frame_from_data`, e.g. the real env's). The recorder owns a copy of the
    model (with its offscreen buffer enlarged to fit), an `MjData`, a GL context and MuJoCo's
    render context; `close` (or leaving a ``with`` block) frees them.

    Args:
        model: the MuJoCo model to draw.
        width: frame width in pixels (even: H.264 with yuv420p needs even sizes).
        height: frame height in pixels (even).
        fps: frames per second of the written videos (the control rate gives real time).
        camera: a camera of the model by name or id, or -1 for a free camera. The free camera
            looks at the root body's origin (at ``qpos0``) from far enough to keep everything
            the chain can reach in view, unless `lookat` / `distance` say otherwise.
        backend: OpenGL backend, one of `BACKENDS`; None: `default_backend()`.
        azimuth: free camera azimuth in degrees (None: the model's, 90 = looking along +y).
        elevation: free camera elevation in degrees.
        lookat: free camera target point (3,), or None (fit as above).
        distance: free camera distance, or None (fit as above).
        track_root: the free camera follows the root body's subtree (MuJoCo's tracking
            camera), for systems that travel (a walking humanoid leaves a fixed view).
        markers: world points (x, y, z) drawn in every frame as small green spheres
            (`Task.markers`: arm_reach's target).

    Raises:
        ValueError: a bad size, fps or camera.
        VideoBackendError: no GL context can be made with `backend`.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        width: int,
        height: int,
        fps: float,
        camera: str | int = -1,
        backend: str | None = None,
        azimuth: float | None = None,
        elevation: float = DEFAULT_ELEVATION,
        lookat: Sequence[float] | None = None,
        distance: float | None = None,
        track_root: bool = False,
        markers: Sequence[Sequence[float]] = (),
    ) -> None:
        for label, size in (("width", width), ("height", height)):
            if not isinstance(size, int | np.integer) or size < 2 or size % 2:
                raise ValueError(f"video {label}={size!r}: it must be an even integer >= 2")
        if not fps > 0:
            raise ValueError(f"video fps={fps!r}: it must be > 0")
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.markers = np.asarray(markers, dtype=np.float64).reshape(-1, 3)  # (K, 3)
        self.backend = resolve_backend(backend)
        self.model = copy.deepcopy(model)
        offscreen = self.model.vis.global_
        offscreen.offwidth = max(offscreen.offwidth, self.width)
        offscreen.offheight = max(offscreen.offheight, self.height)
        if self.model.nlight == 0:  # only MuJoCo's headlight: make it bright enough to see
            self.model.vis.headlight.ambient[:] = 0.35
            self.model.vis.headlight.diffuse[:] = 0.75
        self.data = mujoco.MjData(self.model)
        self._ghost_data = mujoco.MjData(self.model)  # a reference pose drawn translucent
        self.camera = self._camera(camera, azimuth, elevation, lookat, distance)
        self.rail: Rail | None = None
        if track_root and self.camera.type == mujoco.mjtCamera.mjCAMERA_FREE:
            self.camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
            self.camera.trackbodyid = 1 if self.model.nbody > 1 else 0
            self.rail = Rail.behind(self.model, self.camera.trackbodyid)
        self._gl: Any = None
        self._context: mujoco.MjrContext | None = None
        # Backends report the cause of a failure as warnings (glfw: "DISPLAY ... missing")
        # and fail only later, in MjrContext: keep the warnings for the error message.
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                self._gl = make_gl_context(self.backend, self.width, self.height)
                self._context = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_150)
                mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._context)
            except Exception as err:  # noqa: BLE001 - mujoco.FatalError and GL errors alike
                self._free_quietly()
                notes = [str(w.message) for w in caught]
                if isinstance(err, VideoBackendError):
                    raise VideoBackendError(_with_notes(str(err), notes)) from err.__cause__
                raise _backend_error(self.backend, err, notes) from err
        for w in caught:
            log.debug("while opening the %s GL context: %s", self.backend, w.message)
        self._scene = mujoco.MjvScene(self.model, maxgeom=10_000)
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._viewport = mujoco.MjrRect(0, 0, self.width, self.height)

    def _camera(
        self,
        camera: str | int,
        azimuth: float | None,
        elevation: float,
        lookat: Sequence[float] | None,
        distance: float | None,
    ) -> mujoco.MjvCamera:
        cam = mujoco.MjvCamera()
        if isinstance(camera, str):
            cam_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
            if cam_id < 0:
                raise ValueError(f"the model has no camera named {camera!r}")
            camera = cam_id
        if camera >= 0:
            if camera >= self.model.ncam:
                raise ValueError(f"camera id {camera} is out of range (ncam={self.model.ncam})")
            cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
            cam.fixedcamid = int(camera)
            return cam
        mujoco.mjv_defaultFreeCamera(self.model, cam)
        fit_lookat, fit_distance = self._fit_free_camera()
        cam.lookat[:] = fit_lookat if lookat is None else np.asarray(lookat, dtype=np.float64)
        cam.distance = fit_distance if distance is None else float(distance)
        if azimuth is not None:
            cam.azimuth = float(azimuth)
        cam.elevation = float(elevation)
        return cam

    def _fit_free_camera(self) -> tuple[np.ndarray, float]:
        """Root body origin at qpos0, and a distance that shows a sphere of the chain's reach.

        The reach is twice the farthest geom extent from the root at qpos0 (a chain hanging
        down can swing up to the same distance above), at least the model's extent.
        """
        mujoco.mj_forward(self.model, self.data)
        root = self.data.xpos[1].copy() if self.model.nbody > 1 else self.model.stat.center
        if self.model.ngeom:
            reach = np.linalg.norm(self.data.geom_xpos - root, axis=1) + self.model.geom_rbound
            radius = float(reach.max())
        else:
            radius = float(self.model.stat.extent)
        radius = max(radius, 1e-3) * _FIT_MARGIN
        half_fov = np.deg2rad(self.model.vis.global_.fovy) / 2.0
        aspect = min(1.0, self.width / self.height)  # fovy is vertical: narrow frames need room
        return root, radius / (np.tan(half_fov) * aspect)

    def frame_from_data(
        self,
        data: mujoco.MjData,
        overlay: Overlay | None = None,
        ghost: mujoco.MjData | None = None,
    ) -> np.ndarray:
        """The picture of `data` (kinematics must be current), uint8 (height, width, 3);
        `overlay` (titles, values): two columns of text in the top-left corner; `ghost`: a
        second pose of the same model (kinematics current) drawn translucent in the frame."""
        if self._context is None:
            raise RuntimeError("VideoRecorder used after close()")
        self._gl.make_current()
        mujoco.mjv_updateScene(
            self.model,
            data,
            self._option,
            self._perturb,
            self.camera,
            mujoco.mjtCatBit.mjCAT_ALL,
            self._scene,
        )
        if ghost is not None:
            self._add_ghost(ghost)
        self._add_markers()
        if self.rail is not None:
            self.rail.add_to(self._scene, float(data.xpos[self.camera.trackbodyid][0]))
        mujoco.mjr_render(self._viewport, self._scene, self._context)
        if overlay is not None:
            font, corner = mujoco.mjtFont.mjFONT_SHADOW, mujoco.mjtGridPos.mjGRID_TOPLEFT
            mujoco.mjr_overlay(font, corner, self._viewport, *overlay, self._context)
        pixels = np.empty((self.height, self.width, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(pixels, None, self._viewport, self._context)
        return np.ascontiguousarray(pixels[::-1])  # OpenGL's rows run bottom-up

    def _add_ghost(self, ghost: mujoco.MjData) -> None:
        """Append the moving bodies' geoms of the `ghost` pose to the scene, translucent."""
        first = self._scene.ngeom
        mujoco.mjv_addGeoms(
            self.model,
            ghost,
            self._option,
            self._perturb,
            mujoco.mjtCatBit.mjCAT_DYNAMIC,
            self._scene,
        )
        for i in range(first, self._scene.ngeom):
            self._scene.geoms[i].rgba[:] = GHOST_RGBA

    def _add_markers(self) -> None:
        """Append a sphere per marker to the scene (after `mjv_updateScene` filled it)."""
        radius = MARKER_RADIUS * max(float(self.model.stat.extent), 1e-3)
        for point in self.markers:
            if self._scene.ngeom >= self._scene.maxgeom:
                return
            mujoco.mjv_initGeom(
                self._scene.geoms[self._scene.ngeom],
                mujoco.mjtGeom.mjGEOM_SPHERE,
                np.array([radius, 0.0, 0.0]),
                point,
                np.eye(3).reshape(-1),
                MARKER_RGBA,
            )
            self._scene.ngeom += 1

    def frame_from_state(
        self,
        q: Tensor | np.ndarray,
        qd: Tensor | np.ndarray,
        overlay: Overlay | None = None,
        ghost_q: Tensor | np.ndarray | None = None,
    ) -> np.ndarray:
        """The picture of the state (q (nq,), qd (nv,)), uint8 (height, width, 3), with the
        pose `ghost_q` (nq,) drawn translucent in the same frame (a reference to follow)."""
        self.data.qpos[:] = _numpy(q)
        self.data.qvel[:] = _numpy(qd)
        mujoco.mj_forward(self.model, self.data)
        ghost = None
        if ghost_q is not None:
            self._ghost_data.qpos[:] = _numpy(ghost_q)
            mujoco.mj_kinematics(self.model, self._ghost_data)
            ghost = self._ghost_data
        return self.frame_from_data(self.data, overlay, ghost)

    def frames_from_states(
        self,
        q: Tensor | np.ndarray,
        qd: Tensor | np.ndarray,
        overlays: Sequence[Overlay] | None = None,
        ghost_q: Tensor | np.ndarray | None = None,
    ) -> np.ndarray:
        """Pictures of a state sequence (q (T, nq), qd (T, nv)), uint8 (T, height, width, 3);
        `overlays`: one (titles, values) text per frame (`step_reward_overlays`); `ghost_q`:
        one pose (T, nq) per frame drawn translucent (a tracking task's reference)."""
        q_np, qd_np = _numpy(q), _numpy(qd)
        if q_np.ndim != 2 or qd_np.ndim != 2 or q_np.shape[0] != qd_np.shape[0]:
            raise ValueError(f"want q (T, nq) and qd (T, nv), got {q_np.shape}, {qd_np.shape}")
        if overlays is not None and len(overlays) != q_np.shape[0]:
            raise ValueError(f"{len(overlays)} overlays for {q_np.shape[0]} frames")
        ghosts = None if ghost_q is None else _numpy(ghost_q)
        if ghosts is not None and ghosts.shape != q_np.shape:
            raise ValueError(f"want ghost poses {q_np.shape}, got {ghosts.shape}")
        frames = np.empty((q_np.shape[0], self.height, self.width, 3), dtype=np.uint8)
        for t in range(q_np.shape[0]):
            text = None if overlays is None else overlays[t]
            ghost = None if ghosts is None else ghosts[t]
            frames[t] = self.frame_from_state(q_np[t], qd_np[t], text, ghost)
        return frames

    def write(self, path: str | Path, frames: np.ndarray | Sequence[np.ndarray]) -> Path:
        """Write `frames` to the MP4 `path` atomically at this recorder's fps."""
        return write_mp4(path, frames, self.fps)

    def record(
        self,
        path: str | Path,
        q: Tensor | np.ndarray,
        qd: Tensor | np.ndarray,
        overlays: Sequence[Overlay] | None = None,
        ghost_q: Tensor | np.ndarray | None = None,
    ) -> Path:
        """Render the state sequence (q (T, nq), qd (T, nv)), with the poses `ghost_q`
        (T, nq) translucent in the same frames, and write it to the MP4 `path`."""
        return self.write(path, self.frames_from_states(q, qd, overlays, ghost_q))

    def _free_quietly(self) -> None:
        """`close` after a failed start: what is half made may not free cleanly."""
        try:
            self.close()
        except Exception as err:  # noqa: BLE001 - the start's own error matters more
            log.debug("freeing a failed %s GL context: %s", self.backend, err)
        self._context, self._gl = None, None

    def close(self) -> None:
        """Free the render and GL contexts. Safe to call twice."""
        if self._context is not None:
            self._gl.make_current()
            self._context.free()
            self._context = None
        if self._gl is not None:
            self._gl.free()
            self._gl = None

    def __enter__(self) -> VideoRecorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def step_reward_overlays(rollout: TensorDictBase) -> list[Overlay]:
    """The text of each of a (T,) rollout's T + 1 frames: its step and the reward of the step
    that reached it (none at the first)."""
    rewards = rollout.get(keys.NEXT_REWARD).reshape(-1).tolist()  # (T,)
    values = ["0\n-"] + [f"{t + 1}\n{r:.3f}" for t, r in enumerate(rewards)]
    return [("step\nreward", text) for text in values]


def rollout_states(rollout: TensorDictBase) -> tuple[Tensor, Tensor]:
    """The T + 1 states of a (T,) rollout: its first state, then every reached one.

    -> q (T + 1, nq), qd (T + 1, nv).
    """
    q = torch.cat([rollout.get(keys.Q)[:1], rollout.get(keys.NEXT_Q)])
    qd = torch.cat([rollout.get(keys.QD)[:1], rollout.get(keys.NEXT_QD)])
    return q, qd


def _numpy(x: Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().cpu().to(torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def write_mp4(path: str | Path, frames: np.ndarray | Sequence[np.ndarray], fps: float) -> Path:
    """Encode RGB frames (T, H, W, 3) uint8 to H.264 MP4 at `path`, atomically.

    The video is written to a hidden temporary ``.mp4`` next to `path`, fsynced and renamed
    onto `path`; on any failure the temporary file is removed and `path` is left as it was.
    H and W must be even. Needs `imageio` with `imageio-ffmpeg` (which ships ffmpeg).
    """
    import imageio.v2 as imageio  # on demand: only runs with videos need it

    path = Path(path)
    array = np.asarray(frames)
    if array.ndim != 4 or array.shape[0] == 0 or array.shape[-1] != 3:
        raise ValueError(f"want frames of shape (T >= 1, H, W, 3), got {array.shape}")
    if array.shape[1] % 2 or array.shape[2] % 2:
        raise ValueError(f"frame size {array.shape[2]}x{array.shape[1]} must be even")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp.mp4")
    try:
        writer = imageio.get_writer(
            tmp,
            format="FFMPEG",
            mode="I",
            fps=fps,
            codec="libx264",
            pixelformat="yuv420p",
            macro_block_size=2,
            ffmpeg_log_level="error",
        )
        try:
            for frame in array:
                writer.append_data(np.ascontiguousarray(frame, dtype=np.uint8))
        finally:
            writer.close()
        with tmp.open("rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def check_backend(backend: str | None) -> str:
    """Render one tiny frame with `backend` (None: `default_backend()`); -> the backend used.

    Raises:
        VideoBackendError: with the backend's name and how to choose another.
    """
    name = resolve_backend(backend)
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><geom type="sphere" size="0.1"/></worldbody></mujoco>'
    )
    with VideoRecorder(model, 16, 16, fps=1.0, backend=name) as recorder:
        try:
            frame = recorder.frame_from_state(np.zeros(0), np.zeros(0))
        except Exception as err:  # noqa: BLE001 - see make_gl_context
            raise _backend_error(name, err) from err
    if not frame.any():
        raise VideoBackendError(
            f"MuJoCo's OpenGL backend {name!r} rendered an empty (black) test frame. {_HINT}"
        )
    return name
