"""The browser master's rules, free of I/O: socket frames, their validation, the browser's clock,
the freshness of its samples and the fresh-press rule after a reconnect.

The web console (:mod:`telesurg.services.console.web`) feeds every websocket frame through a
:class:`SocketGuard` (size, rate, strict JSON: no NaN/Inf, known fields only, finite numbers in
range) and hands accepted samples to a :class:`BrowserMaster`, which its publisher asks at a
fixed rate for the sample to publish (None: nothing is published, so the watchdog holds).

A frame from the browser is one JSON object with a ``type``:

* ``sample`` — the master pose the page computed from its input device::

      {"type": "sample", "master": "m1", "t": 1764640000123.4, "p": [x, y, z],
       "q": [qx, qy, qz, qw], "clutch": true, "present": true, "device": "mouse"}

  ``t``: the browser's clock at the input event, ms since the Unix epoch
  (``performance.timeOrigin + event.timeStamp``); ``p`` in m (master frame, |p| ≤ 1 m);
  ``q`` a unit quaternion (x, y, z, w; norm within 1 %).
* ``hidden`` — the tab was hidden or is closing: the master's samples are invalid at once.
* ``estop`` / ``reset`` (``arm``: an arm or ``*``; a reset needs ``"confirm": true``),
  ``command`` (``arm``, ``name``, ``args``: ["key=value", …], ``target``: slave | mapping),
  ``record`` (``action``: start | stop).
* ``control`` (``action``: take | release | grant | refuse) and ``invite`` (a one-time login link
  for another page); a page not in control (a viewer) may send only these, ``estop``, ``hidden``
  and ``ping``.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Any

from telesurg.shared.errors import TelesurgError

#: frame type → its fields (``type`` included) and which of them are required
FRAMES: dict[str, tuple[frozenset[str], frozenset[str]]] = {
    "sample": (
        frozenset({"type", "master", "t", "p", "q", "clutch", "present", "device"}),
        frozenset({"type", "master", "t", "p", "q", "clutch"}),
    ),
    "hidden": (frozenset({"type", "master"}), frozenset({"type"})),
    "estop": (frozenset({"type", "arm"}), frozenset({"type"})),
    "reset": (frozenset({"type", "arm", "confirm"}), frozenset({"type", "confirm"})),
    "command": (frozenset({"type", "arm", "name", "args", "target"}), frozenset({"type", "arm", "name"})),
    "record": (frozenset({"type", "action"}), frozenset({"type", "action"})),
    # the operator's answer to a server's ``confirm required`` (a motion-starting command)
    "confirm": (frozenset({"type", "yes"}), frozenset({"type", "yes"})),
    "ping": (frozenset({"type", "t"}), frozenset({"type"})),
    # control of the master (services/console/control.py): take | release | grant | refuse
    "control": (frozenset({"type", "action"}), frozenset({"type", "action"})),
    # a one-time login link for another page (a viewer)
    "invite": (frozenset({"type"}), frozenset({"type"})),
}
#: frame types a viewer (a page not in control) may send; the rest need control
VIEWER_FRAMES = frozenset({"estop", "hidden", "ping", "control", "invite"})
DEVICES = ("mouse", "touch", "gamepad", "keyboard")
MAX_POSITION_M = 1.0  # m: a browser master's position beyond this is refused


class FrameError(TelesurgError):
    """A websocket frame was refused; ``kind`` names the counter it goes to."""

    def __init__(self, kind: str, text: str) -> None:
        super().__init__(text)
        self.kind = kind
        self.admitted = False  # raised after SocketGuard.admit passed the frame (a bad field)


def _no_constant(name: str) -> Any:
    raise FrameError("nonfinite", f"{name} is not a number JSON allows")


def _finite(v: Any, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise FrameError("invalid", f"{what} must be a number")
    f = float(v)
    if not math.isfinite(f):
        raise FrameError("nonfinite", f"{what} is not finite")
    return f


def _vector(v: Any, n: int, what: str) -> tuple[float, ...]:
    if not isinstance(v, list) or len(v) != n:
        raise FrameError("invalid", f"{what} must be a list of {n} numbers")
    return tuple(_finite(x, f"{what}[{i}]") for i, x in enumerate(v))


@dataclass(frozen=True)
class Sample:
    """One validated browser master sample (see the module docstring)."""

    master: str
    t_ms: float  # browser clock, ms since the epoch
    position: tuple[float, float, float]  # m
    orientation: tuple[float, float, float, float]  # x, y, z, w (normalised)
    clutch: bool
    present: bool
    device: str


def parse_frame(text: str | bytes, max_bytes: int) -> dict[str, Any]:
    """Decode one frame: a JSON object of a known type with known fields only.

    Raises:
        FrameError: ``oversized``, ``binary``, ``malformed`` (not JSON, not an object),
            ``nonfinite`` (NaN / Infinity), ``unknown`` (type or field) or ``invalid``.
    """
    if isinstance(text, bytes):
        raise FrameError("binary", "binary frames are not accepted")
    if len(text) > max_bytes:
        raise FrameError("oversized", f"frame of {len(text)} characters > {max_bytes}")
    try:
        obj = json.loads(text, parse_constant=_no_constant)
    except FrameError:
        raise
    except (ValueError, RecursionError) as exc:
        raise FrameError("malformed", f"not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise FrameError("malformed", "a frame must be a JSON object")
    kind = obj.get("type")
    if not isinstance(kind, str) or kind not in FRAMES:
        raise FrameError("unknown", f"unknown frame type {kind!r}; valid: {', '.join(FRAMES)}")
    allowed, required = FRAMES[kind]
    extra = set(obj) - allowed
    if extra:
        raise FrameError("unknown", f"{kind}: unknown fields {sorted(extra)}")
    missing = required - set(obj)
    if missing:
        raise FrameError("invalid", f"{kind}: missing fields {sorted(missing)}")
    return obj


def parse_sample(obj: dict[str, Any], masters: tuple[str, ...]) -> Sample:
    """A ``sample`` frame (from :func:`parse_frame`) checked field by field."""
    master = obj["master"]
    if master not in masters:
        mine = ", ".join(masters) or "none (web.master_service is off)"
        raise FrameError("invalid", f"master {master!r} is not one of this console's: {mine}")
    t = _finite(obj["t"], "t")
    p = _vector(obj["p"], 3, "p")
    if max(abs(x) for x in p) > MAX_POSITION_M:
        raise FrameError("invalid", f"p {p} beyond ±{MAX_POSITION_M} m")
    q = _vector(obj["q"], 4, "q")
    norm = math.sqrt(sum(x * x for x in q))
    if not 0.99 <= norm <= 1.01:
        raise FrameError("invalid", f"q must be a unit quaternion (norm {norm:.3f})")
    clutch, present = obj["clutch"], obj.get("present", True)
    if not isinstance(clutch, bool) or not isinstance(present, bool):
        raise FrameError("invalid", "clutch and present must be true or false")
    device = obj.get("device", "mouse")
    if device not in DEVICES:
        raise FrameError("invalid", f"device {device!r}; valid: {', '.join(DEVICES)}")
    qn = (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)
    return Sample(master, t, (p[0], p[1], p[2]), qn, clutch, present, device)


@dataclass
class SocketGuard:
    """Per connection: frame budget and counters; :attr:`abusive` once it must be closed.

    A token bucket allows ``rate_hz`` frames a second on average (bursts of ``burst``); a frame
    beyond it is refused (``flood``). After ``max_rejects`` refused frames of any kind the
    connection is abusive and the server closes it.
    """

    rate_hz: float = 400.0
    burst: float = 100.0
    max_rejects: int = 50
    max_bytes: int = 4096
    counts: dict[str, int] = field(default_factory=dict)
    accepted: int = 0
    _tokens: float = -1.0
    _t: float = 0.0

    @property
    def rejected(self) -> int:
        """Frames refused on this connection."""
        return sum(self.counts.values())

    @property
    def abusive(self) -> bool:
        """Too many refused frames: close the connection."""
        return self.rejected >= self.max_rejects

    def admit(self, text: str | bytes, now: float | None = None) -> dict[str, Any]:
        """The frame decoded, or FrameError (counted)."""
        now = time.monotonic() if now is None else now
        if self._tokens < 0:
            self._tokens, self._t = self.burst, now
        self._tokens = min(self.burst, self._tokens + (now - self._t) * self.rate_hz)
        self._t = now
        try:
            if self._tokens < 1.0:
                raise FrameError("flood", f"more than {self.rate_hz:g} frames/s")
            self._tokens -= 1.0
            obj = parse_frame(text, self.max_bytes)
        except FrameError as exc:
            self.reject(exc.kind)
            raise
        return obj

    def reject(self, kind: str) -> None:
        """Count one refused frame of ``kind``."""
        self.counts[kind] = self.counts.get(kind, 0) + 1


class ClockMap:
    """Maps the browser's clock onto this host's wall clock.

    The offset is the smallest ``receive − browser stamp`` seen on the connection (the frame with
    the least transit delay), so a phone whose clock is off by seconds still gets stamps on this
    host's clock, never later than their arrival.
    """

    def __init__(self) -> None:
        self.offset_ns: int | None = None

    def stamp_ns(self, browser_ms: float, received_ns: int) -> int:
        """The host wall-clock time (ns) of a browser stamp received at ``received_ns``."""
        b = round(browser_ms * 1e6)
        d = received_ns - b
        if self.offset_ns is None or d < self.offset_ns:
            self.offset_ns = d
        return min(b + self.offset_ns, received_ns)


@dataclass(frozen=True)
class Published:
    """What the publisher sends for one master this cycle."""

    stamp_ns: int
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    clutch: bool
    present: bool


class BrowserMaster:
    """One master fed by the browser; not thread-safe (the caller holds a lock).

    Its samples are valid while a connection feeds it and the newest sample is younger than
    ``timeout_s``. A connection that closes or says ``hidden`` invalidates them at once. The
    clutch it reports is pressed only after a *release* was seen on the current connection: a
    browser that reconnects with the clutch held must release it and press again.
    """

    def __init__(self, master: str, timeout_s: float) -> None:
        self.master = master
        self.timeout_s = timeout_s
        self.owner: object | None = None  # the connection feeding it
        self.sample: Sample | None = None
        self.stamp_ns = 0  # host wall-clock time of the sample
        self.rx = 0.0  # monotonic s it arrived
        self.released_seen = False  # a release seen on the current connection
        self.invalidations = 0  # times the samples went invalid (hidden, closed, stale)
        self._valid = False

    def attach(self, owner: object) -> None:
        """A connection takes this master over (the previous one's samples are void)."""
        self.owner, self.sample, self.released_seen = owner, None, False
        self._invalidate()

    def detach(self, owner: object) -> None:
        """The connection closed or the tab was hidden: samples invalid at once."""
        if self.owner is owner:
            self.owner, self.sample, self.released_seen = None, None, False
            self._invalidate()

    def feed(self, owner: object, s: Sample, stamp_ns: int, now: float) -> None:
        """An accepted sample from ``owner``."""
        if self.owner is not owner:
            self.attach(owner)
        if not s.clutch:
            self.released_seen = True
        self.sample, self.stamp_ns, self.rx = s, stamp_ns, now

    def current(self, now: float) -> Published | None:
        """What to publish now, or None (no connection, hidden, or the newest sample too old)."""
        s = self.sample
        if self.owner is None or s is None or now - self.rx > self.timeout_s:
            if self._valid:
                self._invalidate()
            return None
        self._valid = True
        return Published(self.stamp_ns, s.position, s.orientation, s.clutch and self.released_seen, s.present)

    def _invalidate(self) -> None:
        if self._valid:
            self.invalidations += 1
        self._valid = False
