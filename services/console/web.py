"""``telesurg console --web``: the web surgeon console, served by this process (aiohttp).

One page (``/``; its script and style under ``/static/``, nothing from the internet) shows per
arm the teleop state, the operating state and control mode, the safety state with its causes,
the command latency p50/p99, the operator's motion scale and the watchdog's factor (labelled
apart), the joints with limit bars, the tip position (and the commanded tip, the "ghost", in the
arm view), the RCM error in trocar mode; its controls are a large e-stop (a reset asks for
confirmation), the clutch (a held key — Space, what USB foot pedals type — or the on-screen
pedal), scale up / down, the operator commands and record start / stop.

The page is also the master device: mouse and keyboard, a phone or tablet (device orientation +
touch drag), or a gamepad (the browser's Gamepad API). It sends its samples over the websocket
``/ws``; this process checks each frame (:mod:`telesurg.services.console.browser`) and publishes
``master/<m>/measured_cp`` and ``master/<m>/buttons`` at ``web.rate_hz`` (and at once on each new
sample) from a second node whose service id is ``web.master_service`` (``master_capture``: the
mapping and the watchdog accept master streams from that id only), each pose stamped with the
browser's own time of the sample mapped onto this host's clock. A browser that goes quiet —
tab hidden, socket closed, no sample for ``web.sample_timeout_ms`` — makes its samples invalid at
once: nothing is published and the watchdog holds; after a reconnect the clutch counts only
after it was seen released (a fresh press). Commands and e-stops go out through the same
:class:`~telesurg.services.console.model.ConsoleModel` as the terminal console, with its
identity (``service``, ``console``).

Everything is served only to a logged-in browser (:mod:`telesurg.shared.door`): the
one-time login URL printed at start (or handed over by the launcher, :data:`LOGIN_ENV`) is swapped
for a session cookie; ``Host`` and ``Origin`` are checked; one page controls the master, the others
view until control is handed over (:mod:`telesurg.services.console.control`).

Examples::

    telesurg console --web --connect tcp/127.0.0.1:7447            # prints its login URL
    telesurg console --web --port 8080 --set web.host=0.0.0.0 \
        --set 'web.allowed_hosts=["192.168.1.20"]'                 # a phone on the LAN
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import importlib.resources
import json
import logging
import math
import os
import re
import secrets
import signal
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.services.common import install_stop_handlers, watch_parent
from telesurg.services.console.browser import (
    VIEWER_FRAMES,
    BrowserMaster,
    ClockMap,
    FrameError,
    SocketGuard,
    parse_sample,
)
from telesurg.services.console.control import Control
from telesurg.services.console.model import ConsoleConfig, ConsoleModel
from telesurg.shared import mjpeg, robots
from telesurg.shared.bus import POLL_CAPACITY, Node, Outlet, Resend, only
from telesurg.shared.clock import wall_ns
from telesurg.shared.door import LOGIN_ENV, Door
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import (
    CameraImage,
    CartesianPose,
    CartesianWrench,
    JointState,
    MasterButtons,
    VideoFeedback,
)
from telesurg.shared.teleop.camera_frame import project
from telesurg.shared.timing import CycleTimer, start_loop
from telesurg.shared.video import StreamGate, is_keyframe, pack

log = logging.getLogger(__name__)


#: messages per polled stream checked for one state: a full buffer (what waited while no page
#: was open) in one go, and still a bound when a starved process cannot keep up with its streams
POLL_LIMIT = POLL_CAPACITY


def static_dir() -> Path:
    """The page's files (``services/console/static``)."""
    root = importlib.resources.files("telesurg.services.console") / "static"
    if not isinstance(root, Path):
        raise ConfigError(f"the web console's files are not on the file system ({root})")
    return root


def _r(v: float, nd: int = 3) -> float | None:
    return round(v, nd) if math.isfinite(v) else None


@dataclass
class ArmView:
    """What the page shows of an arm beyond the console model: joints, tip, commanded tip."""

    js: JointState | None = None
    js_rx: float = 0.0
    tip: CartesianPose | None = None
    setpoint: CartesianPose | None = None
    setpoint_rx: float = 0.0
    cf: CartesianWrench | None = None  # the tissue's force on the instrument (measured_cf)
    cf_rx: float = -math.inf  # monotonic s: when the newest measured_cf arrived


class PictureLag:
    """How long after a motion the picture shows it, on average: the wait for the camera's next
    capture (half a frame period) plus the frame's age when it reaches this console (capture,
    render, encode, the bus), each a running mean of the last frames (EWMA). The stream to the page
    adds its own milliseconds (the MJPEG part written on arrival, the browser's decode)."""

    ALPHA = 0.1

    def __init__(self) -> None:
        self.arrival_ms: float | None = None
        self.period_ms: float | None = None
        self.capture_ns: int | None = None  # the previous frame's

    def add(self, capture_ns: int, rx_ns: int) -> None:
        def ewma(old: float | None, x: float) -> float:
            return x if old is None else old + self.ALPHA * (x - old)

        self.arrival_ms = ewma(self.arrival_ms, (rx_ns - capture_ns) / 1e6)
        if self.capture_ns is not None and 0 < capture_ns - self.capture_ns < 2_000_000_000:
            self.period_ms = ewma(self.period_ms, (capture_ns - self.capture_ns) / 1e6)
        self.capture_ns = capture_ns

    def behind_ms(self) -> float:
        return (self.arrival_ms or 0.0) + (self.period_ms or 0.0) / 2


class Counters:
    """Totals over every connection (shown on the page, served on ``/api/stats``)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.rejected: dict[str, int] = {}
        self.accepted = 0
        self.closed_abusive = 0
        self.connections = 0
        self.busy = 0

    def as_dict(self) -> dict[str, Any]:
        with self.lock:
            return {
                "accepted": self.accepted,
                "rejected": dict(self.rejected),
                "rejected_total": sum(self.rejected.values()),
                "closed_abusive": self.closed_abusive,
                "connections": self.connections,
                "busy": self.busy,
            }


@dataclass
class _Tally:
    """One camera's H.264 arrivals since its last report."""

    t0: float
    frames: int = 0
    lost: int = 0
    bytes: int = 0
    ages: list[float] = dataclasses.field(default_factory=list)


