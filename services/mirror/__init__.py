"""mirror: streams everything on the bus to rerun (web viewer on localhost, or an .rrd file).

Subscribes to ``telesurg/<site>/**``, decodes every sample with the strict decoder (malformed
payloads are counted and dropped, never drawn) and draws at ``draw_hz``: joint series, tip and
target trails, the slave arm from forward kinematics, the master tip, state changes and events.
Entity paths and the layout are described in :mod:`services.mirror.view`.

zenoh callbacks only decode and append to a buffer; the draw loop takes the whole buffer each tick
and sends high-rate series in blocks (one ``send_columns`` per entity per tick).

Examples::

    telesurg mirror --connect tcp/127.0.0.1:7447 --serve          # then open the URL it logs
    telesurg mirror --connect tcp/127.0.0.1:7447 --save run.rrd   # headless recording
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from services.common import service_main
from services.mirror.view import (
    EVENTS_PATH,
    MASTER_COLOR,
    SLAVE_COLOR,
    TARGET_COLOR,
    RerunView,
    master_path,
    safety_path,
    slave_path,
)
from shared.bus import BusConfig, Node
from shared.errors import ConfigError, KinematicsError
from shared.kinematics.mh3f import fk_frames
from shared.messages import (
    AnyMessage,
    CartesianPose,
    JointSetpoint,
    JointState,
    MasterButtons,
    Message,
    OperatingState,
    SafetyEvent,
    SafetyState,
)
from shared.timing import CycleTimer

log = logging.getLogger(__name__)

#: Most distinct drawn streams (arm × stream); more are ignored so a misbehaving publisher cannot
#: grow the recording without bound.
MAX_STREAMS = 256


@dataclass
class MirrorConfig:
    """mirror config."""

    site: str = "local"  # key prefix telesurg/<site>: the site to mirror
    service: str = "mirror"  # instance id (liveliness alive/<service>, heartbeat)
    save: str = ""  # path of an .rrd to write headless ("" = no file); needs save or serve
    serve: bool = False  # serve gRPC (data, 127.0.0.1 only) + the web viewer; open the logged URL
    web_port: int = 9090  # TCP port of the web viewer, HTTP (static viewer files only, no data)
    grpc_port: int = 9876  # TCP port of the rerun gRPC data server on 127.0.0.1
    draw_hz: float = 30.0  # Hz: how often buffered samples are sent to rerun (viewer frame rate)
    trail_s: float = 5.0  # s: length of the tip / target / master trails
    trail_hz: float = 50.0  # Hz: trail points are thinned to at most this rate (file size)
    application_id: str = "telesurg"  # rerun application id (groups recordings in the viewer)
    recording_id: str = ""  # rerun recording id; "" = random; same id merges several processes
    # Only these services' master/, slave/ and safety/ streams are drawn (look-alikes from any
    # other source are counted and dropped); events and heartbeats are drawn from anyone.
    trusted_sources: list[str] = field(
        default_factory=lambda: ["master_capture", "mapping", "slave_control", "watchdog"]
    )
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session

    def validate(self) -> None:
        """Raise ConfigError naming what is wrong."""
        if not self.save and not self.serve:
            raise ConfigError("mirror needs an output: --set save=FILE.rrd and/or --set serve=true")
        if not 1.0 <= self.draw_hz <= 240.0:
            raise ConfigError(f"draw_hz={self.draw_hz} outside [1, 240]")
        if not 0.1 <= self.trail_s <= 600.0:
            raise ConfigError(f"trail_s={self.trail_s} outside [0.1, 600]")
        if not 1.0 <= self.trail_hz <= 10_000.0:
            raise ConfigError(f"trail_hz={self.trail_hz} outside [1, 10000]")
        for name, port in (("web_port", self.web_port), ("grpc_port", self.grpc_port)):
            if not 1 <= port <= 65535:
                raise ConfigError(f"{name}={port} outside [1, 65535]")
        if self.serve and self.web_port == self.grpc_port:
            raise ConfigError(f"web_port and grpc_port must differ (both {self.web_port})")


# --------------------------------------------------------------------------- reception


class Inbox:
    """Thread-safe buffer between zenoh callbacks and the draw loop.

    :meth:`on_message` runs on zenoh threads for every message that passed the strict decoder
    and the per-key sequence check of :meth:`shared.bus.Node.subscribe` (which also counts the
    rejects); it stamps the receive time and appends ``(key, receive_ns, message)``;
    :meth:`take` hands the whole buffer to the draw loop.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: list[tuple[str, int, AnyMessage]] = []
        self.received = 0

    def on_message(self, msg: Message, key: str) -> None:
        """Node.subscribe callback: buffer the decoded message."""
        rx = time.time_ns()
        with self._lock:
            self._items.append((key, rx, cast(AnyMessage, msg)))  # decode returns AnyMessage
            self.received += 1

    def take(self) -> list[tuple[str, int, AnyMessage]]:
        """Everything buffered since the last call, in arrival order."""
        with self._lock:
            items, self._items = self._items, []
        return items


