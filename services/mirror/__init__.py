"""mirror: streams the site's bus to rerun (web viewer on localhost, or an .rrd file).

Subscribes to the streams it draws under ``telesurg/<site>/`` (slave joints, setpoints, tip poses
and operating state; master poses and buttons; the watchdog's state; events), decodes every
sample with the strict decoder (malformed payloads are counted and dropped, never drawn) and
draws: joint series (measured vs setpoint), the tip tracking and RCM errors, latency, tip and
target trails, the mapping's teleop state of each pair (a text line per change, an engaged
series), each slave arm from its kinematic model (the robot is recognised by the joint names
of ``measured_js`` among the registered robots and drawn by its registry entry's ``sketch``, see
:mod:`telesurg.shared.robots`; ``--plugin FILE`` adds robots), the robot's own bodies from its
MuJoCo scene posed by ``mj_kinematics`` at the measured joints
(:mod:`telesurg.services.mirror.geometry`), the trocar / RCM / VIP points,
the master tip, mode changes and events. Entity paths and the layout are described in
:mod:`telesurg.services.mirror.view`; the layout is sent once, when the slave arms are known.

zenoh callbacks only decode and append to a buffer (the continuous streams wait in zenoh's own
buffer until the draw loop polls them, :data:`CONTINUOUS`). The draw loop takes the whole buffer each tick
and draws the 3D scene (latest state, trails thinned to ``trail_hz``) at ``draw_hz``; scalar
samples are sent in blocks (one ``send_columns`` per entity) at ``series_hz``, so a 1 kHz stream
costs a handful of rerun calls a second, never one per sample. While it serves the web viewer
with the ``lean`` layout, what that layout does not show (the master trail, clutch, engaged,
latency, scale, tip / RCM error, camera frames) goes out every 5 s
(:data:`LIVE_OFFVIEW_HZ`), every sample kept, the joint blocks once a second and the trails are
redrawn once a second: the viewer takes in a bounded number of messages (one per entity and
block) per frame it draws, and under software WebGL a large page draws 1–2 frames a second.

Examples::

    telesurg mirror --connect tcp/127.0.0.1:7447 --serve          # then open the URL it logs
    telesurg mirror --connect tcp/127.0.0.1:7447 --save run.rrd   # headless recording
"""

from __future__ import annotations

import ipaddress
import json
import logging
import re
import resource
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np
import numpy.typing as npt
from telesurg.services.common import service_main
from telesurg.services.mirror.geometry import POSE_EPS, RobotGeometry, moved
from telesurg.services.mirror.view import (
    EVENTS_PATH,
    JOINT_COLORS,
    LATENCY,
    LATENCY_QUANTILES,
    LAYOUTS,
    MASTER_COLOR,
    RCM_COLOR,
    SLAVE_COLOR,
    TARGET_COLOR,
    TROCAR_COLOR,
    VIP_COLOR,
    RerunView,
    mapping_path,
    master_path,
    safety_path,
    slave_path,
)
from telesurg.shared import robots
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.clock import wall_ns
from telesurg.shared.errors import ConfigError, KinematicsError
from telesurg.shared.malloc import Trimmer
from telesurg.shared.messages import (
    AnyMessage,
    CameraImage,
    CartesianPose,
    JointSetpoint,
    JointState,
    MasterButtons,
    Message,
    OperatingState,
    SafetyEvent,
    SafetyState,
    TeleopState,
)
from telesurg.shared.robots import ArmProfile, RobotSpec, Sketch
from telesurg.shared.timing import CycleTimer, settle_gc, step_down

log = logging.getLogger(__name__)

#: Most distinct drawn streams (arm × stream); more are ignored so a misbehaving publisher cannot
#: grow the recording without bound.
MAX_STREAMS = 256

#: Keys the mirror subscribes to, relative to ``telesurg/<site>/`` (what it draws; leases,
#: wrenches and heartbeats are not received at all).
SUBSCRIBED = (
    "slave/*/measured_js",
    "slave/*/servo_jp",
    "slave/*/measured_cp",
    "slave/*/setpoint_cp",
    "slave/*/operating_state",
    "master/*/measured_cp",
    "master/*/buttons",
    "safety/*/state",
    "mapping/*/teleop_state",
    "events/*",
)
#: Of those, the state streams whose current value a starting mirror asks for at once.
LATEST = ("mapping/*/teleop_state",)
#: Of those, the continuous streams (100 Hz – 1 kHz): they wait in zenoh's buffer
#: (:data:`~telesurg.shared.bus.POLL_CAPACITY` messages a subscription, the oldest dropped beyond
#: it and counted as lost) until the mirror's loop takes them in (Node.subscribe ``polled``): no
#: thread wake-up and GIL hand-over per message — a quarter less of the mirror's CPU in the demo
#: (docs/performance.md), which the browser drawing the viewer gets instead.
CONTINUOUS = (
    "slave/*/measured_js",
    "slave/*/servo_jp",
    "slave/*/measured_cp",
    "slave/*/setpoint_cp",
    "master/*/measured_cp",
)


#: Hz the joint series are thinned to while the mirror serves the live web viewer (``plot_hz = -1``):
#: 200 points a series in the 20 s plot window
LIVE_PLOT_HZ = 10.0
#: Hz of the 3D scene while serving the live web viewer / when only saving (``draw_hz = -1``)
LIVE_DRAW_HZ = 5.0
FILE_DRAW_HZ = 30.0
#: Hz of the joint series blocks while serving the live web viewer / when only saving
#: (``series_hz = -1``): each block is one message per series for the viewer to take in
LIVE_SERIES_HZ = 1.0
FILE_SERIES_HZ = 4.0
#: Hz the trails (tip, target) are redrawn at while serving the live web viewer (``trail_draw_hz
#: = -1``; when only saving, with every scene): each redraw is the whole trail, one message each
LIVE_TRAIL_DRAW_HZ = 1.0
#: Hz at which the entities the ``lean`` layout does not show (master trail and clutch, engaged,
#: latency, scale, tip / RCM error; camera frames at most this often) are sent while serving the
#: live web viewer: the viewer takes in ~10 messages (one per entity and batch) per frame it
#: draws, and under software WebGL a 1280x720 page draws 1-1.5 frames a second; they stay in the
#: recording, a view away, with every sample, in 5 s blocks
LIVE_OFFVIEW_HZ = 0.2
#: m the drawn RCM point must move before it is sent again
RCM_MOVED_M = 0.2e-3
#: Hz of the mirror's loop (taking in messages, sending due series blocks and frames), at least
LOOP_HZ = 20.0