class H264Relay:
    """The cameras' H.264 streams to the pages (``/video.h264``) and the pages' reports back to the
    cameras (:class:`~telesurg.shared.messages.VideoFeedback` on ``camera/<cam>/video_feedback``).

    Each open stream has a queue of packets (:func:`telesurg.shared.video.pack`); a stream starts at
    a keyframe, and one that falls behind (a slow page) or sees a frame missing drops what it holds
    and waits for the next keyframe, which is asked for at once: a decoder is never fed a frame whose
    reference it did not get."""

    REPORT_S = 0.5  # s: a camera's report period (while its frames arrive)
    BACKLOG = 8  # packets a stream may hold before it is reset to the next keyframe

    def __init__(self, node: Node) -> None:
        self.node = node
        self.lock = threading.Lock()
        self.streams: dict[str, set[Callable[[bytes, bool, bool], None]]] = {}  # camera → page streams
        self.last_seq: dict[str, int] = {}
        self.stats: dict[str, _Tally] = {}
        self.outs: dict[str, Outlet] = {}  # camera → its feedback outlet
        self.out_lock = threading.Lock()

    def _put(self, cam: str, frames: int, lost: int, kbps: float, age_ms: float, keyframe: bool) -> None:
        """One report to ``cam``: from a zenoh thread (:meth:`add`) or the pages' event loop
        (:meth:`ask_keyframe`), so one outlet per camera and one put at a time (its sequence)."""
        with self.out_lock:
            out = self.outs.get(cam)
            if out is None:
                out = self.outs[cam] = self.node.outlet(
                    self.node.keys.camera(cam, "video_feedback"), control=False
                )
            out.put(VideoFeedback(out.header(), cam, frames, lost, kbps, age_ms, keyframe))

    def add(self, m: CameraImage, rx_ns: int, offset_ns: int) -> None:
        """One access unit arrived (a zenoh thread)."""
        cam = m.camera
        key = is_keyframe(m.data)
        capture_ns = m.capture_ns + offset_ns
        with self.lock:
            prev = self.last_seq.get(cam)
            self.last_seq[cam] = m.header.seq
            lost = max(0, m.header.seq - prev - 1) if prev is not None else 0
            st = self.stats.setdefault(cam, _Tally(time.monotonic()))
            st.frames += 1
            st.lost += lost
            st.bytes += len(m.data)
            st.ages.append((rx_ns - capture_ns) / 1e6)
            sinks = list(self.streams.get(cam, ()))
        packet = pack(m.data, key, capture_ns / 1e6, m.header.seq, m.width, m.height)
        for sink in sinks:
            sink(packet, key, lost > 0)
        self._report(cam, keyframe=bool(lost and sinks))

    def _report(self, cam: str, keyframe: bool = False) -> None:
        now = time.monotonic()
        with self.lock:
            st = self.stats.get(cam)
            if st is None or not (keyframe or now - st.t0 >= self.REPORT_S):
                return
            self.stats[cam] = _Tally(now)
        kbps = st.bytes * 8 / max(now - st.t0, 1e-3) / 1e3
        age = max(0.0, float(np.median(st.ages))) if st.ages else 0.0
        self._put(cam, st.frames, st.lost, round(kbps, 1), age, keyframe)

    def ask_keyframe(self, cam: str) -> None:
        """A page joined or fell behind: the camera's next frame is a keyframe."""
        self._put(cam, 0, 0, 0.0, 0.0, True)

    def attach(self, cam: str, sink: Callable[[bytes, bool, bool], None]) -> None:
        with self.lock:
            self.streams.setdefault(cam, set()).add(sink)

    def detach(self, cam: str, sink: Callable[[bytes, bool, bool], None]) -> None:
        with self.lock:
            self.streams.get(cam, set()).discard(sink)