# --------------------------------------------------------------------------- drawing state


class _Series:
    """Buffered joint samples of one (arm, kind, names) stream until the next draw."""

    __slots__ = ("positions", "rx", "src")

    def __init__(self) -> None:
        self.src: list[int] = []
        self.rx: list[int] = []
        self.positions: list[tuple[float, ...]] = []


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


class Mirror:
    """Turns decoded bus messages into rerun drawing calls (see :mod:`services.mirror.view`)."""

    def __init__(self, view: RerunView, prefix: str, trail_s: float, trail_hz: float) -> None:
        self.view = view
        self._prefix = prefix.rstrip("/") + "/"
        self._span_ns = int(trail_s * 1e9)
        self._min_dt_ns = int(1e9 / trail_hz)
        self._series: dict[tuple[str, str, tuple[str, ...]], _Series] = {}
        self._trails: dict[tuple[str, str, str], _Trail] = {}
        self._q: dict[str, tuple[int, int, tuple[float, ...]]] = {}  # arm → latest measured
        self._q_drawn: dict[str, int] = {}
        self._clutch: dict[str, _Series] = {}
        self._op_state: dict[str, tuple[str, bool, str]] = {}
        self._safety: dict[str, tuple[str, tuple[str, ...]]] = {}
        self._streams: set[tuple[str, str]] = set()
        self.ignored = 0  # decoded messages that are not drawn (leases, heartbeats, unknown keys)
        self.drawn = 0
        self._warned: set[str] = set()

    # -- dispatch ------------------------------------------------------------------------
    def feed(self, items: list[tuple[str, int, AnyMessage]]) -> None:
        """Sort one batch of received messages into the per-stream buffers."""
        for key, rx, msg in items:
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
                self._joint(arm, "measured", src, rx, msg.names, msg.position)
                self._q[arm] = (src, rx, msg.position)
            elif stream == "servo_jp" and isinstance(msg, JointSetpoint):
                self._joint(arm, "setpoint", src, rx, msg.names, msg.position)
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
                s = self._clutch.setdefault(arm, _Series())
                s.src.append(src)
                s.rx.append(rx)
                s.positions.append((1.0 if msg.clutch else 0.0,))
            else:
                return False
        elif role == "safety" and stream == "state" and isinstance(msg, SafetyState):
            self._safety_state(arm, src, rx, msg)
        else:
            return False
        return True

    def _joint(
        self,
        arm: str,
        kind: str,
        src: int,
        rx: int,
        names: tuple[str, ...],
        position: tuple[float, ...],
    ) -> None:
        s = self._series.get((arm, kind, names))
        if s is None:
            s = self._series[(arm, kind, names)] = _Series()
        s.src.append(src)
        s.rx.append(rx)
        s.positions.append(position)

    def _trail(self, role: str, arm: str, leaf: str) -> _Trail:
        t = self._trails.get((role, arm, leaf))
        if t is None:
            t = self._trails[(role, arm, leaf)] = _Trail(self._span_ns, self._min_dt_ns)
        return t

    def _operating_state(self, arm: str, src: int, rx: int, m: OperatingState) -> None:
        now = (m.state, m.follow, m.reason)
        if self._op_state.get(arm) == now:
            return
        self._op_state[arm] = now
        text = f"{m.state} follow={m.follow} mode={m.control_mode}"
        if m.reason:
            text += f" reason: {m.reason}"
        sev = {"FAULT": "error", "PAUSED": "warning", "DISABLED": "warning"}.get(m.state, "info")
        self.view.text(slave_path(arm, "state"), src, rx, text, sev)

    def _safety_state(self, arm: str, src: int, rx: int, m: SafetyState) -> None:
        base = safety_path(arm).rsplit("/", 1)[0]
        figures = {
            "latency/p50_ms": m.latency_p50_ms,
            "latency/p90_ms": m.latency_p90_ms,
            "latency/p99_ms": m.latency_p99_ms,
            "scale": m.scale,
        }
        for name, value in figures.items():  # ~5 Hz: one row each is cheap
            self.view.series(f"{base}/{name}", [src], [rx], np.array([value]))
        now = (m.state, m.causes)
        if self._safety.get(arm) == now:
            return
        self._safety[arm] = now
        text = m.state + (f": {'; '.join(m.causes)}" if m.causes else "")
        sev = {"OK": "info", "ESTOP": "error"}.get(m.state, "warning")
        self.view.text(safety_path(arm), src, rx, text, sev)

    def _event(self, src: int, rx: int, m: SafetyEvent) -> None:
        text = f"{f'[{m.arm}] ' if m.arm else ''}{m.kind}: {m.text}"
        self.view.text(EVENTS_PATH, src, rx, text, m.severity)

    def _warn_once(self, tag: str, text: str) -> None:
        if tag not in self._warned:
            self._warned.add(tag)
            log.warning("%s", text)

    # -- drawing -------------------------------------------------------------------------
    def draw(self) -> None:
        """Send everything buffered since the last draw; call at draw_hz and once at the end."""
        for (arm, kind, names), s in self._series.items():
            if not s.src:
                continue
            self.view.joints(arm, kind, names, s.src, s.rx, np.asarray(s.positions, np.float64))
            self.drawn += len(s.src)
            s.src, s.rx, s.positions = [], [], []
        for arm, s in self._clutch.items():
            if s.src:
                values = np.asarray(s.positions, np.float64)[:, 0]
                self.view.series(master_path(arm, "clutch"), s.src, s.rx, values)
                s.src, s.rx, s.positions = [], [], []
        for (role, arm, leaf), t in self._trails.items():
            if t.dirty:
                t.dirty = False
                pts = np.asarray(t.points, np.float64)
                self.view.trail(_trail_path(role, arm, leaf), t.src, t.rx, pts, _color(role, leaf))
        for arm, (src, rx, q) in self._q.items():
            if self._q_drawn.get(arm) == src:
                continue
            self._q_drawn[arm] = src
            if len(q) != 6:
                self._warn_once(f"q{arm}", f"{arm}: {len(q)} joints, cannot draw a 6-axis arm")
                continue
            try:
                frames = fk_frames(np.asarray(q, np.float64))
            except (KinematicsError, ValueError) as exc:
                self._warn_once(f"fk{arm}", f"{arm}: forward kinematics failed: {exc}")
                continue
            self.view.links(arm, src, rx, frames)