@dataclass
class MirrorConfig:
    """mirror config."""

    site: str = "local"  # key prefix telesurg/<site>: the site to mirror
    service: str = "mirror"  # instance id (liveliness alive/<service>, heartbeat)
    save: str = ""  # path of an .rrd to write headless ("" = no file); needs save or serve
    serve: bool = False  # serve gRPC (data, 127.0.0.1 only) + the web viewer; open the logged URL
    web_port: int = 9090  # TCP port of the web viewer, HTTP (static viewer files only, no data)
    # address the web viewer listens on (127.0.0.1: this host only; 0.0.0.0 to show it on the LAN —
    # its data still comes from the gRPC port, on 127.0.0.1 only)
    web_host: str = "127.0.0.1"
    grpc_port: int = 9876  # TCP port of the rerun gRPC data server on 127.0.0.1
    # MB of recent data the gRPC server keeps for a viewer that opens later (oldest dropped
    # first; the static robot geometry stays while it fits: at 0.05 MB it did not): a new viewer starts
    # near live instead of replaying the session from its start; 0 = rerun's default (1 GiB)
    history_mb: float = 0.15
    # write rerun's RRD footer (a manifest of every chunk) when the file is closed: rerun keeps
    # that manifest in memory for the whole session (measured: ~340 bytes a chunk; the mirror
    # writes ~49 chunks/s, ~200 MB an hour); without it the file is a valid .rrd that every rerun
    # reader opens (``rerun rrd optimize`` adds a footer afterwards)
    rrd_footer: bool = False
    # The rates below are the live web viewer's budget (docs/performance.md, "a viewer within 1 s
    # of live"): under software WebGL on 2 cores it takes in a few hundred rows a second, and
    # each entity is one message per send; at rerun's defaults and a 30 Hz scene it fell behind
    # live by 0.3-0.8 s every second.
    # s between rerun's batcher sends of the logged rows (3D scene, trails, text) to the viewer and
    # the file: each send is one message per entity; 0 = rerun's default (0.2 s)
    flush_s: float = 0.25
    # Hz: how often the 3D scene is redrawn (robot bodies, trails, points); -1 (the default) =
    # LIVE_DRAW_HZ while serving the web viewer (it draws 2-4 frames a second under software
    # WebGL: faster poses are rows it must take in and never shows), FILE_DRAW_HZ when only saving
    draw_hz: float = -1.0
    # Hz: how often scalar samples are sent, in blocks (a plot lags live by up to 1/series_hz);
    # -1 (the default) = LIVE_SERIES_HZ while serving the web viewer, FILE_SERIES_HZ when saving
    series_hz: float = -1.0
    # Hz: how often the tip / target trails are redrawn (each time the whole trail); -1 (the
    # default) = LIVE_TRAIL_DRAW_HZ while serving the web viewer, with every scene when saving
    trail_draw_hz: float = -1.0
    trail_s: float = 5.0  # s: length of the tip / target / master trails
    trail_hz: float = 10.0  # Hz: trail points are thinned to at most this rate
    error_hz: float = 10.0  # Hz: tip tracking error samples per arm, at most (two FKs each)
    # Hz: joint series (measured, setpoint) are thinned to at most this rate per stream for
    # display (a 1 kHz stream at 10 Hz: a hundredth of the rows for the viewer to take in and
    # plot; the MCAP recorder keeps every sample); 0 = every sample; -1 (the default) =
    # LIVE_PLOT_HZ while serving the web viewer, every sample when only saving an .rrd
    plot_hz: float = -1.0
    plot_window_s: float = 20.0  # s: time series show this much history before the time cursor
    # messages the mirror buffers between its draw passes, at most: while it is starved of CPU (it
    # runs below the control path) the oldest are dropped and counted instead of the buffer
    # growing without bound (~2 s of the local site's streams); the recorder keeps every message
    inbox_max: int = 10_000
    # s between returns of freed memory to the OS (glibc ``malloc_trim``, with a fixed trim
    # threshold; telesurg.shared.malloc): after a burst — the mirror catching up once it gets CPU
    # again, e.g. after a flood — its peak would otherwise stay resident; 0 = never
    malloc_trim_s: float = 30.0
    # Hz: camera frames drawn per camera (the newest, as its JPEG; camera/*/image), 0 = none
    image_hz: float = 2.0
    layout_wait_s: float = 0.5  # s after the first slave arm is seen before the layout is sent
    # draw each slave robot's own bodies from its MuJoCo model (static geoms sent once, one pose
    # per moved body per drawn frame, from mj_kinematics at the measured joints); false: only the
    # registry's sketch (link polyline, forceps)
    geometry: bool = True
    # the viewer's default layout: "lean" — the slave 3D view, the joint plots, the states log
    # (what software WebGL draws within 1 s of live); "full" — also the tip/target and master 3D
    # views and the error, latency and scale plots (every entity is recorded either way)
    layout: str = "lean"
    application_id: str = "telesurg"  # rerun application id (groups recordings in the viewer)
    recording_id: str = ""  # rerun recording id; "" = random; same id merges several processes
    # Only these services' master/, slave/ and safety/ streams are drawn (look-alikes from any
    # other source are counted and dropped); events are drawn from anyone.
    trusted_sources: list[str] = field(
        default_factory=lambda: ["master_capture", "mapping", "slave_control", "watchdog"]
    )
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session

    def effective_draw_hz(self) -> float:
        """``draw_hz``, with -1 resolved: :data:`LIVE_DRAW_HZ` while serving, else :data:`FILE_DRAW_HZ`."""
        if self.draw_hz > 0:
            return self.draw_hz
        return LIVE_DRAW_HZ if self.serve else FILE_DRAW_HZ

    def effective_series_hz(self) -> float:
        """``series_hz``, with -1 resolved: :data:`LIVE_SERIES_HZ` while serving, else
        :data:`FILE_SERIES_HZ`."""
        if self.series_hz > 0:
            return self.series_hz
        return LIVE_SERIES_HZ if self.serve else FILE_SERIES_HZ

    def effective_trail_draw_hz(self) -> float:
        """``trail_draw_hz``, with -1 resolved: :data:`LIVE_TRAIL_DRAW_HZ` while serving, else the
        scene's rate."""
        if self.trail_draw_hz > 0:
            return self.trail_draw_hz
        return LIVE_TRAIL_DRAW_HZ if self.serve else self.effective_draw_hz()

    def effective_plot_hz(self) -> float:
        """``plot_hz``, with -1 resolved: :data:`LIVE_PLOT_HZ` while serving, else 0 (every sample)."""
        if self.plot_hz >= 0:
            return self.plot_hz
        return LIVE_PLOT_HZ if self.serve else 0.0

    def effective_offview_hz(self) -> float:
        """Hz of the entities the layout does not show: :data:`LIVE_OFFVIEW_HZ` while serving the
        ``lean`` layout, else 0 (with the others)."""
        return LIVE_OFFVIEW_HZ if self.serve and self.layout == "lean" else 0.0

    def effective_image_hz(self) -> float:
        """``image_hz``, at most the off-view rate while serving the ``lean`` layout (it shows no
        camera)."""
        offview = self.effective_offview_hz()
        return min(self.image_hz, offview) if offview > 0 else self.image_hz

    def validate(self) -> None:
        """Raise ConfigError naming what is wrong."""
        if not self.save and not self.serve:
            raise ConfigError("mirror needs an output: --set save=FILE.rrd and/or --set serve=true")
        for name, value, lo, hi in (
            ("draw_hz", self.draw_hz, -1.0, 240.0),
            ("series_hz", self.series_hz, -1.0, 240.0),
            ("trail_draw_hz", self.trail_draw_hz, -1.0, 240.0),
            ("trail_s", self.trail_s, 0.1, 600.0),
            ("trail_hz", self.trail_hz, 1.0, 10_000.0),
            ("error_hz", self.error_hz, 1.0, 1000.0),
            ("plot_hz", self.plot_hz, -1.0, 100_000.0),
            ("plot_window_s", self.plot_window_s, 1.0, 3600.0),
            ("layout_wait_s", self.layout_wait_s, 0.0, 60.0),
            ("history_mb", self.history_mb, 0.0, 1_000_000.0),
            ("flush_s", self.flush_s, 0.0, 10.0),
            ("inbox_max", self.inbox_max, 100, 10_000_000),
            ("malloc_trim_s", self.malloc_trim_s, 0.0, 3600.0),
        ):
            if not lo <= value <= hi:
                raise ConfigError(f"{name}={value} outside [{lo:g}, {hi:g}]")
        if self.draw_hz != -1.0 and self.draw_hz < 1.0:
            raise ConfigError(f"draw_hz={self.draw_hz}: -1 (auto) or a rate of at least 1 Hz")
        for name, value in (("series_hz", self.series_hz), ("trail_draw_hz", self.trail_draw_hz)):
            if value != -1.0 and value < 0.5:
                raise ConfigError(f"{name}={value}: -1 (auto) or a rate of at least 0.5 Hz")
        if -1.0 < self.plot_hz < 0.0:
            raise ConfigError(f"plot_hz={self.plot_hz}: 0 (every sample), -1 (auto) or a rate in Hz")
        if self.layout not in LAYOUTS:
            raise ConfigError(f"layout={self.layout!r}: valid: {', '.join(LAYOUTS)}")
        for name, port in (("web_port", self.web_port), ("grpc_port", self.grpc_port)):
            if not 1 <= port <= 65535:
                raise ConfigError(f"{name}={port} outside [1, 65535]")
        if self.serve and self.web_port == self.grpc_port:
            raise ConfigError(f"web_port and grpc_port must differ (both {self.web_port})")
        try:
            ipaddress.ip_address(self.web_host)
        except ValueError:
            raise ConfigError(f"web_host={self.web_host!r}: an IP address (127.0.0.1, 0.0.0.0)") from None