class WebConsole:
    """The bus side of the web console: the console model, the arm views and the browser masters."""

    def __init__(self, cfg: ConsoleConfig, node: Node, master_node: Node | None) -> None:
        self.cfg, self.web = cfg, cfg.web
        self.model = ConsoleModel(cfg, node)
        self.node, self.master_node = node, master_node
        self.views = {a: ArmView() for a in self.model.arms}
        self.lock = threading.Lock()  # views, masters
        self._poll_lock = threading.Lock()
        browser = self.model.masters if master_node is not None else []
        self.masters = {m: BrowserMaster(m, self.web.sample_timeout_ms / 1e3) for m in browser}
        self.counters = Counters()
        self.published = dict.fromkeys(self.masters, 0)
        k = node.keys
        s_src = only(cfg.slave_source)
        for arm in self.model.arms:
            # (polled: 250 Hz and 100 Hz streams only drawn at state_hz; no thread wake-up per
            # message in the process that also relays the browser's samples, none at all while
            # no page is open)
            node.subscribe(k.slave(arm, "measured_js"), JointState, self._on_js, sources=s_src, polled=True)
            node.subscribe(
                k.slave(arm, "measured_cp"), CartesianPose, self._on_cp, sources=s_src, polled=True
            )
            m_src = only(cfg.mapping_source)
            node.subscribe(
                k.slave(arm, "setpoint_cp"), CartesianPose, self._on_setpoint, sources=m_src, polled=True
            )
            # the tip force (500 Hz on the MH3F) for the page's force overlay and gamepad rumble:
            # only its newest few are checked at each state (20 Hz), not all 500 a second
            node.subscribe(
                k.slave(arm, "measured_cf"), CartesianWrench, self._on_cf, sources=s_src, polled=True, keep=4
            )
        # the endoscope picture (camera service, docs/console.md): the newest frame of each camera,
        # served to the page as an MJPEG stream (/video.mjpg); nothing is queued behind it
        self.frames: dict[str, tuple[CameraImage, int]] = {}  # camera → (frame, receive time ns)
        self.picture_lag: dict[str, PictureLag] = {}
        self.frame_waiters: set[Callable[[], None]] = set()  # called on each new frame
        if self.web.video == "h264":  # (only what the page shows crosses the link)
            self.h264 = H264Relay(node)
            node.subscribe(f"{k.prefix}/camera/*/video", CameraImage, self._on_video, sources=only("camera"))
        else:
            node.subscribe(f"{k.prefix}/camera/*/image", CameraImage, self._on_frame, sources=only("camera"))
        # the cameras' optical-frame poses (latest: the current one at once), for the overlay
        self.cam_poses: dict[str, CartesianPose] = {}
        node.subscribe(
            f"{k.prefix}/camera/*/measured_cp",
            CartesianPose,
            self._on_cam_pose,
            sources=only("camera"),
            latest=True,
        )
        mk = node.keys
        out = master_node.outlet if master_node is not None else None
        self._pose_out = {m: out(mk.master(m, "measured_cp"), datagram=True) for m in self.masters if out}
        self._buttons_out = {m: out(mk.master(m, "buttons"), datagram=True) for m in self.masters if out}
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._recorder: Any = None
        self._thread = threading.Thread(target=self._publish_loop, daemon=True, name="web-master")
        self._thread.start()

    # -- slave streams (zenoh threads) -------------------------------------------------------
    def _on_js(self, m: JointState, key: str) -> None:
        with self.lock:
            v = self.views[key.rsplit("/", 2)[-2]]
            v.js, v.js_rx = m, time.monotonic()

    def _on_cp(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            self.views[key.rsplit("/", 2)[-2]].tip = m

    def _on_setpoint(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            v = self.views[key.rsplit("/", 2)[-2]]
            v.setpoint, v.setpoint_rx = m, time.monotonic()

    def _on_cf(self, m: CartesianWrench, key: str) -> None:
        rx = self.node.received(key)  # (polled: the earliest it can have come)
        with self.lock:
            v = self.views[key.rsplit("/", 2)[-2]]
            v.cf, v.cf_rx = m, rx

    def _force(self, v: ArmView, now: float) -> dict[str, Any] | None:
        """The tip force for the page's overlay and rumble: the vector (N, in ``frame``), its
        magnitude, the tissue limit it is drawn against, its age and whether it is stale."""
        if v.cf is None:
            return None
        f = v.cf.force
        age_ms = (now - v.cf_rx) * 1e3
        return {
            "n": [_r(x) for x in f],
            "mag": _r(math.sqrt(sum(x * x for x in f))),
            "frame": v.cf.frame,
            "limit_n": self.web.force_limit_n,
            "age_ms": round(age_ms, 1),
            "stale": age_ms > self.web.force_stale_ms,
        }

    def _on_frame(self, m: CameraImage, key: str) -> None:
        rx = wall_ns()
        with self.lock:
            self.frames[m.camera] = (m, rx)
            self.picture_lag.setdefault(m.camera, PictureLag()).add(m.capture_ns, rx)
            wake = list(self.frame_waiters)
        for w in wake:  # the MJPEG streams waiting for a new frame (their event loop's callbacks)
            w()

    def _on_video(self, m: CameraImage, key: str) -> None:
        if m.encoding != "h264":
            return
        rx = wall_ns()
        self.h264.add(m, rx, self.clock_offset_ns())
        self._on_frame(m, key)

    def clock_offset_ns(self) -> int:
        """This host's clock minus the slave site's (the watchdog's estimate, the first arm that
        has one; 0 while unknown): a slave-site time + this is on this host's clock."""
        for a in self.model.arms.values():
            if a.safety is not None and a.safety.clock_offset_ms:
                return int(a.safety.clock_offset_ms * 1e6)
        return 0

    def _on_cam_pose(self, m: CartesianPose, key: str) -> None:
        if m.frame == "base":
            with self.lock:
                self.cam_poses[key.rsplit("/", 2)[-2]] = m

    def overlay(self) -> dict[str, Any]:
        """The predictive overlay, per camera: each arm's commanded tip (the mapping's
        ``setpoint_cp``, out before the slave moves and long before a picture can show it) in
        pixels of the camera's image, one point per eye (None: not in front of the camera), and
        ``behind_ms``: how far the picture lags what the overlay shows (:class:`PictureLag`)."""
        with self._poll_lock:  # (the setpoints arrive polled)
            self.node.poll(limit=POLL_LIMIT)
        now = time.monotonic()
        with self.lock:
            frames, poses = dict(self.frames), dict(self.cam_poses)
            lags = {cam: self.picture_lag[cam].behind_ms() for cam in frames}
            cmds = {a: (v.setpoint, v.setpoint_rx) for a, v in self.views.items()}
        out: dict[str, Any] = {}
        for cam, (img, _rx) in frames.items():
            pose = poses.get(cam)
            intr = (img.fx, img.fy, img.cx, img.cy)
            arms: dict[str, Any] = {}
            for arm, (sp, rx) in cmds.items():
                if pose is None or sp is None or sp.frame != "base":
                    continue
                eyes = [project(sp.position, pose, *intr)]
                if img.layout == "stereo_sbs":  # the right eye, in the image's right half
                    r = project(sp.position, pose, *intr, baseline_m=img.baseline_m)
                    eyes.append(None if r is None else (r[0] + img.width / 2, r[1]))
                arms[arm] = {
                    "px": [None if e is None else [round(e[0], 1), round(e[1], 1)] for e in eyes],
                    "age_ms": round((now - rx) * 1e3, 1),
                }
            out[cam] = {
                "width": img.width,
                "height": img.height,
                "behind_ms": round(lags[cam], 1),
                "arms": arms,
            }
        return out

    def latest_frame(self, camera: str = "") -> CameraImage | None:
        """The newest frame of ``camera`` ("" = the first camera seen), None if none yet."""
        with self.lock:
            if not self.frames:
                return None
            got = self.frames.get(camera or next(iter(self.frames)))
        return got[0] if got is not None else None

    def _video_state(self) -> dict[str, Any]:
        """Per camera: image size, frame age at arrival and now (ms), sequence, layout."""
        now = wall_ns()
        with self.lock:
            frames = dict(self.frames)
        return {
            cam: {
                "width": m.width,
                "height": m.height,
                "layout": m.layout,
                "encoding": m.encoding,
                "seq": m.header.seq,
                "age_at_arrival_ms": round((rx - m.capture_ns) / 1e6, 1),
                "age_ms": round((now - m.capture_ns) / 1e6, 1),
                "dropped": m.dropped,
            }
            for cam, (m, rx) in frames.items()
        }

    # -- browser masters ---------------------------------------------------------------------
    def feed(self, conn: object, obj: dict[str, Any], clock: ClockMap) -> str:
        """An admitted ``sample`` frame; "" when taken, else why it was not (FrameError if invalid)."""
        received = wall_ns()
        s = parse_sample(obj, tuple(self.masters))
        stamp = clock.stamp_ns(s.t_ms, received)
        now = time.monotonic()
        with self.lock:
            bm = self.masters[s.master]
            if bm.owner is not None and bm.owner is not conn and now - bm.rx <= bm.timeout_s:
                return f"master {s.master} is driven by another page"
            bm.feed(conn, s, stamp, now)
        self._wake.set()
        return ""

    def release(self, conn: object, master: str | None = None) -> None:
        """``conn`` closed or its tab was hidden: its masters' samples are invalid at once."""
        with self.lock:
            for m, bm in self.masters.items():
                if master in (None, m):
                    bm.detach(conn)

    def _publish_loop(self) -> None:
        start_loop(self.web.rt_priority)
        timer = CycleTimer(self.web.rate_hz)
        resend = {m: Resend(round(self.web.rate_hz / self.web.buttons_hz)) for m in self.masters}
        while not self._stop.is_set():
            now = time.monotonic()
            with self.lock:
                pubs = {m: bm.current(now) for m, bm in self.masters.items()}
            for m, p in pubs.items():
                if p is None:
                    resend[m].reset()  # buttons go out first when samples resume
                    continue
                buttons = (p.clutch, p.present)
                bo, po = self._buttons_out[m], self._pose_out[m]
                if resend[m].due(buttons):
                    bo.put(MasterButtons(bo.header(), *buttons))
                h = dataclasses.replace(po.header(), stamp_ns=p.stamp_ns)
                po.put(CartesianPose(h, "master", p.position, p.orientation))
                self.published[m] += 1
            # the next cycle, or at once when a new browser sample arrives; with no page
            # driving a master (each already invalidated) nothing is due until one does: no
            # 200 Hz wake-ups for nothing on a host that shares its CPU with the control path
            idle = all(p is None for p in pubs.values())
            self._wake.wait(None if idle else max(0.0, timer.period_s - (time.monotonic() - now)))
            self._wake.clear()

    # -- what the page shows -----------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Everything the page draws, as JSON-ready data."""
        with self._poll_lock:  # (the polled slave streams: one thread at a time)
            # (bounded: on a CPU-starved host whose streams — measured_cf at 500 Hz — come
            # faster than they are checked, the state still goes out)
            self.node.poll(limit=POLL_LIMIT)
        arms, clutch, alive = self.model.snapshot()
        now = time.monotonic()
        stale = self.cfg.stale_s
        out: list[dict[str, Any]] = []
        with self.lock:
            views = {a: dataclasses.replace(v) for a, v in self.views.items()}
            masters = {
                m: {
                    "connected": bm.owner is not None,
                    "valid": bm.current(now) is not None,
                    "clutch": bool(bm.sample and bm.sample.clutch and bm.released_seen),
                    "clutch_raw": bool(bm.sample and bm.sample.clutch),
                    "device": bm.sample.device if bm.sample else "",
                    "invalidations": bm.invalidations,
                    "published": self.published[m],
                }
                for m, bm in self.masters.items()
            }
        for a in arms:
            v = views[a.arm]
            d: dict[str, Any] = {"arm": a.arm, "master": a.master}
            tp = a.teleop
            d["teleop"] = (
                None
                if tp is None
                else {
                    "state": tp.state,
                    "previous": tp.previous,
                    "reason": tp.reason,
                    "since_s": round(max(0.0, time.time() - tp.since_ns / 1e9), 1),
                    "scale": tp.scale,
                    "safety_scale": tp.safety_scale,
                    "mode": tp.mode,
                    "stale": now - a.teleop_rx > stale,
                }
            )
            op = a.op
            d["op"] = (
                None
                if op is None
                else {
                    "state": op.state,
                    "control_mode": op.control_mode,
                    "follow": op.follow,
                    "lease_ok": op.lease_ok,
                    "reason": op.reason,
                    "rcm_error_mm": _r(op.rcm_error_mm),
                    "stale": now - a.op_rx > stale,
                }
            )
            s = a.safety
            d["safety"] = (
                None
                if s is None
                else {
                    "state": s.state,
                    "causes": list(s.causes),
                    "scale": s.scale,
                    "p50_ms": _r(s.latency_p50_ms, 1),
                    "p99_ms": _r(s.latency_p99_ms, 1),
                    "samples": s.latency_samples,
                    "clock_offset_ms": _r(s.clock_offset_ms, 1),
                    "stale": now - a.safety_rx > stale,
                }
            )
            d["joints"] = self._joints(a.arm, v)
            d["tip_mm"] = [round(x * 1e3, 2) for x in v.tip.position] if v.tip else None
            d["ghost_mm"] = (
                [round(x * 1e3, 2) for x in v.setpoint.position]
                if v.setpoint and now - v.setpoint_rx < 0.5
                else None
            )
            d["sketch"] = self._sketch(a.arm, v)
            d["force"] = self._force(v, now)
            d["events"] = [
                {"t": round(t, 3), "src": src, "kind": kind, "text": text}
                for t, src, kind, text in list(a.events)[-self.cfg.events_per_arm :]
            ]
            d["reply"] = a.last_reply
            d["console_clutch"] = clutch.get(a.master, False)
            out.append(d)
        return {
            "type": "state",
            "site": self.cfg.site,
            "time": time.time(),
            "arms": out,
            "masters": masters,
            "alive": sorted(alive),
            "socket": self.counters.as_dict(),
            "recording": self._recorder is not None and self._recorder.poll() is None,
            "mouse_mm_per_px": self.web.mouse_mm_per_px,
            "video": self._video_state(),
            "confirm": (
                None
                if (p := self.model.pending_confirm) is None
                else {"arm": p.arm, "command": p.line, "question": p.question}
            ),
            "trial": self._trial(now),
        }

    def _trial(self, now: float) -> dict[str, Any] | None:
        """The study's current trial as the operator may see it (None: no study, or its last state
        is older than 10 s — the study ended or stopped)."""
        with self.model.lock:
            got = self.model.trial
        if got is None or now - got[1] > 10.0:
            return None
        m, rx = got
        # (the clock runs on between the study's 4 Hz states while the trial runs)
        elapsed = m.elapsed_s + (now - rx if m.phase == "running" else 0.0)
        return {
            "trial": m.trial,
            "trials": m.trials,
            "task": m.task,
            "instructions": m.instructions,
            "condition": m.condition,
            "practice": m.practice,
            "phase": m.phase,
            "elapsed_s": round(elapsed, 1),
            "time_limit_s": m.time_limit_s,
            "goals_reached": m.goals_reached,
            "goals": m.goals,
            "result": m.result,
            "goals_mm": [
                [round(v * 1e3, 2) for v in m.goal_points[i : i + 3]]
                for i in range(0, len(m.goal_points) - 2, 3)
            ],
        }

    @staticmethod
    def _joints(arm: str, v: ArmView) -> list[dict[str, Any]]:
        if v.js is None:
            return []
        found = robots.recognise(arm, v.js.names)
        out = []
        for i, (name, q) in enumerate(zip(v.js.names, v.js.position, strict=True)):
            row: dict[str, Any] = {"name": name, "pos": _r(q, 4)}
            if found is not None:
                row["lo"], row["hi"] = found[1].lower[i], found[1].upper[i]
            out.append(row)
        return out

    @staticmethod
    def _sketch(arm: str, v: ArmView) -> dict[str, Any] | None:
        if v.js is None:
            return None
        found = robots.recognise(arm, v.js.names)
        if found is None:
            return None
        sk = found[0].sketch(arm, np.asarray(v.js.position, dtype=np.float64))

        def mm(a: Any) -> list[list[float]] | None:
            return None if a is None else np.round(np.atleast_2d(a) * 1e3, 1).tolist()

        return {"links": mm(sk.links), "forceps": mm(sk.forceps), "rcm": mm(sk.rcm)}

    # -- record ------------------------------------------------------------------------------
    def record(self, action: str) -> str:
        """Start or stop ``telesurg record`` for this site (a child process); a line for the log."""
        import subprocess
        import sys

        if action == "start":
            if self._recorder is not None and self._recorder.poll() is None:
                return "already recording"
            folder = Path(self.web.record_dir)
            folder.mkdir(parents=True, exist_ok=True)
            out = folder / time.strftime("console-%Y%m%d-%H%M%S.mcap")
            argv = [sys.executable, "-m", "telesurg.services.cli", "record", "--out", str(out)]
            argv += ["--site", self.cfg.site]
            for ep in self.cfg.bus.connect:
                argv += ["--connect", ep]
            self._recorder = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            return f"recording to {out}"
        if action == "stop":
            rec, self._recorder = self._recorder, None
            if rec is None or rec.poll() is not None:
                return "not recording"
            rec.send_signal(signal.SIGINT)
            try:
                rec.wait(10)
            except subprocess.TimeoutExpired:
                rec.kill()
            return "recording stopped"
        raise FrameError("invalid", f"record action {action!r}; valid: start, stop")

    def close(self) -> None:
        """Stop publishing, stop a recording, close the model."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)
        if self._recorder is not None:
            self.record("stop")
        self.model.close()


# --------------------------------------------------------------------------- the web server


class Server:
    """The aiohttp application: ``/login``, the page, static files, ``/api/state``, ``/api/stats``,
    ``/video.mjpg`` and ``/ws`` — every one behind the :class:`~telesurg.shared.door.Door`
    (Host, Origin, the session cookie) and the websocket's frames behind the
    :class:`~telesurg.services.console.control.Control` (one controlling page)."""

    def __init__(self, wc: WebConsole, door: Door) -> None:
        from aiohttp import web

        self.wc, self.door = wc, door
        self.sockets: weakref.WeakSet[Any] = weakref.WeakSet()
        self.pages: dict[Any, str] = {}  # open socket → its page
        self.page_sid: dict[str, str] = {}  # page → its session id
        self.ctl = Control(grace_s=wc.web.control_grace_s, alive=self._page_alive)
        self._told: dict[str, int] = {}  # refusal kind → events published

        @web.middleware
        async def guard(request: Any, handler: Any) -> Any:
            return await self._guard(request, handler)

        self.app = web.Application(middlewares=[guard])
        self.app.router.add_get("/login", self._login)
        self.app.router.add_get("/", self._index)
        self.app.router.add_get("/api/state", self._api_state)
        self.app.router.add_get("/api/stats", self._api_stats)
        self.app.router.add_get("/ws", self._ws)
        self.app.router.add_get("/video.mjpg", self._video)
        self.app.router.add_get("/video.h264", self._video_h264)
        self.app.router.add_static("/static/", static_dir())

    # -- the door ------------------------------------------------------------------------------
    def _page_alive(self, page: str) -> bool:
        return self.door.alive(self.page_sid.get(page, ""))

    @staticmethod
    def _is_ws(request: Any) -> bool:
        return str(request.headers.get("Upgrade", "")).lower() == "websocket"

    async def _guard(self, request: Any, handler: Any) -> Any:
        """Every request: Host, Origin and the session (:meth:`Door.admit`); a refusal is one line
        (a refused websocket is accepted only to be closed at once with the reason)."""
        from aiohttp import web

        ws = self._is_ws(request)
        v = self.door.admit(request.method, request.path, request.headers, request.cookies, ws)
        if v.ok:
            request["session"] = v.session
            return await handler(request)
        self.refused(v.kind, v.reason, request.remote)
        if ws:
            sock = web.WebSocketResponse()
            await sock.prepare(request)
            await sock.close(code=4400 + (v.status % 100), message=v.reason.encode()[:120])
            return sock
        return web.Response(status=v.status, text=v.reason + "\n", headers={"Cache-Control": "no-store"})

    def refused(self, kind: str, reason: str, peer: str | None) -> None:
        """Log a refusal and publish it as a ``web_refused`` event (the first five of each kind,
        then every 100th: a flood of refusals does not flood the bus)."""
        n = self._told.get(kind, 0) + 1
        self._told[kind] = n
        if n <= 5 or n % 100 == 0:
            total = self.door.counts().get(kind, n)
            text = f"{reason} (from {peer}; {kind} refusals: {total})"
            self.wc.node.event("web_refused", text, severity="warning")

    async def _login(self, request: Any) -> Any:
        """``/login?token=T``: a one-time token for a session cookie, then the page (303)."""
        from aiohttp import web

        got = self.door.login(request.query.get("token", ""))
        if got is None:
            reason = "refused: this login link is not valid (already used, expired or mistyped)"
            self.refused("login", reason, request.remote)
            return web.Response(status=401, text=reason + "\n", headers={"Cache-Control": "no-store"})
        value, s = got
        self.wc.node.event("web_login", f"session {s.label} logged in from {request.remote}")
        return web.Response(
            status=303,
            headers={
                "Location": "/",
                "Set-Cookie": self.door.cookie_header(value),
                "Cache-Control": "no-store",
                "Referrer-Policy": "no-referrer",
            },
        )

    # -- what is served --------------------------------------------------------------------------
    async def _index(self, request: Any) -> Any:
        from aiohttp import web

        return web.FileResponse(static_dir() / "index.html")

    async def state(self) -> dict[str, Any]:
        """The console's state with the door's and the control's. The console's part (which polls
        the slave streams and checks their signatures) is made on a worker thread: the event loop
        keeps relaying the browser's master samples meanwhile."""
        st = await asyncio.to_thread(self.wc.state)
        holder, request = self.ctl.snapshot()
        st["control"] = {"holder": holder, "request": request}
        st["door"] = {"refused": self.door.counts()}
        return st

    async def _api_state(self, request: Any) -> Any:
        from aiohttp import web

        return web.json_response(await self.state())

    async def _api_stats(self, request: Any) -> Any:
        from aiohttp import web

        return web.json_response({**self.wc.counters.as_dict(), "door": self.door.counts()})

    async def _video(self, request: Any) -> Any:
        """The endoscope picture as an MJPEG stream (``?camera=ID``; default: the first camera):
        each new frame once, as the camera encoded it; a slow page skips frames, never queues."""
        from aiohttp import web

        camera = request.query.get("camera", "")
        resp = web.StreamResponse(
            headers={
                "Content-Type": mjpeg.CONTENT_TYPE,
                "Cache-Control": "no-store",
            }
        )
        await resp.prepare(request)
        last = -1
        with contextlib.suppress(ConnectionError, asyncio.CancelledError):
            await resp.write(mjpeg.START)
            loop, new = asyncio.get_running_loop(), asyncio.Event()

            def wake() -> None:  # (a zenoh thread: the frame's arrival)
                loop.call_soon_threadsafe(new.set)

            with self.wc.lock:
                self.wc.frame_waiters.add(wake)
            try:
                while True:
                    m = self.wc.latest_frame(camera)
                    if m is not None and m.header.seq != last and m.encoding == "jpeg":
                        last = m.header.seq
                        await resp.write(mjpeg.part(m.data))  # (shown on arrival: shared/mjpeg.py)
                    with contextlib.suppress(TimeoutError):  # (the timeout: a stream with no frames)
                        await asyncio.wait_for(new.wait(), 1.0)
                    new.clear()
            finally:
                with self.wc.lock:
                    self.wc.frame_waiters.discard(wake)
        return resp

    async def _video_h264(self, request: Any) -> Any:
        """The endoscope picture as H.264 access units (``?camera=ID``; the page reads them with
        ``fetch`` and decodes them with WebCodecs), each framed by :func:`telesurg.shared.video.pack`;
        from a keyframe on, and again from the next keyframe after a frame missed or a backlog."""
        from aiohttp import web

        relay = getattr(self.wc, "h264", None)
        camera = request.query.get("camera", "")
        if relay is None:
            raise web.HTTPNotFound(text="this console serves MJPEG (/video.mjpg); H.264: web.video = 'h264'")
        if not camera:
            frame = self.wc.latest_frame()
            if frame is None:
                raise web.HTTPServiceUnavailable(text="no camera publishes H.264 yet")
            camera = frame.camera
        resp = web.StreamResponse(
            headers={"Content-Type": "application/octet-stream", "Cache-Control": "no-store"}
        )
        await resp.prepare(request)
        loop, new = asyncio.get_running_loop(), asyncio.Event()
        gate = StreamGate(H264Relay.BACKLOG)

        def on_packet(packet: bytes, key: bool, gap: bool) -> None:  # (a zenoh thread)
            loop.call_soon_threadsafe(take, packet, key, gap)

        def take(packet: bytes, key: bool, gap: bool) -> None:
            if gate.offer(packet, key, gap):
                relay.ask_keyframe(camera)
            new.set()

        relay.attach(camera, on_packet)
        relay.ask_keyframe(camera)
        try:
            with contextlib.suppress(ConnectionError, asyncio.CancelledError):
                while True:
                    while gate.queue:
                        await resp.write(gate.queue.popleft())
                    await new.wait()
                    new.clear()
        finally:
            relay.detach(camera, on_packet)
        return resp

    # -- control ---------------------------------------------------------------------------------
    def _role(self, page: str) -> dict[str, Any]:
        holder, request = self.ctl.snapshot()
        return {
            "type": "control",
            "page": page,
            "role": "controller" if holder == page else "viewer",
            "holder": holder,
            "request": request,
        }

    async def tell_roles(self) -> None:
        """Tell every page its role now (after any change of control)."""
        for ws, page in list(self.pages.items()):
            if not ws.closed:
                with contextlib.suppress(Exception):
                    await ws.send_json(self._role(page))

    def _control_event(self, text: str) -> None:
        if text:
            self.wc.node.event("web_control", text)

    def _handover(self, before: str | None) -> None:
        """Control moved away from ``before``: its samples are invalid at once (the watchdog
        holds until the new controller presses the clutch afresh)."""
        holder, _ = self.ctl.snapshot()
        if before is not None and holder != before:
            for conn_ws, page in list(self.pages.items()):
                if page == before:
                    self.wc.release(conn_ws)

    async def _ws(self, request: Any) -> Any:
        from aiohttp import WSCloseCode, WSMsgType, web

        w = self.wc.web
        sid = str(request["session"])
        asked = request.query.get("page", "")
        pid = asked if re.fullmatch(r"[A-Za-z0-9]{4,32}", asked) else secrets.token_hex(4)
        page = f"{sid[:6]}-{pid}"
        # aiohttp's own cap (a larger frame closes the socket, code 1009); below it, SocketGuard
        # refuses frames over max_frame_bytes and counts them
        ws = web.WebSocketResponse(max_msg_size=16 * w.max_frame_bytes, heartbeat=5.0)
        await ws.prepare(request)
        guard = SocketGuard(rate_hz=w.max_frames_hz, max_rejects=w.max_rejects, max_bytes=w.max_frame_bytes)
        clock = ClockMap()
        with self.wc.counters.lock:
            self.wc.counters.connections += 1
        self.sockets.add(ws)
        self.page_sid[page] = sid
        self.pages[ws] = page
        self._control_event(self.ctl.join(page))
        peer = request.remote
        log.info("page %s connected from %s", page, peer)
        await ws.send_json(await self.state())
        await self.tell_roles()
        told: dict[str, int] = {}
        try:
            async for msg in ws:
                if msg.type == WSMsgType.ERROR:
                    self._count("oversized" if "size" in str(ws.exception()) else "protocol")
                    break
                if not self.door.alive(sid):
                    self._count("expired")
                    await ws.close(code=4401, message=b"session expired: log in again")
                    break
                text: str | bytes = msg.data if msg.type == WSMsgType.TEXT else bytes(msg.data)
                before = self.ctl.snapshot()
                try:
                    reply = self._handle(ws, page, guard.admit(text), clock)  # admit counts its refusals
                except FrameError as exc:
                    if exc.admitted and exc.kind != "viewer":  # a bad field, after admission
                        guard.reject(exc.kind)
                    self._count(exc.kind)
                    if guard.abusive:
                        with self.wc.counters.lock:
                            self.wc.counters.closed_abusive += 1
                        log.warning("closing the connection from %s: %d refused frames", peer, guard.rejected)
                        self.wc.release(ws)
                        await ws.close(code=WSCloseCode.POLICY_VIOLATION, message=b"too many refused frames")
                        break
                    told[exc.kind] = told.get(exc.kind, 0) + 1
                    if told[exc.kind] <= 3:  # tell the page, without echoing a flood
                        await ws.send_json({"type": "refused", "kind": exc.kind, "text": str(exc)})
                    continue
                with self.wc.counters.lock:
                    self.wc.counters.accepted += 1
                if isinstance(reply, dict):
                    await ws.send_json(reply)
                elif reply:
                    await ws.send_json({"type": "notice", "text": reply})
                if self.ctl.snapshot() != before:  # control moved, or was asked for
                    self._handover(before[0])
                    await self.tell_roles()
        finally:
            self.wc.release(ws)
            self.pages.pop(ws, None)
            self._control_event(self.ctl.leave(page))
            log.info("page %s from %s gone (%d frames refused)", page, peer, guard.rejected)
            with contextlib.suppress(Exception):
                await self.tell_roles()
        return ws

    def _count(self, kind: str) -> None:
        """Count a refused frame (shown on the page, served on ``/api/stats``)."""
        with self.wc.counters.lock:
            self.wc.counters.rejected[kind] = self.wc.counters.rejected.get(kind, 0) + 1

    def _handle(self, conn: object, page: str, obj: dict[str, Any], clock: ClockMap) -> str | dict[str, Any]:
        """One admitted frame; the text (or message) to tell the page, if any (FrameError marked
        admitted)."""
        try:
            if obj["type"] not in VIEWER_FRAMES and not self.ctl.is_controller(page):
                raise FrameError("viewer", f"this page is a viewer: {obj['type']} needs control (ask for it)")
            if obj["type"] == "control":
                return self._control(page, obj["action"])
            if obj["type"] == "invite":
                token = self.door.mint(self.wc.web.invite_s)
                self.wc.node.event("web_invite", f"page {page} made a login link for another page")
                return {"type": "invite", "url": f"/login?token={token}", "valid_s": self.wc.web.invite_s}
            return self._handle_frame(conn, obj, clock)
        except FrameError as exc:
            exc.admitted = True
            raise

    def _control(self, page: str, action: Any) -> str:
        """A ``control`` frame: take | release | grant | refuse (services/console/control.py)."""
        if action == "take":
            granted, text = self.ctl.take(page)
            self._control_event(text)
            return "" if granted else "asked the controlling page for control"
        if action == "release":
            text = self.ctl.release(page)
            self._control_event(text)
            return "control released" if text else "this page is not in control"
        if action in ("grant", "refuse"):
            text = self.ctl.answer(page, action == "grant")
            self._control_event(text)
            return "" if text else "no request to answer"
        raise FrameError("invalid", f"control action {action!r}; valid: take, release, grant, refuse")

    def _handle_frame(self, conn: object, obj: dict[str, Any], clock: ClockMap) -> str:
        kind = obj["type"]
        model = self.wc.model
        if kind == "sample":
            busy = self.wc.feed(conn, obj, clock)
            if busy:
                with self.wc.counters.lock:
                    self.wc.counters.busy += 1
            return ""
        if kind == "hidden":
            master = obj.get("master")
            self.wc.release(conn, master if isinstance(master, str) else None)
            return ""
        if kind == "ping":
            return ""
        if kind == "confirm":  # the operator answers the question the page shows (state.confirm)
            if not isinstance(obj["yes"], bool):
                raise FrameError("invalid", "confirm needs yes: true or false")
            if model.pending_confirm is None:
                return "nothing to confirm"
            model.confirm(obj["yes"])
            return ""
        arm = obj.get("arm", "*")
        if not isinstance(arm, str) or (arm != "*" and arm not in model.arms):
            raise FrameError("invalid", f"arm {arm!r}; valid: *, {', '.join(model.arms)}")
        if kind == "estop":
            model.estop(arm, "estop", "web console: operator")
            return ""
        if kind == "reset":
            if obj.get("confirm") is not True:
                raise FrameError("invalid", "a reset needs confirm: true")
            model.estop(arm, "reset", "web console: operator")
            return ""
        if kind == "command":
            name, args, target = obj["name"], obj.get("args", []), obj.get("target", "slave")
            if arm == "*" or not isinstance(name, str) or target not in ("slave", "mapping"):
                raise FrameError("invalid", "command needs one arm, a name and target slave or mapping")
            if not isinstance(args, list) or not all(isinstance(x, str) for x in args) or len(args) > 16:
                raise FrameError("invalid", "command args must be a list of key=value strings")
            model.command(arm, name, args, target=target)
            return ""
        if kind == "record":
            action = obj["action"]
            return self.wc.record(action if isinstance(action, str) else "")
        raise FrameError("unknown", f"unknown frame type {kind!r}")

    async def broadcast_overlay(self, stop: asyncio.Event) -> None:
        """Push the predictive overlay to every page at ``overlay_hz`` while a camera publishes."""
        hz = self.wc.web.overlay_hz
        while hz > 0 and not stop.is_set():
            if self.sockets and self.wc.frames:
                ov = await asyncio.to_thread(self.wc.overlay)
                data = json.dumps({"type": "overlay", "cams": ov})
                for ws in list(self.sockets):
                    page = self.pages.get(ws)
                    if not ws.closed and (page is None or self._page_alive(page)):
                        with contextlib.suppress(Exception):
                            await ws.send_str(data)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), 1.0 / hz)

    async def broadcast(self, stop: asyncio.Event) -> None:
        """Push the state (and new notices) to every page at ``state_hz``."""
        period = 1.0 / self.wc.web.state_hz
        while not stop.is_set():
            notices = self.wc.model.drain()
            if self.sockets:
                state = await self.state()
                state["notices"] = [
                    {"t": n.stamp, "severity": n.severity, "text": n.text, "toast": n.toast} for n in notices
                ]
                data = json.dumps(state)
                for ws in list(self.sockets):
                    page = self.pages.get(ws)
                    if page is not None and not ws.closed and not self._page_alive(page):
                        self._count("expired")  # a page that sends nothing learns it too
                        with contextlib.suppress(Exception):
                            await ws.close(code=4401, message=b"session expired: log in again")
                        continue
                    if not ws.closed:
                        with contextlib.suppress(Exception):
                            await ws.send_str(data)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), period)


