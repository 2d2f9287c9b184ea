"""Camera sources behind one interface: the simulated endoscope (MuJoCo) and a real camera (PyAV).

A :class:`CameraSource` yields RGB frames (``(h, w, 3)`` uint8) with the pinhole intrinsics of one
eye and, for a source that knows it, the pose of its optical frame in the site's base frame
(OpenCV convention: x right, y down, z along the view). Heavy imports (mujoco, av) happen inside
the chosen source.

* :class:`MujocoSource` renders the site's MuJoCo scene (the robot's ``scene.xml``) from its
  ``endoscope`` camera with MuJoCo's offscreen renderer, the arms set to the joints the caller
  passes (the slave's ``measured_js``). Shadows, reflections, skybox and multisampling are off:
  on the 2-core VM that is ~15 ms a 320×240 frame instead of ~140 ms. ``stereo_baseline_m > 0``
  renders a side-by-side pair (left eye left). The camera's holder is a mocap body, so
  :meth:`MujocoSource.move` moves it.
* :class:`VideoSource` reads a V4L2 device or any URL / file FFmpeg opens, through PyAV; a file
  loops (``loop=True``) so a recorded clip stands in for a live camera.

Example::

    src = MujocoSource(robots.get("mh3f").scene, width=320, height=240)
    frame = src.grab({"j1": 0.0, ...})        # Frame(rgb, intrinsics, pose, t_ns)
"""

from __future__ import annotations

import abc
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from telesurg.services.common import gl_backend
from telesurg.shared.clock import wall_ns
from telesurg.shared.errors import ConfigError

FloatArray = npt.NDArray[np.float64]
#: MuJoCo camera frame (x right, y up, looks along −z) → OpenCV optical frame (x right, y down, z view).
MJ_TO_CV = np.diag([1.0, -1.0, -1.0])


class CameraError(ConnectionError):
    """The camera cannot produce frames (no OpenGL for the renderer, a device or file that does
    not open); the message says why."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of one eye, pixels: ``u = fx·x/z + cx``, ``v = fy·y/z + cy``."""

    fx: float
    fy: float
    cx: float
    cy: float


@dataclass(frozen=True)
class Frame:
    """One picture: RGB ``(h, w, 3)`` uint8, the time it shows (wall clock ns), its intrinsics, the
    optical-frame pose ``(4, 4)`` in the base frame (None if unknown), and its production time."""

    rgb: npt.NDArray[np.uint8]
    capture_ns: int
    intrinsics: Intrinsics
    pose: FloatArray | None
    produce_ms: float


class CameraSource(abc.ABC):
    """Where frames come from."""

    layout: str = "mono"  # "mono" or "stereo_sbs"
    baseline_m: float = 0.0

    @abc.abstractmethod
    def grab(self, joints: dict[str, float] | None = None) -> Frame:
        """The next frame; ``joints`` (model joint name → position) for a simulated scene."""

    def pose(self) -> FloatArray | None:
        """Optical-frame pose ``(4, 4)`` in the base frame now, None if the source cannot tell."""
        return None

    def move(self, pose: FloatArray) -> None:
        """Move the camera (its holder) to the optical-frame pose ``(4, 4)``.

        Raises:
            CameraError: this camera cannot be moved.
        """
        raise CameraError(f"{type(self).__name__} cannot be moved")

    def close(self) -> None:  # noqa: B027 - optional
        """Release the device / renderer."""


def _gl_backend() -> str:
    """Choose MuJoCo's GL backend before mujoco is imported: EGL, else OSMesa, as installed."""
    backend = gl_backend()
    if not backend:
        raise CameraError(
            "no OpenGL for the MuJoCo renderer: install libegl1 + libgl1-mesa-dri (EGL) or libosmesa6"
        )
    os.environ["MUJOCO_GL"] = backend
    if backend in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", backend)
    return backend