# --------------------------------------------------------------------------- reception


class Inbox:
    """Thread-safe buffer between zenoh callbacks and the draw loop.

    :meth:`on_message` runs on zenoh threads (on the draw loop's, for the :data:`CONTINUOUS`
    streams it polls) for every message that passed the strict decoder and the per-key sequence
    check of :meth:`telesurg.shared.bus.Node.subscribe` (which also counts the rejects); it stamps
    the receive time (for a polled message: the poll's) and appends ``(key, receive_ns, message)``;
    :meth:`take` hands the whole buffer to the draw loop. The buffer holds at most ``max_items``:
    when the draw loop falls behind (a starved mirror), the oldest are dropped and counted in
    :attr:`dropped`, so its memory stays bounded.
    """

    def __init__(self, max_items: int = 10_000) -> None:
        self._lock = threading.Lock()
        self._items: deque[tuple[str, int, AnyMessage]] = deque(maxlen=max_items)
        self.received = 0
        self.dropped = 0

    def on_message(self, msg: Message, key: str) -> None:
        """Node.subscribe callback: buffer the decoded message."""
        rx = wall_ns()
        with self._lock:
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
            self._items.append((key, rx, cast(AnyMessage, msg)))  # decode returns AnyMessage
            self.received += 1

    def take(self) -> list[tuple[str, int, AnyMessage]]:
        """Everything buffered since the last call, in arrival order."""
        with self._lock:
            items = list(self._items)
            self._items.clear()
        return items


# --------------------------------------------------------------------------- arm sketches


def recognise(arm: str, names: tuple[str, ...]) -> tuple[RobotSpec, ArmProfile] | None:
    """(robot, profile) of the registered robot whose arm ``arm`` has exactly these joint names, or None."""
    return robots.recognise(arm, names)


def sketch(robot: RobotSpec, arm: str, q: npt.NDArray[np.float64]) -> Sketch:
    """What the robot's registry entry draws of ``arm`` at joints ``q`` (world frame, m).

    Raises:
        KinematicsError / ValueError: ``q`` does not fit the robot.
    """
    return robot.sketch(arm, q)


