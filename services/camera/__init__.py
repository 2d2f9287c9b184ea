"""camera: the endoscope view of the slave site, as JPEG frames on ``camera/<cam>/image``.

One process per camera. Its :class:`~telesurg.services.camera.sources.CameraSource` is either the
simulated endoscope (``source = "sim"``: the site's MuJoCo scene rendered offscreen from its
``endoscope`` camera, the arms at the slave's measured joints ``slave/<arm>/measured_js``, so the
picture shows what the slave did) or a real camera (``source = "video"``: a V4L2 device or any
URL / file FFmpeg opens, through PyAV). Each frame is encoded with simplejpeg and published with
its capture time, sequence, size and intrinsics on ``camera/<cam>/image`` at ``Priority.DATA_LOW``
with ``CongestionControl.DROP`` — below every control stream, never queued: the loop produces the
newest picture at ``fps`` and a frame that could not be made in its period is dropped and counted
(``dropped``). The camera's optical-frame pose goes out on ``camera/<cam>/measured_cp`` (x right,
y down, z along the view; frame ``base``) at ``pose_hz`` and after every move; a pose on
``camera/<cam>/servo_cp`` moves the simulated endoscope's holder. The launcher runs it under
``SCHED_IDLE``: it gets the CPU the control loops leave. Without OpenGL (no EGL, no OSMesa) the
simulated camera exits at once saying so, and ``telesurg up`` / ``demo`` go on without video.
With ``video = "h264"`` each frame also goes out as one H.264 access unit on
``camera/<cam>/video`` (shared/video.py), for viewers across a distance: its bitrate follows
their reports on ``camera/<cam>/video_feedback``, and a viewer that lost a frame gets a keyframe.

Examples::

    telesurg camera --connect tcp/127.0.0.1:7447 --set fps=12
    telesurg camera --connect tcp/127.0.0.1:7447 --set source=video --set url='"clip.mp4"'
    telesurg camera --connect tcp/127.0.0.1:7447 --set video='"h264"' --set width=640 --set height=480
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from telesurg.services.common import service_main
from telesurg.shared import robots
from telesurg.shared.bus import BusConfig, Node, Outlet
from telesurg.shared.errors import ConfigError
from telesurg.shared.kinematics import matrix_from_quat, quat_from_matrix
from telesurg.shared.messages import CameraImage, CartesianPose, JointState, VideoFeedback
from telesurg.shared.timing import CycleTimer, step_down

log = logging.getLogger("telesurg.camera")

SOURCES = ("sim", "video")
VIDEO_CODECS = ("", "h264")  # "": JPEG frames only (camera/<cam>/image)
KEYFRAME_GAP_S = 0.5  # s: keyframes the viewers ask for come at most this often


@dataclass
class CameraConfig:
    """camera config."""

    site: str = "local"  # key prefix telesurg/<site>
    service: str = "camera"  # instance id (liveliness alive/<service>, heartbeat)
    camera: str = "endo"  # camera id: the <cam> of camera/<cam>/image
    source: str = "sim"  # "sim" (MuJoCo render of the site's scene) or "video" (PyAV: device, URL, file)
    model: str = "mh3f"  # the site's robot (its scene.xml is rendered); [site] robot
    scene: str = ""  # another scene of the robot (a scene_*.xml in its folder; "" = scene.xml); [site] scene
    arm: str = "arm1"  # arm id of a single-arm robot (multi-arm robots: all their arms)
    # px: image size (both eyes together for a stereo pair). 320x240 at 12 fps measured on the
    # 2-core VM beside the 1 kHz pipeline (docs/console.md)
    width: int = 320
    height: int = 240
    fps: float = 12.0  # Hz: frames a second; a frame not made within its period is dropped (counted)
    quality: int = 80  # JPEG quality 1–100 (simplejpeg)
    stereo_baseline_m: float = 0.0  # m: > 0 renders a side-by-side stereo pair (the VIP site: 0.005)
    scene_camera: str = "endoscope"  # the MuJoCo camera rendered (source "sim")
    holder: str = "endoscope_holder"  # its mocap holder body, moved by servo_cp ("" or absent: fixed)
    url: str = ""  # source "video": /dev/videoN, rtsp://..., or a file (looped)
    loop: bool = True  # source "video": start a file over at its end
    fov_deg: float = 70.0  # deg: source "video": vertical field of view (intrinsics), until calibrated
    pose_hz: float = 10.0  # Hz: camera/<cam>/measured_cp rate (and at once after a move)
    # video for distance (docs/console.md): "h264" also publishes each frame as H.264 on
    # camera/<cam>/video, its bitrate adapted to the viewers' feedback between the two limits
    video: str = ""
    video_kbps: int = 1500  # kbit/s: the starting bitrate
    video_min_kbps: int = 200
    video_max_kbps: int = 4000
    keyframe_s: float = 2.0  # s: a keyframe at least this often (and when a viewer asks)
    # who may report on the video (camera/<cam>/video_feedback): the viewers' service ids
    feedback_sources: list[str] = field(default_factory=lambda: ["console", "telesurg-view"])
    # the slave's measured_js publisher (only it drives the rendered arms)
    slave_source: str = "slave_control"
    # who may move the camera on camera/<cam>/servo_cp ([] = anyone: a sim camera moves no patient)
    move_sources: list[str] = field(default_factory=list)
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session

    def validate(self) -> None:
        """ConfigError naming the bad key."""
        if self.source not in SOURCES:
            raise ConfigError(f"camera: source {self.source!r} invalid; valid: {', '.join(SOURCES)}")
        if self.source == "video" and not self.url:
            raise ConfigError("camera: source 'video' needs url (a device, URL or file)")
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise ConfigError(f"camera: width, height {self.width}x{self.height} outside 16..4096")
        if not 0.1 <= self.fps <= 120.0:
            raise ConfigError(f"camera: fps {self.fps} outside [0.1, 120]")
        if not 1 <= self.quality <= 100:
            raise ConfigError(f"camera: quality {self.quality} outside [1, 100]")
        if not 0.0 <= self.stereo_baseline_m <= 0.2:
            raise ConfigError(f"camera: stereo_baseline_m {self.stereo_baseline_m} outside [0, 0.2]")
        if self.pose_hz <= 0:
            raise ConfigError("camera: pose_hz must be > 0")
        if self.video not in VIDEO_CODECS:
            raise ConfigError(f"camera: video {self.video!r} invalid; valid: '' (JPEG only), 'h264'")
        if self.video and (self.width % 2 or self.height % 2):
            raise ConfigError(
                f"camera: video h264 needs an even width and height: {self.width}x{self.height}"
            )
        if not 50 <= self.video_min_kbps <= self.video_kbps <= self.video_max_kbps <= 100_000:
            raise ConfigError(
                f"camera: video kbit/s must satisfy 50 <= video_min_kbps ({self.video_min_kbps}) <= "
                f"video_kbps ({self.video_kbps}) <= video_max_kbps ({self.video_max_kbps}) <= 100000"
            )
        if not 0.2 <= self.keyframe_s <= 60.0:
            raise ConfigError(f"camera: keyframe_s {self.keyframe_s} outside [0.2, 60]")


def unavailable(cfg: CameraConfig) -> str:
    """Why this camera cannot run here ("" if it can): a simulated camera needs OpenGL (EGL or
    OSMesa, a library lookup) and a scene with its camera. For the launcher, before it starts
    anything."""
    from telesurg.services.common import gl_backend

    if cfg.source != "sim":
        return ""
    if not gl_backend():
        return (
            "no OpenGL for the MuJoCo renderer (neither libEGL nor libOSMesa found; install "
            "libegl1 libgl1-mesa-dri, or libosmesa6)"
        )
    import mujoco

    try:
        scene = robots.get(cfg.model).scene_file(cfg.scene)
        model = mujoco.MjModel.from_xml_path(str(scene))
    except (ConfigError, ValueError) as exc:
        return f"robot {cfg.model!r}: {exc}"
    if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, cfg.scene_camera) < 0:
        return f"the {cfg.model} scene ({scene}) has no camera {cfg.scene_camera!r}"
    return ""


def make_source(cfg: CameraConfig) -> Any:
    """The configured :class:`~telesurg.services.camera.sources.CameraSource`."""
    from telesurg.services.camera.sources import MujocoSource, VideoSource

    if cfg.source == "video":
        return VideoSource(cfg.url, width=cfg.width, height=cfg.height, fov_deg=cfg.fov_deg, loop=cfg.loop)
    return MujocoSource(
        robots.get(cfg.model).scene_file(cfg.scene),
        width=cfg.width,
        height=cfg.height,
        camera=cfg.scene_camera,
        holder=cfg.holder,
        stereo_baseline_m=cfg.stereo_baseline_m,
    )


def pose_matrix(msg: CartesianPose) -> np.ndarray:
    """``(4, 4)`` from a pose message (quaternion ``[x, y, z, w]``)."""
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(np.array(msg.orientation))
    T[:3, 3] = msg.position
    return T


def quat_xyzw(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion ``[x, y, z, w]`` of a rotation matrix."""
    q = quat_from_matrix(R)
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