async def serve(wc: WebConsole, stop: asyncio.Event, token: str = "") -> None:
    """Serve the page until ``stop``. ``token``: the one-time login token the launcher made and
    printed; without one, a token is made here and the login URL printed (stdout only, never the
    log)."""
    from aiohttp import web

    w = wc.web
    door = Door(w.host, w.port, session_s=w.session_s, allowed_hosts=tuple(w.allowed_hosts))
    server = Server(wc, door)
    runner = web.AppRunner(server.app, handle_signals=False, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, w.host, w.port)
    await site.start()
    with contextlib.suppress(Exception):
        door.port = runner.addresses[0][1]
    log.info("web console on http://%s:%d/ (log in with the login URL)", w.host, door.port)
    if token:
        door.add_token(token)
        print(f"web console: http://{w.host}:{door.port}/ (login URL: from the launcher)", flush=True)
    else:
        print(f"web console: {door.login_url(door.mint())}", flush=True)
    task = asyncio.create_task(server.broadcast(stop))
    overlay = asyncio.create_task(server.broadcast_overlay(stop))
    try:
        await stop.wait()
    finally:
        for ws in list(server.sockets):
            with contextlib.suppress(Exception):
                await ws.close()
        await task
        await overlay
        await runner.cleanup()


def run_web(cfg: ConsoleConfig, parent_pid: int = 0) -> None:
    """Open the console's node and the master node, serve until SIGINT / SIGTERM (or, with
    ``parent_pid``, until that launcher is gone)."""
    cfg.web.validate()
    token = os.environ.pop(LOGIN_ENV, "")
    gone = threading.Event()  # SIGINT / SIGTERM (from now on: no KeyboardInterrupt mid-start-up)
    install_stop_handlers(gone)
    if parent_pid:
        watch_parent(parent_pid, gone)
    with contextlib.ExitStack() as stack:
        node = stack.enter_context(Node(cfg.bus, cfg.site, cfg.service))
        ms = cfg.web.master_service
        mnode = stack.enter_context(Node(cfg.bus, cfg.site, ms)) if ms else None
        wc = WebConsole(cfg, node, mnode)
        try:

            async def main() -> None:
                stop = asyncio.Event()
                loop = asyncio.get_running_loop()
                threading.Thread(
                    target=lambda: (gone.wait(), loop.call_soon_threadsafe(stop.set)), daemon=True
                ).start()
                await serve(wc, stop, token)

            asyncio.run(main())
        finally:
            wc.close()