def nearest_on_line(
    a: npt.NDArray[np.float64], b: npt.NDArray[np.float64], p: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """The point of the line through ``a`` and ``b`` nearest to ``p`` (all (3,), m)."""
    d = b - a
    n = float(d @ d)
    if n < 1e-18:
        return a.copy()
    out: npt.NDArray[np.float64] = a + (float((p - a) @ d) / n) * d
    return out


#: An arm's profile and its latest measured joints (the geometry's forward kinematics input).
_ArmQ = tuple[ArmProfile, tuple[float, ...]]

#: Measured joints kept for the tip error, ns of source time.
_HISTORY_NS = 1_000_000_000
#: Setpoints waiting for a later measured sample (for the tip error), at most.
_MAX_PENDING = 256

_VIP_TEXT = re.compile(r"\(\s*(-?[\d.]+),\s*(-?[\d.]+),\s*(-?[\d.]+)\s*\)\s*mm")


def parse_vip_mm(text: str) -> tuple[float, float, float] | None:
    """The VIP of a mapping ``vip`` event (``"VIP of arm1 at (1.0, -2.0, 30.5) mm: ..."``), m."""
    m = _VIP_TEXT.search(text)
    if m is None:
        return None
    try:
        x, y, z = (float(g) / 1e3 for g in m.groups())
    except ValueError:
        return None
    return (x, y, z) if all(np.isfinite((x, y, z))) else None


# --------------------------------------------------------------------------- drawing state


#: Hz: a step signal's samples when it does not change (its changes are all kept)
STEP_HZ = 5.0
_STEP_DT_NS = int(1e9 / STEP_HZ)


class _Series:
    """Buffered samples of one stream until the next block is sent."""

    __slots__ = ("last_src", "last_value", "positions", "rx", "src")

    def __init__(self) -> None:
        self.src: list[int] = []
        self.rx: list[int] = []
        self.positions: list[tuple[float, ...]] = []
        self.last_src = -(1 << 62)  # stamp of the last sample kept (for thinning)
        self.last_value: tuple[float, ...] = ()  # value of the last sample kept (step signals)

    def add(self, src: int, rx: int, value: tuple[float, ...]) -> None:
        self.src.append(src)
        self.rx.append(rx)
        self.positions.append(value)

    def take(self) -> tuple[list[int], list[int], npt.NDArray[np.float64]]:
        out = (self.src, self.rx, np.asarray(self.positions, np.float64))
        self.src, self.rx, self.positions = [], [], []
        return out


class _Trail:
    """Recent positions of one point, thinned to ``min_dt_ns`` and cut to ``span_ns``."""

    __slots__ = ("dirty", "min_dt_ns", "points", "rx", "span_ns", "src", "stamps")

    def __init__(self, span_ns: int, min_dt_ns: int) -> None:
        self.span_ns = span_ns
        self.min_dt_ns = min_dt_ns
        self.stamps: deque[int] = deque()
        self.points: deque[tuple[float, float, float]] = deque()
        self.src = 0
        self.rx = 0
        self.dirty = False

    def add(self, src: int, rx: int, p: tuple[float, float, float]) -> None:
        self.src, self.rx, self.dirty = src, rx, True
        if self.stamps and src - self.stamps[-1] < self.min_dt_ns:
            self.points[-1] = p  # keep the newest position as the trail's head
            return
        self.stamps.append(src)
        self.points.append(p)
        while self.stamps and src - self.stamps[0] > self.span_ns:
            self.stamps.popleft()
            self.points.popleft()


class _Arm:
    """What the mirror tracks of one slave arm."""

    def __init__(self, names: tuple[str, ...], robot: tuple[RobotSpec, ArmProfile] | None) -> None:
        self.names = names
        self.robot: RobotSpec | None = robot[0] if robot else None
        self.profile: ArmProfile | None = robot[1] if robot else None
        self.q: tuple[int, int, tuple[float, ...]] | None = None  # latest measured (src, rx, q)
        self.q_drawn = -1
        # measured joints kept for the tip error: (src, q), oldest first
        self.history: deque[tuple[int, tuple[float, ...]]] = deque(maxlen=4096)
        self.pending: list[tuple[int, int, tuple[float, ...]]] = []  # setpoints awaiting a measured
        self.last_error_src = 0
        self.errors = _Series()
        self.rcm_errors = _Series()
        self.op: OperatingState | None = None
        self.rcm_drawn: npt.NDArray[np.float64] | None = None  # the RCM point last sent


class Mirror:
    """Turns decoded bus messages into rerun drawing calls (see :mod:`telesurg.services.mirror.view`).

    :meth:`feed` sorts each batch into buffers; :meth:`draw` (at ``draw_hz``) draws the 3D scene
    and, every ``1/series_hz`` s of receive time, sends the scalar blocks; :meth:`flush` sends
    everything still buffered (the view calls it on close).
    """

    def __init__(
        self,
        view: RerunView,
        prefix: str,
        trail_s: float,
        trail_hz: float,
        *,
        series_hz: float = 5.0,
        draw_hz: float = 0.0,
        error_hz: float = 50.0,
        plot_hz: float = 0.0,
        plot_window_s: float = 20.0,
        layout_wait_s: float = 0.5,
        geometry: bool = True,
        layout: str = "full",
        offview_hz: float = 0.0,
        trail_draw_hz: float = 0.0,
        send_at_once: bool = False,
    ) -> None:
        self.view = view
        # hand each drawn scene to the sinks at once (a live viewer), not at the batcher's next
        # tick (a file: the batcher's fewer, larger chunks)
        self._send_at_once = send_at_once
        self._layout = layout
        self._geometry_on = geometry
        # robot (registry entry) → its MuJoCo geometry, None where it failed to load
        self._geometry: dict[str, RobotGeometry | None] = {}
        # (robot, body with meshes) → its pose last sent; robot → its primitives' poses last sent
        self._body_sent: dict[tuple[str, str], tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]] = {}
        self._prims_sent: dict[str, npt.NDArray[np.float64]] = {}
        self._prefix = prefix.rstrip("/") + "/"
        self._span_ns = int(trail_s * 1e9)
        self._min_dt_ns = int(1e9 / trail_hz)
        self._series_dt_ns = int(1e9 / series_hz)
        self._draw_dt_ns = int(1e9 / draw_hz) if draw_hz > 0 else 0  # 0: each draw() call
        self._drawn_rx = 0
        self._error_dt_ns = int(1e9 / error_hz)
        self._plot_dt_ns = int(1e9 / plot_hz) if plot_hz > 0 else 0
        self._plot_window_s = plot_window_s
        self._layout_wait_ns = int(layout_wait_s * 1e9)
        self._series: dict[tuple[str, str, tuple[str, ...]], _Series] = {}
        self._scalars: dict[str, _Series] = {}  # entity path → samples (clutch, latency, scale)
        self._trails: dict[tuple[str, str, str], _Trail] = {}
        self._arms: dict[str, _Arm] = {}
        self._op_state: dict[str, tuple[str, str, bool, str]] = {}
        self._safety: dict[str, tuple[str, tuple[str, ...]]] = {}
        self._teleop: dict[str, tuple[str, str, float, float]] = {}
        self._streams: set[tuple[str, str]] = set()
        self._now_rx = 0  # latest receive time fed: the clock of the series blocks and the layout
        self._series_sent_rx = 0
        # entities the layout does not show: sent every 1/offview_hz s (0: with the others)
        self._offview_dt_ns = int(1e9 / offview_hz) if offview_hz > 0 else 0
        self._offview_sent_rx = 0
        self._offview_drawn_rx = 0
        # the tip / target trails: redrawn every 1/trail_draw_hz s (0: with each scene)
        self._trail_dt_ns = int(1e9 / trail_draw_hz) if trail_draw_hz > 0 else 0
        self._trails_drawn_rx = 0
        self._first_arm_rx = 0
        self.ignored = 0  # decoded messages that are not drawn (unknown keys, types or streams)
        self.drawn = 0  # joint samples drawn (after plot_hz thinning)
        self._warned: set[str] = set()
        view.add_flusher(self.flush)

    # -- dispatch ------------------------------------------------------------------------
    def feed(self, items: list[tuple[str, int, AnyMessage]]) -> None:
        """Sort one batch of received messages into the per-stream buffers."""
        for key, rx, msg in items:
            self._now_rx = max(self._now_rx, rx)
            if not self._dispatch(key, rx, msg):
                self.ignored += 1

    def _admit(self, arm: str, stream: str) -> bool:
        if (arm, stream) in self._streams:
            return True
        if len(self._streams) >= MAX_STREAMS:
            self._warn_once("streams", f"more than {MAX_STREAMS} streams; ignoring new ones")
            return False
        self._streams.add((arm, stream))
        return True

    def _dispatch(self, key: str, rx: int, msg: AnyMessage) -> bool:
        if not key.startswith(self._prefix):
            return False
        parts = key[len(self._prefix) :].split("/")
        src = msg.header.stamp_ns
        if parts[0] == "events" and isinstance(msg, SafetyEvent):
            self._event(src, rx, msg)
            return True
        if len(parts) != 3:
            return False
        role, arm, stream = parts
        if not self._admit(arm, f"{role}/{stream}"):
            return False
        if role == "slave":
            if stream == "measured_js" and isinstance(msg, JointState):
                self._measured(arm, src, rx, msg)
            elif stream == "servo_jp" and isinstance(msg, JointSetpoint):
                self._setpoint(arm, src, rx, msg)
            elif stream == "measured_cp" and isinstance(msg, CartesianPose):
                self._trail("slave", arm, "tip").add(src, rx, msg.position)
            elif stream == "setpoint_cp" and isinstance(msg, CartesianPose):
                self._trail("slave", arm, "target").add(src, rx, msg.position)
            elif stream == "operating_state" and isinstance(msg, OperatingState):
                self._operating_state(arm, src, rx, msg)
            else:
                return False
        elif role == "master":
            if stream == "measured_cp" and isinstance(msg, CartesianPose):
                self._trail("master", arm, "tip").add(src, rx, msg.position)
            elif stream == "buttons" and isinstance(msg, MasterButtons):
                self._step(master_path(arm, "clutch"), src, rx, 1.0 if msg.clutch else 0.0)
            else:
                return False
        elif role == "safety" and stream == "state" and isinstance(msg, SafetyState):
            self._safety_state(arm, src, rx, msg)
        elif role == "mapping" and stream == "teleop_state" and isinstance(msg, TeleopState):
            self._teleop_state(arm, src, rx, msg)
        else:
            return False
        return True

    def _joint(self, arm: str, kind: str, src: int, rx: int, m: JointState | JointSetpoint) -> None:
        s = self._series.get((arm, kind, m.names))
        if s is None:
            s = self._series[(arm, kind, m.names)] = _Series()
        if self._plot_dt_ns:  # thinned for display: the first sample of each 1/plot_hz
            if 0 <= src - s.last_src < self._plot_dt_ns:
                return
            s.last_src = src
        s.add(src, rx, m.position)
        self.drawn += 1  # buffered samples are all sent, at the latest by flush()

    def _scalar_series(self, path: str) -> _Series:
        s = self._scalars.get(path)
        if s is None:
            s = self._scalars[path] = _Series()
        return s

    def _scalar(self, path: str, src: int, rx: int, *values: float) -> None:
        """One sample of a scalar entity: one value, or one per series of the entity."""
        self._scalar_series(path).add(src, rx, values)

    def _step(self, path: str, src: int, rx: int, value: float) -> None:
        """One sample of a 0/1 step signal (clutch, engaged): every change, and otherwise at most
        :data:`STEP_HZ` samples a second (the buttons come at 50 Hz: rows the viewer would only
        draw on top of each other)."""
        s = self._scalar_series(path)
        if s.last_value == (value,) and 0 <= src - s.last_src < _STEP_DT_NS:
            return
        s.last_src, s.last_value = src, (value,)
        s.add(src, rx, (value,))

    def _arm(self, arm: str, names: tuple[str, ...], rx: int) -> _Arm:
        a = self._arms.get(arm)
        if a is None or a.names != names:
            robot = recognise(arm, names)
            if robot is None:
                self._warn_once(
                    f"model{arm}", f"{arm}: joints {', '.join(names)} match no robot model; arm not drawn"
                )
            a = self._arms[arm] = _Arm(names, robot)
            if not self._first_arm_rx:
                self._first_arm_rx = rx
            elif self.view.blueprint_arms is not None and arm not in self.view.blueprint_arms:
                self._warn_once(f"late{arm}", f"{arm} appeared after the layout was sent: no plot panel")
        return a

    def _measured(self, arm: str, src: int, rx: int, m: JointState) -> None:
        self._joint(arm, "measured", src, rx, m)
        a = self._arm(arm, m.names, rx)
        a.q = (src, rx, m.position)
        if a.profile is not None:
            a.history.append((src, m.position))
            while src - a.history[0][0] > _HISTORY_NS:  # a setpoint older than this gets no error
                a.history.popleft()

    def _setpoint(self, arm: str, src: int, rx: int, m: JointSetpoint) -> None:
        self._joint(arm, "setpoint", src, rx, m)
        a = self._arms.get(arm)
        if a is None or a.profile is None or not m.follow or m.names != a.names:
            return
        if src - a.last_error_src >= self._error_dt_ns:  # thinned: two FKs per error sample
            a.last_error_src = src
            a.pending.append((src, rx, m.position))
            if len(a.pending) > _MAX_PENDING:  # no measured joints arrive: keep the newest only
                del a.pending[0]

    def _trail(self, role: str, arm: str, leaf: str) -> _Trail:
        t = self._trails.get((role, arm, leaf))
        if t is None:
            t = self._trails[(role, arm, leaf)] = _Trail(self._span_ns, self._min_dt_ns)
        return t

    def _operating_state(self, arm: str, src: int, rx: int, m: OperatingState) -> None:
        a = self._arms.get(arm)
        if a is not None:
            if a.op is None or a.op.trocar != m.trocar:
                self.view.point(slave_path(arm, "trocar"), src, rx, m.trocar, TROCAR_COLOR, "trocar")
            a.op = m
            if m.control_mode == "trocar":  # the watchdog checks the RCM error only in trocar mode
                a.rcm_errors.add(src, rx, (m.rcm_error_mm,))
        now = (m.state, m.control_mode, m.follow, m.reason)
        if self._op_state.get(arm) == now:
            return
        self._op_state[arm] = now
        text = f"{m.state} follow={m.follow} mode={m.control_mode}"
        if m.reason:
            text += f" reason: {m.reason}"
        sev = {"FAULT": "error", "PAUSED": "warning", "DISABLED": "warning"}.get(m.state, "info")
        self.view.text(slave_path(arm, "state"), src, rx, text, sev)

    def _safety_state(self, arm: str, src: int, rx: int, m: SafetyState) -> None:
        latency = safety_path(arm, LATENCY)
        if latency not in self._scalars:
            colors = [JOINT_COLORS[k % len(JOINT_COLORS)] for k in range(len(LATENCY_QUANTILES))]
            self.view.series_style(latency, [f"{arm} {q}" for q in LATENCY_QUANTILES], colors, 1.5)
        self._scalar(latency, src, rx, m.latency_p50_ms, m.latency_p90_ms, m.latency_p99_ms)
        self._scalar(safety_path(arm, "scale"), src, rx, m.scale)
        now = (m.state, m.causes)
        if self._safety.get(arm) == now:
            return
        self._safety[arm] = now
        text = m.state + (f": {'; '.join(m.causes)}" if m.causes else "")
        sev = {"OK": "info", "ESTOP": "error"}.get(m.state, "warning")
        self.view.text(safety_path(arm), src, rx, text, sev)

    def _teleop_state(self, arm: str, src: int, rx: int, m: TeleopState) -> None:
        self._step(mapping_path(arm, "engaged"), src, rx, 1.0 if m.state == "ENABLED" else 0.0)
        now = (m.state, m.reason, m.scale, m.safety_scale)
        if self._teleop.get(arm) == now:
            return
        self._teleop[arm] = now
        text = f"{m.state} (was {m.previous}) {m.master} → {m.slave}: {m.reason or '-'}"
        text += f" · scale {m.scale:.3g} × safety {m.safety_scale:.3g} · {m.mode}"
        sev = {"HOLDING": "warning", "DISABLED": "warning"}.get(m.state, "info")
        self.view.text(mapping_path(arm, "teleop"), src, rx, text, sev)

    def _event(self, src: int, rx: int, m: SafetyEvent) -> None:
        text = f"{f'[{m.arm}] ' if m.arm else ''}{m.kind}: {m.text}"
        self.view.text(EVENTS_PATH, src, rx, text, m.severity)
        if m.kind == "vip" and m.arm and self._admit(m.arm, "slave/vip"):
            v = parse_vip_mm(m.text)
            if v is not None:
                self.view.point(slave_path(m.arm, "vip"), src, rx, v, VIP_COLOR, "VIP")

    def _warn_once(self, tag: str, text: str) -> None:
        if tag not in self._warned:
            self._warned.add(tag)
            log.warning("%s", text)

    # -- drawing -------------------------------------------------------------------------
    def draw(self) -> None:
        """Draw the 3D scene (when ``1/draw_hz`` s have passed); send the scalar blocks when
        ``1/series_hz`` s have."""
        first = self._first_arm_rx
        if self.view.blueprint_arms is None and first and self._now_rx - first >= self._layout_wait_ns:
            self._send_layout()
        if self._now_rx - self._drawn_rx >= self._draw_dt_ns:
            self._drawn_rx = self._now_rx
            self._draw_scene()
            if self._send_at_once:
                self.view.send_now()  # up to flush_s sooner to the viewer, the same messages
        if self._now_rx - self._series_sent_rx >= self._series_dt_ns:
            self._series_sent_rx = self._now_rx
            offview = self._now_rx - self._offview_sent_rx >= self._offview_dt_ns
            if offview:
                self._offview_sent_rx = self._now_rx
            self._send_series(offview)

    def _draw_scene(self, everything: bool = False) -> None:
        """The 3D scene: the robots at each call; the trails when ``1/trail_draw_hz`` s have passed
        (the master's, which the lean layout does not show, at most every ``1/offview_hz`` s);
        ``everything``: every trail now (the last frame, at close)."""
        trails = everything or self._now_rx - self._trails_drawn_rx >= self._trail_dt_ns
        offview = trails and (everything or self._now_rx - self._offview_drawn_rx >= self._offview_dt_ns)
        if trails:
            self._trails_drawn_rx = self._now_rx
        if offview:
            self._offview_drawn_rx = self._now_rx
        for (role, arm, leaf), t in self._trails.items():
            if not (offview if role == "master" else trails):
                continue
            if t.dirty:
                t.dirty = False
                pts = np.asarray(t.points, np.float64)
                self.view.trail(_trail_path(role, arm, leaf), t.src, t.rx, pts, _color(role, leaf))
        if self._geometry_on:
            self._draw_geometry()
        for arm, a in self._arms.items():
            self._draw_arm(arm, a)

    def flush(self) -> None:
        """Send everything buffered, and the layout if it has not been sent yet."""
        self._draw_scene(everything=True)
        self._send_series(offview=True)
        if self.view.blueprint_arms is None:
            self._send_layout()

    def _send_layout(self) -> None:
        self.view.send_blueprint(
            {arm: self._arms[arm].names for arm in sorted(self._arms)}, self._plot_window_s, self._layout
        )

    def _draw_geometry(self) -> None:
        """Pose the geometry of each robot with an arm measured since the last frame (one forward
        kinematics per robot and frame): its primitives, and each moved body with meshes."""
        robots_now: dict[str, tuple[RobotSpec, dict[str, _ArmQ], int, int]] = {}
        fresh: set[str] = set()
        for arm, a in self._arms.items():
            if a.q is None or a.profile is None or a.robot is None:
                continue
            src, rx, q = a.q
            spec, arms, src0, rx0 = robots_now.get(a.robot.name, (a.robot, {}, 0, 0))
            arms[arm] = (a.profile, q)
            robots_now[a.robot.name] = (spec, arms, max(src0, src), max(rx0, rx))
            if a.q_drawn != src:
                fresh.add(a.robot.name)
        for key in fresh:
            spec, arms, src, rx = robots_now[key]
            geo = self._robot_geometry(key, spec)
            if geo is None:
                continue
            try:
                prims = geo.primitive_poses(arms)
                poses = geo.pose(arms) if geo.mesh_bodies else {}
            except (ConfigError, ValueError) as exc:
                self._warn_once(f"geo-pose{key}", f"robot {key}: no geometry drawn: {exc}")
                self._geometry[key] = None
                continue
            flat = np.concatenate(
                [np.concatenate([c.ravel(), q.ravel()]) for c, q in prims.values()] or [np.zeros(0)]
            )
            last = self._prims_sent.get(key)
            if (
                last is None
                or last.shape != flat.shape
                or float(np.abs(flat - last).max(initial=0.0)) > POSE_EPS
            ):
                self._prims_sent[key] = flat
                self.view.primitive_poses(key, src, rx, prims)
            for body in geo.mesh_bodies:
                pose = poses[body.name]
                if moved(self._body_sent.get((key, body.name)), pose):
                    self._body_sent[(key, body.name)] = pose
                    self.view.body_pose(key, body.name, src, rx, pose[0], pose[1])

    def _robot_geometry(self, key: str, spec: RobotSpec) -> RobotGeometry | None:
        if key in self._geometry:
            return self._geometry[key]
        geo: RobotGeometry | None = None
        try:
            geo = RobotGeometry.load(spec)
        except Exception as exc:  # a model the mirror cannot read: the sketch still shows the arm
            self._warn_once(f"geo{key}", f"robot {key}: no geometry drawn: {exc}")
        else:
            self.view.robot(key, geo.primitives, geo.mesh_bodies)
            log.info("robot %s: %d bodies drawn from %s", key, len(geo.bodies), spec.scene)
        self._geometry[key] = geo
        return geo

    def _draw_arm(self, arm: str, a: _Arm) -> None:
        if a.q is None or a.profile is None or a.robot is None or a.q_drawn == a.q[0]:
            return
        src, rx, q = a.q
        a.q_drawn = src
        try:
            s = sketch(a.robot, arm, np.asarray(q, np.float64))
        except (KinematicsError, ValueError) as exc:
            self._warn_once(f"fk{arm}", f"{arm}: forward kinematics failed: {exc}")
            return
        if not (self._geometry_on and self._geometry.get(a.robot.name) is not None):
            # the stick figure only where the robot's own bodies are not drawn (geometry off, or
            # its model could not be read): two entities fewer for the viewer to take in
            self.view.arm(arm, src, rx, s.links, s.forceps)
        rcm = s.rcm
        if rcm is None and s.forceps is not None and a.op is not None and a.op.control_mode == "trocar":
            rcm = nearest_on_line(s.forceps[0], s.forceps[-1], np.asarray(a.op.trocar, np.float64))
        if rcm is not None:
            rcm = np.asarray(rcm, np.float64)
            # sent when it moved (it stays at the trocar / VIP within a fraction of a millimetre):
            # not a message a scene for the web viewer to take in
            if a.rcm_drawn is None or float(np.max(np.abs(rcm - a.rcm_drawn))) > RCM_MOVED_M:
                self.view.point(slave_path(arm, "rcm"), src, rx, rcm, RCM_COLOR, "RCM")
                a.rcm_drawn = rcm
        elif a.rcm_drawn is not None:
            self.view.hide_point(slave_path(arm, "rcm"), src, rx)
            a.rcm_drawn = None

    def _send_series(self, offview: bool = True) -> None:
        """Send the buffered joint blocks; ``offview``: also the other scalars (clutch, engaged,
        latency, scale, tip / RCM error), which the ``lean`` layout does not show."""
        for (arm, kind, names), s in self._series.items():
            if s.src:
                src, rx, values = s.take()
                self.view.joints(arm, kind, names, src, rx, values)
        for a in self._arms.values():
            self._tip_errors(a)  # computed as they come (the history they need is bounded)
        if not offview:
            return
        for path, s in self._scalars.items():
            if s.src:
                src, rx, values = s.take()
                self.view.series(path, src, rx, values if values.shape[1] > 1 else values[:, 0])
        for arm, a in self._arms.items():
            for leaf, s in (("tip_error_mm", a.errors), ("rcm_error_mm", a.rcm_errors)):
                if s.src:
                    src, rx, values = s.take()
                    self.view.series(slave_path(arm, leaf), src, rx, values[:, 0])

    def _tip_errors(self, a: _Arm) -> None:
        """|tip(setpoint) − tip(measured)| [mm] at each pending setpoint's stamp, the measured
        joints interpolated there; setpoints newer than the last measured sample wait."""
        if not a.pending or len(a.history) < 2 or a.profile is None:
            return
        t = np.fromiter((h[0] for h in a.history), np.int64, len(a.history))
        last = int(t[-1])
        ready = [p for p in a.pending if t[0] <= p[0] <= last]
        a.pending = [p for p in a.pending if p[0] > last]
        if not ready:
            return
        q = np.asarray([h[1] for h in a.history], np.float64)
        tip = a.profile.tip
        for src, rx, q_set in ready:
            q_meas = np.array([np.interp(src, t, q[:, j]) for j in range(q.shape[1])])
            try:
                err = float(np.linalg.norm(tip(np.asarray(q_set, np.float64)) - tip(q_meas)))
            except (KinematicsError, ValueError):
                continue
            a.errors.add(src, rx, (err * 1e3,))
        keep_from = int(np.searchsorted(t, ready[-1][0], side="right")) - 1
        for _ in range(max(0, keep_from)):
            a.history.popleft()