class MujocoSource(CameraSource):
    """The site's MuJoCo scene rendered from its ``camera`` (default ``endoscope``)."""

    def __init__(
        self,
        scene: Path,
        *,
        width: int = 320,
        height: int = 240,
        camera: str = "endoscope",
        holder: str = "endoscope_holder",
        stereo_baseline_m: float = 0.0,
        hide_bodies: tuple[str, ...] = (),
    ) -> None:
        backend = _gl_backend()
        import mujoco

        self._mj = mujoco
        try:
            self.model = mujoco.MjModel.from_xml_path(str(scene))
        except ValueError as exc:
            raise ConfigError(f"camera: scene {scene}: {exc}") from None
        m = self.model
        cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if cam < 0:
            names = [m.camera(i).name for i in range(m.ncam)]
            raise ConfigError(f"camera: scene {scene} has no camera {camera!r}; cameras: {names}")
        self._cam = cam
        body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, holder)
        self._mocap = int(m.body_mocapid[body]) if body >= 0 else -1
        self.data = mujoco.MjData(m)
        for b in hide_bodies:  # the "without the arm" view: hide the bodies' geoms
            bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b)
            if bid < 0:
                raise ConfigError(f"camera: no body {b!r} to hide")
            for g in range(m.ngeom):
                if _descends(m, int(m.geom_bodyid[g]), bid):
                    m.geom_rgba[g, 3] = 0.0
        m.vis.quality.offsamples = 0
        m.vis.global_.offwidth = max(m.vis.global_.offwidth, width)
        m.vis.global_.offheight = max(m.vis.global_.offheight, height)
        self.width, self.height = width, height
        self.baseline_m = float(stereo_baseline_m)
        self.layout = "stereo_sbs" if self.baseline_m > 0 else "mono"
        eye_w = width // 2 if self.baseline_m > 0 else width
        self._eye_w = eye_w
        try:
            self._renderer = mujoco.Renderer(m, height=height, width=eye_w)
        except Exception as exc:  # GL context creation: mujoco raises several types
            raise CameraError(f"MuJoCo renderer ({backend}) failed: {exc}") from None
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION):
            self._renderer.scene.flags[flag] = False
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = False
        fovy = float(m.cam_fovy[cam])
        f = 0.5 * height / np.tan(np.radians(fovy) / 2.0)
        self.intrinsics = Intrinsics(f, f, eye_w / 2.0, height / 2.0)
        self._qadr = {m.joint(j).name: int(m.jnt_qposadr[j]) for j in range(m.njnt)}
        self._opt = mujoco.MjvOption()
        mujoco.mj_forward(m, self.data)

    def set_joints(self, joints: dict[str, float]) -> None:
        """Set the scene's joints (unknown names are ignored)."""
        for name, q in joints.items():
            adr = self._qadr.get(name)
            if adr is not None:
                self.data.qpos[adr] = q

    def grab(self, joints: dict[str, float] | None = None) -> Frame:
        t0 = time.perf_counter()
        capture_ns = wall_ns()
        if joints:
            self.set_joints(joints)
        self._mj.mj_kinematics(self.model, self.data)
        self._mj.mj_camlight(self.model, self.data)
        if self.baseline_m > 0:
            left = self._render_eye(-0.5 * self.baseline_m)
            right = self._render_eye(0.5 * self.baseline_m)
            rgb = np.concatenate([left, right], axis=1)
        else:
            rgb = self._render_eye(0.0)
        return Frame(rgb, capture_ns, self.intrinsics, self.pose(), (time.perf_counter() - t0) * 1e3)

    def _render_eye(self, dx: float) -> npt.NDArray[np.uint8]:
        mj = self._mj
        r = self._renderer
        if dx == 0.0:
            r.update_scene(self.data, camera=self._cam, scene_option=self._opt)
        else:  # a free camera at the eye: the endoscope's pose shifted along its x axis
            cam = mj.MjvCamera()
            mj.mjv_defaultFreeCamera(self.model, cam)
            r.update_scene(self.data, camera=self._cam, scene_option=self._opt)
            for c in r.scene.camera:
                c.pos[:] = np.asarray(c.pos) + dx * self.data.cam_xmat[self._cam].reshape(3, 3)[:, 0]
        out: npt.NDArray[np.uint8] = r.render()
        return out

    def pose(self) -> FloatArray:
        T = np.eye(4)
        T[:3, :3] = self.data.cam_xmat[self._cam].reshape(3, 3) @ MJ_TO_CV
        T[:3, 3] = self.data.cam_xpos[self._cam]
        return T

    def move(self, pose: FloatArray) -> None:
        if self._mocap < 0:
            raise CameraError("this scene's endoscope has no mocap holder to move")
        # the camera sits at its holder's origin, aligned with it (scene.xml)
        R = np.asarray(pose, dtype=np.float64)[:3, :3] @ MJ_TO_CV
        q = np.zeros(4)
        self._mj.mju_mat2Quat(q, R.flatten())
        self.data.mocap_pos[self._mocap] = np.asarray(pose)[:3, 3]
        self.data.mocap_quat[self._mocap] = q
        self._mj.mj_kinematics(self.model, self.data)
        self._mj.mj_camlight(self.model, self.data)

    def close(self) -> None:
        self._renderer.close()


def _descends(m: Any, body: int, ancestor: int) -> bool:
    while body > 0:
        if body == ancestor:
            return True
        body = int(m.body_parentid[body])
    return ancestor == 0


class VideoSource(CameraSource):
    """A real camera: a V4L2 device (``/dev/video0``) or any URL / file FFmpeg opens (PyAV)."""

    def __init__(
        self,
        url: str,
        *,
        width: int = 0,
        height: int = 0,
        fov_deg: float = 70.0,
        loop: bool = True,
        options: dict[str, str] | None = None,
    ) -> None:
        import av

        self._av = av
        self.url, self.loop = url, loop
        fmt = "v4l2" if url.startswith("/dev/video") else None
        try:
            self._container = av.open(url, format=fmt, options=options or {})
        except (OSError, av.FFmpegError) as exc:
            raise CameraError(f"camera {url!r} does not open: {exc}") from None
        if not self._container.streams.video:
            raise CameraError(f"{url!r} has no video stream")
        self._stream = self._container.streams.video[0]
        self._stream.thread_type = "AUTO"
        self._frames = self._container.decode(self._stream)
        self.width = width or int(self._stream.codec_context.width)
        self.height = height or int(self._stream.codec_context.height)
        f = 0.5 * self.height / np.tan(np.radians(fov_deg) / 2.0)
        self.intrinsics = Intrinsics(f, f, self.width / 2.0, self.height / 2.0)
        self._is_file = Path(url).is_file()

    def grab(self, joints: dict[str, float] | None = None) -> Frame:
        t0 = time.perf_counter()
        try:
            frame = next(self._frames)
        except StopIteration:
            if not (self.loop and self._is_file):
                raise CameraError(f"{self.url!r} ended") from None
            self._container.seek(0)
            self._frames = self._container.decode(self._stream)
            frame = next(self._frames)
        except self._av.FFmpegError as exc:
            raise CameraError(f"{self.url!r}: {exc}") from None
        capture_ns = wall_ns()
        rgb: npt.NDArray[np.uint8] = np.asarray(
            frame.to_ndarray(format="rgb24", width=self.width, height=self.height), dtype=np.uint8
        )
        return Frame(rgb, capture_ns, self.intrinsics, None, (time.perf_counter() - t0) * 1e3)

    def close(self) -> None:
        self._container.close()