class Camera:
    """The loop: latest joints in, newest frame out; counts what it dropped."""

    def __init__(self, cfg: CameraConfig, node: Node, source: Any) -> None:
        self.cfg, self.node, self.source = cfg, node, source
        self._lock = threading.Lock()
        self._joints: dict[str, float] = {}
        self._move: np.ndarray | None = None
        self.dropped = 0
        self.frames = 0
        self._handles: list[Any] = []  # zenoh undeclares a publisher that is garbage-collected
        self.image = self._bulk_outlet("image")
        self.pose_out = node.outlet(node.keys.camera(cfg.camera, "measured_cp"), control=False, latest=True)
        if cfg.source == "sim":
            spec = robots.get(cfg.model)
            for arm in spec.arms(cfg.arm):
                names = dict(zip(arm.joint_names, arm.model_joints, strict=True))
                node.subscribe(
                    node.keys.slave(arm.arm, "measured_js"),
                    JointState,
                    self._js_handler(names),
                    sources=[cfg.slave_source],
                    # taken at each frame (step): the newest pose of a 250 Hz stream is all a
                    # 12 fps picture needs, without a thread wake-up per message
                    polled=True,
                )
        self.encoder: Any = None
        if cfg.video:
            from telesurg.shared.video import H264Encoder, RateControl

            self.encoder = H264Encoder(cfg.width, cfg.height, cfg.fps, cfg.video_kbps, cfg.keyframe_s)
            self.rate = RateControl(cfg.video_kbps, cfg.video_min_kbps, cfg.video_max_kbps)
            self.video_out = self._bulk_outlet("video")
            self._feedback: list[VideoFeedback] = []
            self._key_pending, self._key_at = False, float("-inf")
            node.subscribe(
                node.keys.camera(cfg.camera, "video_feedback"),
                VideoFeedback,
                self._on_feedback,
                sources=cfg.feedback_sources,
            )
        node.subscribe(
            node.keys.camera(cfg.camera, "servo_cp"),
            CartesianPose,
            self._on_move,
            sources=cfg.move_sources or None,
        )

    def _bulk_outlet(self, stream: str) -> Outlet:
        """A frame stream: below every control stream (``DATA_LOW``), dropped, never queued."""
        import zenoh

        key = self.node.keys.camera(self.cfg.camera, stream)
        pub = self.node.session.declare_publisher(
            key,
            express=True,
            priority=zenoh.Priority.DATA_LOW,
            congestion_control=zenoh.CongestionControl.DROP,
        )
        self._handles.append(pub)
        return Outlet(pub, self.node.service, self.node.signer, key)

    def _put_frame(
        self, out: Outlet, encoding: str, data: bytes, shape: tuple[int, ...], frame: Any, encode_ms: float
    ) -> None:
        """One encoded frame of ``frame`` (the source's: capture time, intrinsics) on ``out``."""
        k = frame.intrinsics
        h, w = shape[:2]
        out.put(
            CameraImage(
                out.header(),
                self.cfg.camera,
                frame.capture_ns,
                w,
                h,
                encoding,
                self.source.layout,
                self.source.baseline_m,
                float(k.fx),
                float(k.fy),
                float(k.cx),
                float(k.cy),
                frame.produce_ms,
                encode_ms,
                self.dropped,
                data,
            )
        )

    def _js_handler(self, names: dict[str, str]) -> Callable[[JointState, str], None]:
        def on_js(msg: JointState, key: str) -> None:
            self._on_js(msg, names)

        return on_js

    def _on_js(self, msg: JointState, names: dict[str, str]) -> None:
        with self._lock:
            for n, q in zip(msg.names, msg.position, strict=True):
                mj = names.get(n)
                if mj is not None:
                    self._joints[mj] = q

    def _on_feedback(self, msg: VideoFeedback, key: str) -> None:
        with self._lock:
            self._feedback.append(msg)

    def _adapt(self) -> None:
        """The viewers' reports since the last frame → a keyframe if one asked, the bitrate (the
        lowest any viewer's figures allow)."""
        with self._lock:
            reports, self._feedback = self._feedback, []
        now = time.monotonic()
        self._key_pending |= any(r.keyframe for r in reports)
        if self._key_pending and now - self._key_at >= KEYFRAME_GAP_S:  # (a flood of asks: one)
            self.encoder.request_keyframe()
            self._key_pending, self._key_at = False, now
        figures = [r for r in reports if r.frames]  # (a bare keyframe ask carries none)
        if not figures:
            return
        lost = sum(r.lost for r in figures)
        age = max(r.age_p50_ms for r in figures)
        kbps = self.rate.update(lost, age, now)
        if kbps != self.encoder.kbps:
            log.info("camera %s: video %d kbit/s (lost %d, age %.0f ms)", self.cfg.camera, kbps, lost, age)
            self.encoder.set_kbps(kbps)

    def _publish_video(self, rgb: np.ndarray, frame: Any) -> None:
        self._adapt()
        t0 = time.perf_counter()
        data, _key = self.encoder.encode(rgb)
        if data:
            self._put_frame(self.video_out, "h264", data, rgb.shape, frame, (time.perf_counter() - t0) * 1e3)

    def _on_move(self, msg: CartesianPose, key: str) -> None:
        if msg.frame != "base":
            self.node.event(
                "camera_move_refused", f"pose frame {msg.frame!r}, expected 'base'", severity="warning"
            )
            return
        with self._lock:
            self._move = pose_matrix(msg)

    def publish_pose(self) -> None:
        T = self.source.pose()
        if T is None:
            return
        out = self.pose_out
        p = (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]))
        out.put(CartesianPose(out.header(), "base", p, quat_xyzw(T[:3, :3])))

    def step(self) -> None:
        """Apply a pending move, grab, encode, publish one frame."""
        import simplejpeg

        self.node.poll()  # the arm's joints up to now (measured_js, polled)
        with self._lock:
            joints, move, self._move = dict(self._joints), self._move, None
        if move is not None:
            try:
                self.source.move(move)
                self.node.event(
                    "camera_moved", f"camera {self.cfg.camera} moved to {move[:3, 3].round(4).tolist()}"
                )
            except ConnectionError as exc:
                self.node.event("camera_move_refused", str(exc), severity="warning")
            self.publish_pose()
        frame = self.source.grab(joints)
        t0 = time.perf_counter()
        rgb = np.ascontiguousarray(frame.rgb)
        data = simplejpeg.encode_jpeg(rgb, quality=self.cfg.quality, colorspace="RGB")
        self._put_frame(self.image, "jpeg", data, rgb.shape, frame, (time.perf_counter() - t0) * 1e3)
        if self.encoder is not None:
            self._publish_video(rgb, frame)
        self.frames += 1