def _trail_path(role: str, arm: str, leaf: str) -> str:
    return slave_path(arm, leaf) if role == "slave" else master_path(arm, leaf)


def _color(role: str, leaf: str) -> tuple[int, int, int]:
    if role == "master":
        return MASTER_COLOR
    return TARGET_COLOR if leaf == "target" else SLAVE_COLOR


# --------------------------------------------------------------------------- service


class FrameTap:
    """The newest frame of each camera, drawn at most ``hz`` times a second (decimated: the MCAP
    recorder keeps every frame)."""

    def __init__(self, hz: float) -> None:
        self.period = 1.0 / hz if hz > 0 else float("inf")
        self.lock = threading.Lock()
        self.newest: dict[str, tuple[CameraImage, int]] = {}
        self.next_t: dict[str, float] = {}
        self.drawn = 0

    def on_frame(self, msg: CameraImage, key: str) -> None:
        with self.lock:
            self.newest[msg.camera] = (msg, wall_ns())

    def draw(self, view: RerunView) -> None:
        now = time.monotonic()
        with self.lock:
            due = [(cam, fr) for cam, fr in self.newest.items() if now >= self.next_t.get(cam, 0.0)]
            for cam, _ in due:
                del self.newest[cam]
                self.next_t[cam] = now + self.period
        for cam, (msg, rx) in due:
            view.image(cam, msg.capture_ns, rx, msg.data)
            self.drawn += 1