def _trail_path(role: str, arm: str, leaf: str) -> str:
    return slave_path(arm, leaf) if role == "slave" else master_path(arm, leaf)


def _color(role: str, leaf: str) -> tuple[int, int, int]:
    if role == "master":
        return MASTER_COLOR
    return TARGET_COLOR if leaf == "target" else SLAVE_COLOR


# --------------------------------------------------------------------------- service


def run(cfg: MirrorConfig, stop: threading.Event) -> None:
    """Mirror the bus into rerun until ``stop``; the .rrd is complete when this returns."""
    cfg.validate()
    timer = CycleTimer(cfg.draw_hz)
    view = RerunView(
        cfg.application_id,
        cfg.recording_id,
        save=cfg.save,
        serve=cfg.serve,
        web_port=cfg.web_port,
        grpc_port=cfg.grpc_port,
    )
    try:
        if view.url:
            log.info("rerun web viewer: %s", view.url)
        if cfg.save:
            log.info("recording to %s", cfg.save)
        inbox = Inbox()
        with Node(cfg.bus, cfg.site, cfg.service) as node:
            mirror = Mirror(view, node.keys.prefix, cfg.trail_s, cfg.trail_hz)
            trusted = frozenset(cfg.trusted_sources)

            def trust(key: str, source: str) -> bool:
                role = key.split("/", 3)[2] if key.count("/") >= 3 else ""
                return source in trusted or role not in ("master", "slave", "safety")

            node.subscribe(node.keys.all, Message, inbox.on_message, sources=trust)
            draw_errors = 0
            while not stop.is_set():
                try:
                    mirror.feed(inbox.take())
                    mirror.draw()
                except Exception:  # a drawing bug must not take the mirror down; say so
                    draw_errors += 1
                    if draw_errors <= 5 or draw_errors % 1000 == 0:
                        log.exception("draw failed (%d so far); continuing", draw_errors)
                timer.wait()
            rejected = node.rejected
        mirror.feed(inbox.take())  # whatever arrived before the subscriber closed
        mirror.draw()
        log.info(
            "received %d, rejected %d, drew %d joint samples, %d draw overruns",
            inbox.received,
            rejected,
            mirror.drawn,
            timer.overruns,
        )
    finally:
        view.close()


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
