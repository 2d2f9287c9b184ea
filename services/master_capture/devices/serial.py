"""The ``serial`` master device: the all-joints (PLAS) master's encoder board
(:mod:`telesurg.shared.encoder_protocol` over :mod:`telesurg.shared.serial_link`; docs/robots.md, Hardware),
read in a background thread, with automatic reconnection. A reading older than ``stale_ms`` is
invalid (``DeviceSample.valid``): master_capture then publishes nothing and the watchdog holds.

Example: ``telesurg master-capture --set device=serial --set serial.port=/dev/ttyACM0``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from telesurg.services.master_capture.devices import DeviceSample, MasterDevice, register
from telesurg.shared.encoder_protocol import (
    KIND_HELLO,
    Calibration,
    Hello,
    HelloRequest,
    MasterReading,
    Sample,
    decode_message,
    send_message,
)
from telesurg.shared.errors import ConfigError, DeviceConnectionError, MessageError
from telesurg.shared.streams import NEXT

if TYPE_CHECKING:
    from types import TracebackType

    from telesurg.shared.serial_link import Frame, SerialLink

log = logging.getLogger(__name__)


#: measured_js names of the all-joints master, in the order of
#: ``telesurg.shared.robots.plas.kinematics.PlasMasterGeometry.joint_names``.
PLAS_MASTER_JOINTS = ("d1", "theta2", "theta3", "theta4", "theta5", "d6")
_ORIGIN = (0.0, 0.0, 0.0)
_IDENTITY = (0.0, 0.0, 0.0, 1.0)


@dataclass
class SerialMasterConfig:
    """Serial master: the all-joints master's encoder board (``docs/robots.md`` (Hardware))."""

    # serial port or pyserial URL: /dev/ttyACM0, /dev/serial/by-id/... (survives re-plugging),
    # /dev/pts/N (the emulator), loop://, socket://host:port
    port: str = "/dev/ttyACM0"
    baud: int = 115_200  # bit/s: must equal the firmware's BAUD (pseudo-terminals ignore it)
    reconnect_s: float = 0.5  # s: while the port is missing or failing, re-open it this often
    stale_ms: float = 100.0  # ms: no valid SAMPLE for this long → readings invalid, nothing published
    # measured_js joint names, one per calibration joint (PlasMasterGeometry order)
    joint_names: tuple[str, ...] = PLAS_MASTER_JOINTS
    calibration: Calibration = field(default_factory=Calibration)  # counts / ADC → rad / m, per joint

    def validate(self) -> None:
        """Raise ConfigError naming what is wrong."""
        if not self.port:
            raise ConfigError("serial port is empty; e.g. /dev/ttyACM0, /dev/pts/3, loop://")
        if self.baud <= 0:
            raise ConfigError(f"serial baud={self.baud} must be > 0 (the firmware's BAUD, e.g. 115200)")
        if not 0.01 <= self.reconnect_s <= 60.0:
            raise ConfigError(f"serial reconnect_s={self.reconnect_s} outside [0.01, 60] s")
        if not 1.0 <= self.stale_ms <= 10_000.0:
            raise ConfigError(f"serial stale_ms={self.stale_ms} outside [1, 10000] ms")
        if len(self.joint_names) != self.calibration.joints or len(set(self.joint_names)) != len(
            self.joint_names
        ):
            raise ConfigError(
                f"serial joint_names {list(self.joint_names)} must be {self.calibration.joints} distinct "
                "names (calibration.joints)"
            )


@dataclass
class SerialMasterStats:
    """Counters of a serial master since it was made (they survive reconnections).

    Attributes:
        frames: frames that passed framing (COBS, CRC, version), every kind.
        samples: SAMPLEs accepted.
        corrupt: frames dropped by framing: CRC mismatch, bad COBS, truncated, unknown frame
            version, body not MessagePack, oversize (line noise, a cut cable, a reset mid-frame).
        invalid: well-framed messages the encoder protocol rejected: unknown kind, a missing,
            unknown or out-of-range field, a SAMPLE with the wrong number of encoder counts.
        refused: SAMPLEs dropped because the board's HELLO did not match the configuration.
        gaps: sequence gaps (frames lost on the way or never sent); lost: frames missing in them.
        restarts: the board's sequence number went backwards (it restarted).
        reconnects: times the port was opened again after it had been lost.
    """

    frames: int = 0
    samples: int = 0
    corrupt: int = 0
    invalid: int = 0
    refused: int = 0
    gaps: int = 0
    lost: int = 0
    restarts: int = 0
    reconnects: int = 0


