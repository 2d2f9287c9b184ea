"""replay: plays a recording's master streams into a live pipeline and compares the slave's response.

By default the master streams (``master/*/measured_cp``, ``master/*/measured_js``,
``master/*/buttons``) are republished with their original timing (scaled by ``--speed``) under
fresh headers — source ``master_capture`` (``--as``), new sequence numbers, new stamps, the body
unchanged — from a node that is on the bus as ``master_capture`` (liveliness, heartbeat), so the
mapping and the watchdog take it for the real master. Run it against a pipeline without
master_capture. Meanwhile the live ``slave/<arm>/measured_js`` is recorded; at the end the replay
reports, per joint, the RMS and largest difference between the slave response in the file and the
live one, aligned on the time since the first replayed message (header stamps on both sides), as a
table and with ``--json FILE``.

The comparison is meaningful when the recording starts before the first engage (the slave at
home, as in a fresh pipeline): the mapping is incremental, so a slave that was elsewhere when the
recording began follows the same motion from another pose.

Pre-flight and verdict (a replay that means nothing says so and exits non-zero):

* before anything is published, the replay looks at who is alive on the site: a live
  ``master_capture`` (or whatever service ``--as`` names) would fight the replayed streams, so
  the replay refuses, naming it (exit 2);
* a recording whose first ``buttons`` message has the clutch pedal already held would never
  engage (the mapping engages on a press, not on a held pedal): the replay first sends a
  release (``clutch = false``) for ``--release-s`` (0.3 s) and says so, so that the recorded
  held pedal arrives as a press;
* an arm that followed in the recording but never follows in the replay exits 4; a joint RMS
  difference over ``--max-rms`` (default 0.02 rad) exits 3 (``--max-rms 0`` turns it off).

``--to-rerun OUT.rrd`` converts a recording to a rerun file instead, without any network: the
mirror's entity paths (``/slave/<arm>/...``, ``/master/<arm>/...``, ``/safety/...``, ``/events``)
and its two timelines, ``source_time`` (header stamp) and ``receive_time`` (log time).

Examples (a pipeline without master_capture: docs/console.md, "Replay")::

    telesurg replay run.mcap --connect tcp/127.0.0.1:7447 --json diff.json
    telesurg replay run.mcap --step --keys 'master/*/buttons' --connect tcp/127.0.0.1:7447
    telesurg replay run.mcap --to-rerun run.rrd && rerun run.rrd
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import fnmatch
import logging
import queue
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.exceptions import McapError
from telesurg.services.common import install_stop_handlers, setup_logging
from telesurg.services.record import Recorder, iter_decoded, open_mcap, recording_site, written_whole
from telesurg.shared import jsonio
from telesurg.shared.bus import BusConfig, Node, Outlet, add_bus_args, bus_from_args, open_session
from telesurg.shared.errors import ConfigError, TelesurgError
from telesurg.shared.keys import Keys, check_id
from telesurg.shared.messages import (
    CameraImage,
    JointState,
    MasterButtons,
    Message,
    OperatingState,
    SafetyState,
)

log = logging.getLogger(__name__)

#: Streams replayed by default (relative to ``telesurg/<site>/``).
MASTER_GLOBS = ("master/*/measured_cp", "master/*/measured_js", "master/*/buttons")
RESPONSE_GLOB = "slave/*/measured_js"
#: What is recorded of each arm's run: joints, follow state, the watchdog's motion scale.
RESPONSE_KEYS = (RESPONSE_GLOB, "slave/*/operating_state", "safety/*/state")


@dataclass
class ReplayConfig:
    """replay config (from the command line)."""

    file: str = ""  # the .mcap to play
    site: str = ""  # site to publish on ("" = the site the file was recorded on)
    service: str = "master_capture"  # replay node id = header source of replayed messages
    keys: list[str] = field(default_factory=lambda: list(MASTER_GLOBS))  # globs, relative keys
    speed: float = 1.0  # playback speed factor (2 = twice as fast)
    step: bool = False  # wait for Enter before each message (no timing)
    lead_in_s: float = 0.5  # s: on the bus before the first message (subscriptions settle)
    settle_s: float = 1.0  # s: keep recording the slave after the last message
    slave_source: str = "slave_control"  # only this service's slave response is compared
    watchdog_source: str = "watchdog"  # only this service's safety state counts
    record: str = ""  # also record the whole live bus during the replay to this .mcap ("" = no)
    release_s: float = 0.3  # s: a synthesized pedal release before a recording that starts held
    preflight: bool = True  # refuse a site where the replay's own service (--as) is already alive
    max_late_ms: float = 50.0  # ms: later than this for 0.1 s behind the recording's timing = not comparable
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session

    def validate(self) -> None:
        """Raise ConfigError naming what is wrong."""
        if not Path(self.file).is_file():
            raise ConfigError(f"{self.file}: no such file")
        if self.site:
            check_id("site", self.site)
        check_id("service", self.service)
        if not 0.01 <= self.speed <= 100.0:
            raise ConfigError(f"--speed {self.speed} outside [0.01, 100]")
        if not self.keys:
            raise ConfigError("--keys needs at least one glob")
        if not 0.0 <= self.lead_in_s <= 60.0 or not 0.0 <= self.settle_s <= 60.0:
            raise ConfigError("--lead-in and --settle must be within [0, 60] s")
        if not 0.0 <= self.release_s <= 10.0:
            raise ConfigError(f"--release-s {self.release_s} outside [0, 10]")
        if not 1.0 <= self.max_late_ms <= 10_000.0:
            raise ConfigError(f"--max-late-ms {self.max_late_ms} outside [1, 10000]")
        self.bus.validate()


# --------------------------------------------------------------------------- response


@dataclass
class Response:
    """One arm's run as seen on the bus; times are s since the first replayed master message.

    ``t``/``q``: slave measured_js (rad). ``follow``: changes of the slave's follow state and
    reason (operating_state). ``scale``: changes of the watchdog's motion-scale factor or state
    (with the causes at the change).
    """

    names: tuple[str, ...] = ()
    t: list[float] = field(default_factory=list)
    q: list[tuple[float, ...]] = field(default_factory=list)
    follow: list[tuple[float, bool, str]] = field(default_factory=list)
    scale: list[tuple[float, float, str]] = field(default_factory=list)

    def add(self, t: float, msg: Message) -> None:
        """Account one message of this arm (other types are ignored)."""
        if isinstance(msg, JointState):
            if not self.names:
                self.names = msg.names
            if msg.names == self.names:
                self.t.append(t)
                self.q.append(msg.position)
        elif isinstance(msg, OperatingState):
            if not self.follow or self.follow[-1][1:] != (msg.follow, msg.reason):
                self.follow.append((t, msg.follow, msg.reason))
        elif isinstance(msg, SafetyState):
            why = msg.state + (f": {'; '.join(msg.causes)}" if msg.causes else "")
            # a new entry when the scale or the state changes (not for every new latency figure)
            if not self.scale or (self.scale[-1][1], self.scale[-1][2].split(":")[0]) != (
                msg.scale,
                msg.state,
            ):
                self.scale.append((t, msg.scale, why))

    @property
    def follow_s(self) -> float | None:
        """First time (>= 0) the slave reported following, s; None if never."""
        return next((round(t, 3) for t, f, _ in self.follow if f and t >= 0), None)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(t (N,), q (N, J)) sorted by time."""
        t = np.asarray(self.t, dtype=float)
        q = np.asarray(self.q, dtype=float).reshape(len(self.t), len(self.names))
        order = np.argsort(t, kind="stable")
        return t[order], q[order]

    def conditions(self, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """(follow (bool), scale, reason) at each grid time (before any report: False, 1, "")."""
        f_t = np.array([c[0] for c in self.follow])
        s_t = np.array([c[0] for c in self.scale])
        fi = np.searchsorted(f_t, grid, side="right") - 1 if f_t.size else np.full(grid.shape, -1)
        si = np.searchsorted(s_t, grid, side="right") - 1 if s_t.size else np.full(grid.shape, -1)
        follow = np.array([self.follow[i][1] if i >= 0 else False for i in fi], dtype=bool)
        scale = np.array([self.scale[i][1] if i >= 0 else 1.0 for i in si])
        why = [
            (self.follow[i][2] if i >= 0 else "") + (f" [{self.scale[j][2]}]" if j >= 0 else "")
            for i, j in zip(fi, si, strict=True)
        ]
        return follow, scale, why


def _diff(recorded: Response, live: Response, hi: float) -> dict[str, Any]:
    """RMS / max |live − recorded| per joint for recorded samples in [0, hi] (live interpolated)."""
    out: dict[str, Any] = {"samples": 0, "span_s": 0.0, "joints": {}, "rms_max_rad": None, "max_rad": None}
    if not recorded.t or len(live.t) < 2 or recorded.names != live.names:
        return out
    tr, qr = recorded.arrays()
    tl, ql = live.arrays()
    sel = (tr >= max(0.0, tl[0])) & (tr <= min(hi, tl[-1]))
    if not sel.any():
        return out
    tr, qr = tr[sel], qr[sel]
    diff = np.column_stack([np.interp(tr, tl, ql[:, j]) for j in range(ql.shape[1])]) - qr
    rms = np.sqrt(np.mean(diff**2, axis=0))
    mx = np.max(np.abs(diff), axis=0)
    out["samples"] = int(tr.size)
    out["span_s"] = round(float(tr[-1] - tr[0]), 3)
    out["joints"] = {
        n: {"rms_rad": float(r), "max_rad": float(m)} for n, r, m in zip(recorded.names, rms, mx, strict=True)
    }
    out["rms_max_rad"] = float(rms.max())
    out["max_rad"] = float(mx.max())
    return out


def divergence(
    recorded: Response, live: Response, hi: float, window_s: float = 0.1, dt: float = 0.01
) -> tuple[float | None, str]:
    """First time the two runs' control conditions differ for ``window_s`` or longer, and why.

    The conditions are the slave's follow state and, while both follow, the watchdog's
    motion-scale factor. The
    mapping is incremental, so once one run held (or moved at another scale) where the other did
    not, the slave continues from another pose: later differences say nothing about the replay.
    """
    grid = np.arange(0.0, max(hi, 0.0), dt)
    if grid.size == 0:
        return None, ""
    fr, sr, wr = recorded.conditions(grid)
    fl, sl, wl = live.conditions(grid)
    mismatch = (fr != fl) | (fr & fl & (np.abs(sr - sl) > 1e-9))  # the scale matters while following
    need = max(1, round(window_s / dt))
    run = 0
    for i, m in enumerate(mismatch):
        run = run + 1 if m else 0
        if run >= need:
            k = i - need + 1
            return round(float(grid[k]), 3), (
                f"recorded: follow={bool(fr[k])} scale={sr[k]:g} {wr[k]}".rstrip()
                + f"; live: follow={bool(fl[k])} scale={sl[k]:g} {wl[k]}".rstrip()
            )
    return None, ""


def compare(recorded: Response, live: Response, behind: tuple[float, str] | None = None) -> dict[str, Any]:
    """Per-joint RMS and max |live − recorded|, live interpolated onto the recorded samples.

    The figures (``samples``, ``span_s``, ``joints: {name: {rms_rad, max_rad}}``, ``rms_max_rad``,
    ``max_rad``) cover the time from the first replayed message until the runs diverge
    (``diverged_s``, ``diverged_because``; None / "" if they never do, see :func:`divergence`) or
    the replay itself fell behind the recording's timing (``behind``: recorded time and why, from
    :func:`fell_behind`); ``full`` holds the same figures over the whole overlap. ``samples`` is 0
    (and the maxima None) when there is no overlap or the joints differ.
    """
    full = _diff(recorded, live, float("inf"))
    hi = min(recorded.t[-1] if recorded.t else 0.0, live.t[-1] if live.t else 0.0)
    diverged, because = divergence(recorded, live, hi)
    if behind is not None and (diverged is None or behind[0] < diverged):
        diverged, because = behind
    part = _diff(recorded, live, diverged) if diverged is not None else full
    return {
        **part,
        "diverged_s": diverged,
        "diverged_because": because,
        "recorded_follow_s": recorded.follow_s,
        "live_follow_s": live.follow_s,
        "full": full,
    }


def fell_behind(
    sends: Sequence[tuple[float, float]], max_late_ms: float, window_s: float = 0.1
) -> tuple[float, str] | None:
    """When the replay first stayed more than ``max_late_ms`` behind the recording's timing for
    ``window_s`` of recorded time or longer (recorded time and why), if it did.

    ``sends`` are (recorded time [s since the first message], lateness [ms]). A replay that fell
    behind (a stall of a busy host) plays the master's motion late or in a burst: the slave then
    answers another input, and the responses after that point say nothing about the recording. A
    single late message (one scheduling hiccup) is not counted.
    """
    since: float | None = None
    worst = 0.0
    for t, late in sends:
        if late <= max_late_ms:
            since, worst = None, 0.0
            continue
        since = t if since is None else since
        worst = max(worst, late)
        if t - since >= window_s:
            return round(since, 3), (
                f"the replay fell behind the recording's timing at {since:.2f} s ({worst:.0f} ms late, "
                f"over {max_late_ms:g} ms for {window_s:g} s: this host could not keep pace); later "
                "responses are not comparable"
            )
    return None


def _arm_key(topic: str, prefix: str) -> tuple[str, str] | None:
    """(arm, relative key) for the keys that make up an arm's response, else None."""
    rel = topic[len(prefix) :] if topic.startswith(prefix) else ""
    parts = rel.split("/")
    if len(parts) == 3 and any(fnmatch.fnmatchcase(rel, g) for g in RESPONSE_KEYS):
        return parts[1], rel
    return None


def _trusted(rel: str, source: str, slave_source: str, watchdog_source: str) -> bool:
    return source == (watchdog_source if rel.startswith("safety/") else slave_source)


def recorded_response(
    path: str | Path, site: str, t0_ns: int, slave_source: str, watchdog_source: str
) -> dict[str, Response]:
    """Each arm's run in the file (trusted sources only), times relative to ``t0_ns``."""
    prefix = Keys(site).prefix + "/"
    out: dict[str, Response] = {}
    with open_mcap(path) as reader:
        for topic, _lt, _pt, _data, msg in iter_decoded(reader, lambda t: _arm_key(t, prefix) is not None):
            arm_rel = _arm_key(topic, prefix)
            if msg is None or arm_rel is None:
                continue
            arm, rel = arm_rel
            if _trusted(rel, msg.header.source, slave_source, watchdog_source):
                out.setdefault(arm, Response()).add((msg.header.stamp_ns - t0_ns) / 1e9, msg)
    return out


class LiveResponse:
    """Records each arm's live run (strictly decoded, trusted sources only)."""

    def __init__(self, node: Node, arms: Sequence[str], slave_source: str, watchdog_source: str) -> None:
        self.lock = threading.Lock()
        self.t0_ns = 0  # stamp of the first replayed message; set by the replay loop
        self.speed = 1.0
        self.arms: dict[str, Response] = {a: Response() for a in arms}
        k = node.keys
        for arm in arms:
            cb = self._callback(arm)
            node.subscribe(k.slave(arm, "measured_js"), Message, cb, sources=[slave_source])
            node.subscribe(k.slave(arm, "operating_state"), Message, cb, sources=[slave_source])
            node.subscribe(k.safety(arm, "state"), Message, cb, sources=[watchdog_source])

    def _callback(self, arm: str) -> Callable[[Message, str], None]:
        def on_message(m: Message, key: str) -> None:
            with self.lock:
                if self.t0_ns:
                    self.arms[arm].add((m.header.stamp_ns - self.t0_ns) / 1e9 * self.speed, m)

        return on_message

    def snapshot(self) -> dict[str, Response]:
        """A copy of what was recorded so far."""
        with self.lock:
            return {
                a: dataclasses.replace(
                    r, t=list(r.t), q=list(r.q), follow=list(r.follow), scale=list(r.scale)
                )
                for a, r in self.arms.items()
            }


# --------------------------------------------------------------------------- pre-flight

#: Exit codes of ``telesurg replay`` beyond 0 (done), 1 (failure) and 2 (bad flags / refused site).
EXIT_DIVERGED = 3
EXIT_NEVER_ENGAGED = 4


class SiteBusy(ConfigError):
    """The site already runs a publisher of the streams the replay would send."""


def alive_services(bus: BusConfig, site: str, timeout: float = 1.0) -> list[str]:
    """Service ids holding a liveliness token on ``site``, asked from a short session of its own
    (before the replay's node, which is itself on the bus as ``--as``, declares its token)."""
    keys = Keys(site)
    session = open_session(bus)
    try:
        replies = session.liveliness().get(keys.alive("*"), timeout=timeout)
        return sorted({keys.service_of_alive(str(r.ok.key_expr)) for r in replies if r.ok is not None})
    finally:
        session.close()  # type: ignore[no-untyped-call]


def check_site_free(bus: BusConfig, site: str, service: str) -> None:
    """Raise :class:`SiteBusy` naming the live publisher(s) the replay would fight.

    ``master_capture`` publishes the master streams; ``service`` is the id the replay takes
    (``--as``): two publishers under one id and key make both streams look lost or reordered."""
    busy = sorted({"master_capture", service} & set(alive_services(bus, site)))
    if busy:
        raise SiteBusy(
            f"{', '.join(busy)} is alive on site {site!r}: it publishes the master streams the replay "
            "would send (two publishers would fight). Stop it first, e.g. start the site with "
            "`telesurg up --services watchdog,slave_control,mapping,mirror`"
        )


def first_buttons(path: str, prefix: str, globs: Sequence[str]) -> dict[str, MasterButtons]:
    """The first ``buttons`` message of each replayed buttons key (relative key → message)."""
    out: dict[str, MasterButtons] = {}

    def want(topic: str) -> bool:
        rel = topic[len(prefix) :] if topic.startswith(prefix) else ""
        return rel.endswith("/buttons") and rel not in out and any(fnmatch.fnmatchcase(rel, g) for g in globs)

    with open_mcap(path) as reader:
        for topic, _lt, _pt, _data, msg in iter_decoded(reader, want):
            rel = topic[len(prefix) :]
            if isinstance(msg, MasterButtons) and rel not in out:
                out[rel] = msg
    return out


# --------------------------------------------------------------------------- replay


def _reader_thread(
    path: str, prefix: str, globs: Sequence[str], out: queue.Queue[Any], stop: threading.Event
) -> None:
    """Decode the selected messages into ``out`` (bounded), then None; an exception on failure."""

    def want(topic: str) -> bool:
        rel = topic[len(prefix) :] if topic.startswith(prefix) else ""
        return bool(rel) and any(fnmatch.fnmatchcase(rel, g) for g in globs)

    def put(item: Any) -> None:
        while not stop.is_set():
            try:
                out.put(item, timeout=0.2)
                return
            except queue.Full:
                continue

    try:
        with open_mcap(path) as reader:
            for topic, _lt, pt, _data, msg in iter_decoded(reader, want):
                if stop.is_set():
                    return
                put((topic[len(prefix) :], pt, msg))
    except Exception as exc:  # reported by the replay loop
        put(exc)
        return
    put(None)


def replay(cfg: ReplayConfig, stop: threading.Event) -> dict[str, Any]:
    """Play the file into the live bus; the report (see :func:`compare`) per slave arm."""
    cfg.validate()
    with open_mcap(cfg.file) as reader:
        rec_site = recording_site(reader)
        summary = reader.get_summary()
        topics = [c.topic for c in summary.channels.values()] if summary is not None else []
    rec_prefix = Keys(rec_site).prefix + "/"
    arms = sorted(
        {
            t[len(rec_prefix) :].split("/")[1]
            for t in topics
            if t.startswith(rec_prefix) and fnmatch.fnmatchcase(t[len(rec_prefix) :], RESPONSE_GLOB)
        }
    )
    site = cfg.site or rec_site
    if cfg.preflight:
        check_site_free(cfg.bus, site, cfg.service)
    # ~2 s of master data ahead: filled during the lead-in, then decoded at the playback rate
    # (a larger read-ahead is a CPU burst that delays the first replayed messages)
    items: queue.Queue[Any] = queue.Queue(maxsize=1_000)
    reader_stop = threading.Event()
    th = threading.Thread(
        target=_reader_thread, args=(cfg.file, rec_prefix, cfg.keys, items, reader_stop), daemon=True
    )
    th.start()
    held = {rel: m for rel, m in first_buttons(cfg.file, rec_prefix, cfg.keys).items() if m.clutch}
    sent: dict[str, int] = {}
    undecodable = 0
    late_ms: list[float] = []
    sends: list[tuple[float, float]] = []  # (recorded s since the first message, lateness ms)
    t0_rec = 0
    try:
        with contextlib.ExitStack() as stack:
            node = stack.enter_context(Node(cfg.bus, site, cfg.service))
            if cfg.record:
                info = {"replay_of": str(cfg.file), "speed": str(cfg.speed)}
                rec = stack.enter_context(Recorder(cfg.record, site, info=info))
                rec.subscribe(node.session, node.keys.all)
            live = LiveResponse(node, arms, cfg.slave_source, cfg.watchdog_source)
            live.speed = cfg.speed
            outlets: dict[str, Outlet] = {}
            log.info(
                "replaying %s (%s) onto %s as %r",
                cfg.file,
                ", ".join(cfg.keys),
                node.keys.prefix,
                cfg.service,
            )
            stop.wait(cfg.lead_in_s)
            for rel, first in held.items():  # the recording starts with the pedal held: release it
                log.warning(
                    "%s: the recording starts with the clutch pedal held; sending a release for %.2f s "
                    "first, so that the recorded pedal engages as a press",
                    rel,
                    cfg.release_s,
                )
                release = outlets[rel] = node.outlet(f"{node.keys.prefix}/{rel}")
                release.put(dataclasses.replace(first, header=release.header(), clutch=False))
            if held:
                stop.wait(cfg.release_s)
            start = 0.0
            while not stop.is_set():
                try:
                    item = items.get(timeout=0.5)
                except queue.Empty:
                    continue
                if item is None:
                    break
                if isinstance(item, Exception):
                    raise item
                rel, pt, msg = item
                if msg is None:
                    undecodable += 1
                    continue
                if not start:
                    start, t0_rec = time.monotonic(), pt
                due = start + (pt - t0_rec) / 1e9 / cfg.speed
                if cfg.step:
                    if not _ask(rel, msg):
                        break
                elif (delay := due - time.monotonic()) > 0 and stop.wait(delay):
                    break
                out = outlets.get(rel)
                if out is None:
                    out = outlets[rel] = node.outlet(f"{node.keys.prefix}/{rel}")
                h = out.header()
                out.put(dataclasses.replace(msg, header=h))
                if not live.t0_ns:
                    with live.lock:
                        live.t0_ns = h.stamp_ns
                late_ms.append((time.monotonic() - due) * 1e3)
                sends.append(((pt - t0_rec) / 1e9, late_ms[-1]))
                sent[rel] = sent.get(rel, 0) + 1
            stop.wait(cfg.settle_s)
            played = live.snapshot()
    finally:
        reader_stop.set()
        th.join(timeout=2.0)
    recorded = (
        recorded_response(cfg.file, rec_site, t0_rec, cfg.slave_source, cfg.watchdog_source) if t0_rec else {}
    )
    lat = np.asarray(late_ms) if late_ms and not cfg.step else np.zeros(1)
    behind = None if cfg.step else fell_behind(sends, cfg.max_late_ms)
    return {
        "file": str(cfg.file),
        "speed": cfg.speed,
        "step": cfg.step,
        "sent": sent,
        "undecodable": undecodable,
        "played_s": round(_played_s(played), 3),
        "synthesized_release": sorted(held),
        "timing_late_ms": {
            "p50": round(float(np.percentile(lat, 50)), 3),
            "p99": round(float(np.percentile(lat, 99)), 3),
            "max": round(float(lat.max()), 3),
        },
        "fell_behind_s": behind[0] if behind else None,
        "arms": {a: compare(recorded.get(a, Response()), played.get(a, Response()), behind) for a in arms},
    }


def _played_s(played: dict[str, Response]) -> float:
    return max((r.t[-1] for r in played.values() if r.t), default=0.0)


def _ask(rel: str, msg: Message) -> bool:
    """--step: show the next message, wait for Enter (False on EOF / 'q')."""
    h = msg.header
    print(f"next: {rel}  {msg.TYPE}  recorded seq {h.seq}  [Enter: send, q: stop] ", end="", flush=True)
    try:
        return input().strip().lower() != "q"
    except EOFError:
        return False


def print_report(report: dict[str, Any], file: Any = None) -> None:
    """Per-arm, per-joint difference table (rich)."""
    from rich.console import Console
    from rich.table import Table

    console = Console(file=file or sys.stdout, width=160)
    sent = ", ".join(f"{k} {n}" for k, n in report["sent"].items()) or "nothing"
    lat = report["timing_late_ms"]
    console.print(
        f"replayed {report['file']} at speed {report['speed']:g}: {sent}; "
        f"send lateness p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms, max {lat['max']:.2f} ms"
    )
    for arm, r in report["arms"].items():
        full = r["full"]
        console.print(
            f"slave {arm}: follows from {r['recorded_follow_s']} s (recorded) / {r['live_follow_s']} s "
            f"(live); compared over {r['span_s']:.2f} s ({r['samples']} samples)"
            + (
                f" until the runs diverged at {r['diverged_s']:.2f} s: {r['diverged_because']}"
                if r["diverged_s"] is not None
                else ", no divergence"
            )
        )
        table = Table(show_edge=False)
        table.add_column("joint")
        table.add_column("RMS [rad]", justify="right")
        table.add_column("max [rad]", justify="right")
        table.add_column(f"RMS, all {full['span_s']:.2f} s", justify="right")
        table.add_column("max, all", justify="right")
        for name, j in r["joints"].items():
            f = full["joints"].get(name, {"rms_rad": float("nan"), "max_rad": float("nan")})
            table.add_row(
                name,
                f"{j['rms_rad']:.5f}",
                f"{j['max_rad']:.5f}",
                f"{f['rms_rad']:.5f}",
                f"{f['max_rad']:.5f}",
            )
        if not r["joints"]:
            table.add_row("(no overlap between the recorded and the live response)", "-", "-", "-", "-")
        console.print(table)


# --------------------------------------------------------------------------- rerun


def to_rerun(path: str | Path, out: str | Path) -> dict[str, int]:
    """Convert a recording to an .rrd with the mirror's drawing code; no network involved.

    Messages are fed to :class:`telesurg.services.mirror.Mirror` in batches of one mirror draw period of
    log time, so the file looks like the live mirror's: joint series in blocks (``send_columns``),
    tip trails and points, state changes and events as text logs. Only the mirror's trusted
    sources are drawn on ``master/``, ``slave/`` and ``safety/`` keys (as live).
    Returns counts: ``messages``, ``undecodable``, ``untrusted``, ``drawn`` (joint samples).
    """
    from telesurg.services.mirror import Mirror, MirrorConfig
    from telesurg.services.mirror.view import RerunView

    mc = MirrorConfig()
    trusted = frozenset(mc.trusted_sources)
    counts = {"messages": 0, "undecodable": 0, "untrusted": 0, "drawn": 0}
    # the file whole or not at all; the view closed (flushed) before it is renamed
    with (
        written_whole(out) as part,
        contextlib.closing(RerunView(mc.application_id, save=str(part))) as view,
        open_mcap(path) as reader,
    ):
        prefix = Keys(recording_site(reader)).prefix + "/"
        mirror = Mirror(view, prefix, mc.trail_s, mc.trail_hz)
        tick_ns = round(1e9 / mc.effective_draw_hz())  # the file-only rate
        next_tick = 0
        batch: list[tuple[str, int, Any]] = []
        image_ns = round(1e9 / mc.image_hz) if mc.image_hz > 0 else 0
        next_image: dict[str, int] = {}
        for topic, lt, _pt, _data, msg in iter_decoded(reader):
            counts["messages"] += 1
            if msg is None:
                counts["undecodable"] += 1
                continue
            if isinstance(msg, CameraImage):  # decimated, as the live mirror draws them
                if image_ns and msg.header.source == "camera" and lt >= next_image.get(msg.camera, 0):
                    next_image[msg.camera] = lt + image_ns
                    view.image(msg.camera, msg.capture_ns, lt, msg.data)
                    counts["images"] = counts.get("images", 0) + 1
                continue
            role = topic[len(prefix) :].split("/", 1)[0] if topic.startswith(prefix) else ""
            if role in ("master", "slave", "safety") and msg.header.source not in trusted:
                counts["untrusted"] += 1
                continue
            if not next_tick:
                next_tick = lt + tick_ns
            if lt >= next_tick:
                mirror.feed(batch)
                mirror.draw()
                batch = []
                next_tick += ((lt - next_tick) // tick_ns + 1) * tick_ns
            batch.append((topic, lt, msg))
        mirror.feed(batch)
        mirror.draw()
        counts["drawn"] = mirror.drawn
    return counts


# --------------------------------------------------------------------------- CLI


def parser() -> argparse.ArgumentParser:
    """Command-line flags of ``telesurg replay``."""
    p = argparse.ArgumentParser(
        prog="telesurg replay", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("file", metavar="FILE.mcap", help="recording made with telesurg record")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--step", action="store_true", help="wait for Enter before each message")
    p.add_argument(
        "--keys",
        nargs="+",
        metavar="GLOB",
        help=f"relative keys to replay (default: {' '.join(MASTER_GLOBS)})",
    )
    p.add_argument("--as", dest="service", default="master_capture", help="header source / node id")
    p.add_argument("--site", default="", help="site to publish on (default: the recorded one)")
    p.add_argument("--lead-in", type=float, default=0.5, help="s on the bus before playing (0.5)")
    p.add_argument("--settle", type=float, default=1.0, help="s of slave response after the end (1)")
    p.add_argument("--json", metavar="FILE", help="write the report as JSON")
    p.add_argument("--record", metavar="OUT.mcap", help="also record the live bus during the replay")
    p.add_argument(
        "--max-rms",
        type=float,
        default=0.02,
        metavar="RAD",
        help="exit 3 if any joint's RMS difference (until the runs diverge) exceeds RAD (0.02; 0 = off)",
    )
    p.add_argument(
        "--max-late-ms",
        type=float,
        default=50.0,
        metavar="MS",
        help="compare only until the replay stayed more than MS behind the recording for 0.1 s (50)",
    )
    p.add_argument(
        "--release-s",
        type=float,
        default=0.3,
        metavar="S",
        help="a recording that starts with the pedal held: send a release for S s first (0.3)",
    )
    p.add_argument(
        "--no-preflight",
        action="store_true",
        help="do not refuse a site where master_capture (or --as) is already alive",
    )
    p.add_argument("--to-rerun", metavar="OUT.rrd", help="convert to a rerun file (no network) and exit")
    p.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    add_bus_args(p)
    return p


def verdict(report: dict[str, Any], max_rms: float) -> tuple[int, str]:
    """(exit code, why) of a replay report: 0 when it means something and matches.

    :data:`EXIT_NEVER_ENGAGED` when no arm ever followed in the replay (or an arm that followed in
    the recording never did live), :data:`EXIT_DIVERGED` when a joint's RMS difference over the
    compared window exceeds ``max_rms`` (> 0) or nothing could be compared."""
    arms = report["arms"]
    never = [a for a, r in arms.items() if r["live_follow_s"] is None and r["recorded_follow_s"] is not None]
    if never or not any(r["live_follow_s"] is not None for r in arms.values()):
        who = ", ".join(never or sorted(arms)) or "no arm"
        return EXIT_NEVER_ENGAGED, f"the replay never engaged ({who}): it shows nothing of the recording"
    if max_rms > 0:
        compared = [r for r in arms.values() if r["samples"]]
        worst = max((r["rms_max_rad"] for r in compared), default=0.0)
        if not compared:
            if report.get("fell_behind_s") is not None:
                return EXIT_DIVERGED, (
                    f"the replay fell behind the recording at {report['fell_behind_s']} s: nothing compared"
                )
            return EXIT_DIVERGED, "no overlap between the recorded and the live response: nothing compared"
        if worst > max_rms:
            return EXIT_DIVERGED, f"RMS difference {worst:.5f} rad exceeds --max-rms {max_rms:g}"
    return 0, ""


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg replay``: 0 done, 1 failure, 2 bad flags or a busy site, 3 over ``--max-rms``, 4
    never engaged."""
    args = parser().parse_args(argv)
    setup_logging(args.log_level, "replay")
    if args.to_rerun:
        if not Path(args.file).is_file():
            print(f"telesurg replay: {args.file}: no such file", file=sys.stderr)
            return 2
        try:
            counts = to_rerun(args.file, args.to_rerun)
        except (TelesurgError, OSError, McapError) as exc:
            log.error("%s", exc)
            return 1
        print(f"wrote {args.to_rerun}: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
        return 0
    cfg = ReplayConfig(
        file=args.file,
        site=args.site,
        service=args.service,
        keys=list(args.keys or MASTER_GLOBS),
        speed=args.speed,
        step=args.step,
        lead_in_s=args.lead_in,
        settle_s=args.settle,
        record=args.record or "",
        release_s=args.release_s,
        max_late_ms=args.max_late_ms,
        preflight=not args.no_preflight,
    )
    try:
        cfg.bus = bus_from_args(args, cfg.bus)
        cfg.validate()
    except TelesurgError as exc:
        print(f"telesurg replay: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    install_stop_handlers(stop)
    try:
        report = replay(cfg, stop)
    except SiteBusy as exc:
        print(f"telesurg replay: {exc}", file=sys.stderr)
        return 2
    except (TelesurgError, ConnectionError, OSError, McapError) as exc:
        log.error("%s", exc)
        return 1
    print_report(report)
    code, why = verdict(report, args.max_rms)
    report["verdict"] = {"exit": code, "why": why}
    if args.json:
        Path(args.json).write_text(jsonio.dumps(report, indent=2) + "\n")
    if code:
        log.error("%s", why)
    return code


if __name__ == "__main__":
    sys.exit(main())