def run(cfg: CameraConfig, stop: threading.Event) -> None:
    """Serve frames until ``stop``."""
    cfg.validate()
    from telesurg.services.camera.sources import CameraError

    try:
        source = make_source(cfg)
    except CameraError as exc:
        raise CameraError(f"camera off: {exc}") from None
    try:
        with Node(cfg.bus, cfg.site, cfg.service) as node:
            cam = Camera(cfg, node, source)
            cam.publish_pose()
            log.info(
                "camera %s: %s %dx%d at %.1f fps on %s",
                cfg.camera,
                cfg.source,
                cfg.width,
                cfg.height,
                cfg.fps,
                node.keys.camera(cfg.camera, "image"),
            )
            step_down()  # set up: below the control path from now on, if the launcher asked
            timer = CycleTimer(cfg.fps, resync=True)  # a late frame: the next at once
            every = max(1, round(cfg.fps / cfg.pose_hz))
            while not stop.is_set():
                cam.step()
                if cam.frames % every == 0:
                    cam.publish_pose()
                cam.dropped += timer.wait()  # whole periods lost: frames never made (newest wins)
            log.info("camera %s: %d frames sent, %d dropped", cfg.camera, cam.frames, cam.dropped)
    finally:
        source.close()


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg camera``."""
    return service_main("camera", CameraConfig, run, argv, __doc__ or "")