@register
class SerialMasterDevice(MasterDevice):
    """The encoder board on a serial port; see :class:`SerialMasterConfig`.

    A background thread owns the port. It opens it and sends HELLO_REQUEST, reads frames,
    checks every HELLO against the calibration (a mismatch is logged and keeps the device invalid
    until a matching HELLO arrives), converts SAMPLEs to joint values, and on a read error or a
    vanished port closes it and re-opens it every ``reconnect_s``. :meth:`read` returns the latest
    reading, ``valid`` only while the port is open, the board accepted and the reading younger
    than ``stale_ms``.

    The all-joints master is mapped joint to joint from ``measured_js``; no master FK is applied
    here, so ``position`` is (0, 0, 0) and ``orientation`` the identity.

    pyserial is imported only when a serial device is made.
    """

    name = "serial"
    config = SerialMasterConfig
    table = "serial"

    def __init__(self, cfg: SerialMasterConfig) -> None:
        from telesurg.shared.serial_link import SerialLink, frame_seq_tracker

        cfg.validate()
        self.cfg = cfg
        self.joint_names: tuple[str, ...] = tuple(cfg.joint_names)
        self._cal = cfg.calibration
        self._stale_s = cfg.stale_ms / 1000.0
        self._link_cls = SerialLink
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # owned by the thread; written under the lock where read() looks at them
        self._link: SerialLink | None = None
        self._latest: MasterReading | None = None
        self._latest_at = 0.0  # time.monotonic() of _latest
        self._hello: Hello | None = None
        self._refused: str | None = None
        self._down: str = "not opened yet"
        self._stats = SerialMasterStats()
        # thread-only state
        self._rx_seq = frame_seq_tracker()  # the board's frame numbers
        self._closed_frames = 0
        self._closed_corrupt = 0
        self._ever_opened = False
        self._logged_open_error: str | None = None
        self._logged_hello: str | None = None  # last HELLO verdict logged on this connection
        self._warned: dict[str, float] = {}

    # ----------------------------------------------------------------- MasterDevice

    def __enter__(self) -> SerialMasterDevice:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"serial-master {self.cfg.port}", daemon=True)
        self._thread.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with self._lock:
            link, self._link = self._link, None
            self._latest = None
            self._down = "closed"
        if link is not None:
            link.close()

    def read(self, t: float) -> DeviceSample:
        """Latest reading; ``valid`` only if fresh (``t`` is not used: the board has its clock)."""
        now = time.monotonic()
        with self._lock:
            r = self._latest
            fresh = (
                r is not None
                and self._link is not None
                and self._refused is None
                and now - self._latest_at <= self._stale_s
            )
        if r is None:
            return DeviceSample(_ORIGIN, _IDENTITY, False, False, (0.0,) * len(self.joint_names), valid=False)
        # joint 1 of the all-joints master is the on/off switch, not an encoder: measured_js carries
        # it as the value of joint d1 (1.0 pressed, 0.0 released) for the all-joints mapping
        joints = (1.0 if r.joint1_switch else 0.0, *r.joints[1:])
        return DeviceSample(_ORIGIN, _IDENTITY, r.clutch, r.operator_present, joints, fresh, r.joint1_switch)

    # ----------------------------------------------------------------- inspection

    @property
    def stats(self) -> SerialMasterStats:
        """A copy of the counters."""
        with self._lock:
            return dataclasses.replace(self._stats)

    @property
    def hello(self) -> Hello | None:
        """The accepted HELLO of the current connection, if any."""
        with self._lock:
            return self._hello

    def status(self) -> str:
        """One line for logs: fresh, stale (and for how long), refused or disconnected (and why)."""
        now = time.monotonic()
        with self._lock:
            if self._link is None:
                return f"disconnected: {self._down}"
            if self._refused is not None:
                return f"refused: {self._refused}"
            if self._latest is None:
                return "connected, no SAMPLE yet"
            age = now - self._latest_at
        return "fresh" if age <= self._stale_s else f"stale: no SAMPLE for {age * 1000:.0f} ms"

    # ----------------------------------------------------------------- reader thread

    def _run(self) -> None:
        next_open = 0.0
        while not self._stop.is_set():
            link = self._link
            if link is None:
                wait = next_open - time.monotonic()
                if wait > 0:
                    self._stop.wait(wait)
                    continue
                next_open = time.monotonic() + self.cfg.reconnect_s
                self._open()
                continue
            try:
                first = link.receive(timeout=0.05)
                frames = [first, *link.poll()] if first is not None else []
                for frame in frames:
                    self._handle(frame)
            except DeviceConnectionError as exc:
                self._drop(str(exc))
                next_open = time.monotonic() + self.cfg.reconnect_s
                continue
            except Exception as exc:  # a bug must not end the thread and leave a dead device behind
                log.exception("serial master reader failed")
                self._drop(f"reader error {type(exc).__name__}: {exc}")
                next_open = time.monotonic() + self.cfg.reconnect_s
                continue
            with self._lock:
                self._stats.frames = self._closed_frames + link.reader.frames
                self._stats.corrupt = self._closed_corrupt + link.reader.error_count

    def _open(self) -> None:
        port = self.cfg.port
        try:
            link = self._link_cls(port, baudrate=self.cfg.baud)
        except DeviceConnectionError as exc:
            self._open_failed(exc)
            return
        try:
            send_message(link, HelloRequest())
        except DeviceConnectionError as exc:
            link.close()
            self._open_failed(exc)
            return
        self._rx_seq.reset()
        self._logged_hello = None
        self._logged_open_error = None
        with self._lock:
            self._link = link
            self._hello = None
            self._refused = None
            if self._ever_opened:
                self._stats.reconnects += 1
        log.info(
            "%s serial master %s; waiting for HELLO", "re-opened" if self._ever_opened else "opened", port
        )
        self._ever_opened = True

    def _open_failed(self, exc: DeviceConnectionError) -> None:
        text = str(exc)
        with self._lock:
            self._down = text
        if text != self._logged_open_error:  # once per outage and cause, not every reconnect_s
            log.warning("%s; retrying every %.2f s", text, self.cfg.reconnect_s)
            self._logged_open_error = text

    def _drop(self, reason: str) -> None:
        with self._lock:
            link, self._link = self._link, None
            self._latest = None
            self._down = reason
            if link is not None:
                self._closed_frames += link.reader.frames
                self._closed_corrupt += link.reader.error_count
        if link is not None:
            link.close()
        log.warning("serial master lost: %s; re-opening every %.2f s", reason, self.cfg.reconnect_s)
        self._logged_open_error = None

    def _handle(self, frame: Frame) -> None:
        t = self._rx_seq
        if t.add(frame.seq) is not NEXT:
            with self._lock:
                self._stats.gaps, self._stats.lost, self._stats.restarts = t.gaps, t.lost, t.restarts
        try:
            msg = decode_message(frame)
        except MessageError as exc:
            self._reject("frame", f"dropped a frame from {self.cfg.port}: {exc}")
            if frame.kind == KIND_HELLO:  # e.g. another protocol version: trust none of its SAMPLEs
                self._refuse(f"HELLO not understood: {exc}")
            return
        if isinstance(msg, Sample):
            self._on_sample(msg)
        elif isinstance(msg, Hello):
            self._on_hello(msg)
        else:
            self._reject(
                "request", f"{self.cfg.port} sent HELLO_REQUEST, which only a host sends: looped back?"
            )

    def _reject(self, key: str, text: str) -> None:
        with self._lock:
            self._stats.invalid += 1
        now = time.monotonic()
        if now - self._warned.get(key, -math.inf) >= 1.0:  # at most one log line per second and key
            self._warned[key] = now
            log.warning("%s (counted in stats.invalid; repeats within 1 s not logged)", text)

    def _refuse(self, reason: str) -> None:
        """Keep the device invalid until a HELLO that matches the configuration arrives."""
        with self._lock:
            self._refused = reason
            self._hello = None
            self._latest = None
        if reason != self._logged_hello:  # once per connection and reason, not every second
            log.error("refusing the board on %s: %s; its readings stay invalid", self.cfg.port, reason)
            self._logged_hello = reason

    def _on_hello(self, hello: Hello) -> None:
        try:
            self._cal.check_hello(hello)
        except MessageError as exc:
            self._refuse(str(exc))
            return
        with self._lock:
            self._refused = None
            self._hello = hello
        text = (
            f"board on {self.cfg.port}: {hello.model} fw {hello.fw}, {hello.joints} joints, "
            f"{hello.encoders} encoders, {hello.counts_per_rev} counts/rev, {hello.rate_hz} Hz"
        )
        if text != self._logged_hello:
            log.info("%s", text)
            self._logged_hello = text

    def _on_sample(self, sample: Sample) -> None:
        if self._refused is not None:
            with self._lock:
                self._stats.refused += 1
            return
        try:
            reading = self._cal.convert(sample)
        except MessageError as exc:
            self._reject("sample", f"dropped a SAMPLE from {self.cfg.port}: {exc}")
            return
        now = time.monotonic()
        with self._lock:
            self._latest = reading
            self._latest_at = now
            self._stats.samples += 1