def run(cfg: MirrorConfig, stop: threading.Event) -> None:
    """Mirror the bus into rerun until ``stop``; the .rrd is complete when this returns."""
    cfg.validate()
    draw_hz = cfg.effective_draw_hz()
    timer = CycleTimer(max(draw_hz, LOOP_HZ))
    wall0, cpu0 = time.monotonic(), _cpu_s()
    view = RerunView(
        cfg.application_id,
        cfg.recording_id,
        save=cfg.save,
        serve=cfg.serve,
        web_port=cfg.web_port,
        web_host=cfg.web_host,
        grpc_port=cfg.grpc_port,
        history_mb=cfg.history_mb,
        flush_s=cfg.flush_s,
        rrd_footer=cfg.rrd_footer,
    )
    try:
        if view.url:
            log.info("rerun web viewer: %s", view.url)
        if cfg.save:
            log.info("recording to %s", cfg.save)
        inbox = Inbox(cfg.inbox_max)
        with Node(cfg.bus, cfg.site, cfg.service) as node:
            mirror = Mirror(
                view,
                node.keys.prefix,
                cfg.trail_s,
                cfg.trail_hz,
                series_hz=cfg.effective_series_hz(),
                draw_hz=draw_hz,
                error_hz=cfg.error_hz,
                plot_hz=cfg.effective_plot_hz(),
                plot_window_s=cfg.plot_window_s,
                layout_wait_s=cfg.layout_wait_s,
                geometry=cfg.geometry,
                layout=cfg.layout,
                offview_hz=cfg.effective_offview_hz(),
                trail_draw_hz=cfg.effective_trail_draw_hz(),
                send_at_once=cfg.serve,
            )
            trusted = frozenset(cfg.trusted_sources)

            def trust(key: str, source: str) -> bool:
                role = key.split("/", 3)[2] if key.count("/") >= 3 else ""
                return source in trusted or role not in ("master", "slave", "safety", "mapping")

            for rel in SUBSCRIBED:
                node.subscribe(
                    f"{node.keys.prefix}/{rel}",
                    Message,
                    inbox.on_message,
                    sources=trust,
                    latest=rel in LATEST,
                    polled=rel in CONTINUOUS,
                )
            image_hz = cfg.effective_image_hz()
            frames = FrameTap(image_hz)
            if image_hz > 0:
                node.subscribe(
                    f"{node.keys.prefix}/camera/*/image", CameraImage, frames.on_frame, sources=["camera"]
                )
            draw_errors = 0
            trimmer = Trimmer(cfg.malloc_trim_s)
            step_down()  # set up: below the control path from now on, if the launcher asked
            settle_gc()
            while not stop.is_set():
                try:
                    node.poll()
                    mirror.feed(inbox.take())
                    mirror.draw()
                    frames.draw(view)
                except Exception:  # a drawing bug must not take the mirror down; say so
                    draw_errors += 1
                    if draw_errors <= 5 or draw_errors % 1000 == 0:
                        log.exception("draw failed (%d so far); continuing", draw_errors)
                trimmer.maybe_trim()
                timer.wait()
            node.poll()  # what the continuous streams buffered since the last pass
            rejected = node.rejected
            lost = node.streams.lost
        mirror.feed(inbox.take())  # whatever arrived before the subscriber closed
    finally:
        view.close()  # sends what is still buffered first (Mirror.flush)
    wall, cpu = time.monotonic() - wall0, _cpu_s() - cpu0
    log.info(
        "received %d (%d dropped while the mirror was behind), rejected %d, lost %d (sequence gaps), "
        "drew %d joint samples, "
        "%d draw overruns; %d malloc trims (%.1f ms); "
        "CPU %.2f s in %.1f s (%.3f of a core, rerun's threads included)",
        inbox.received,
        inbox.dropped,
        rejected,
        lost,
        mirror.drawn,
        timer.overruns,
        trimmer.trims,
        trimmer.cpu_s * 1e3,
        cpu,
        wall,
        cpu / wall if wall > 0 else 0.0,
    )


def _cpu_s() -> float:
    """CPU time of this process (every thread), s."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def shortcut_args(argv: Sequence[str]) -> list[str]:
    """``--save FILE`` → ``--set save="FILE"``; ``--serve`` → ``--set serve=true``."""
    out: list[str] = []
    it = iter(argv)
    for a in it:
        if a == "--serve":
            out += ["--set", "serve=true"]
        elif a == "--save" or a.startswith("--save="):
            path = a.partition("=")[2] if "=" in a else next(it, "")
            out += ["--set", f"save={json.dumps(path)}"]
        else:
            out.append(a)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg mirror`` (also accepts ``--save FILE.rrd`` and ``--serve``)."""
    args = shortcut_args(sys.argv[2:] if argv is None else argv)
    return service_main("mirror", MirrorConfig, run, args, __doc__ or "")
