"""Encoder-board emulator: HELLO and SAMPLE frames of a scripted master on a file descriptor.

:class:`BoardEmulator` speaks :mod:`telesurg.shared.encoder_protocol` exactly like the reference firmware
(``firmware/encoder_board``): a HELLO on start, every ``hello_every_s`` and on HELLO_REQUEST, and a
SAMPLE at ``rate_hz`` generated from a scripted motion of the six master joints through the
default :class:`~telesurg.shared.encoder_protocol.Calibration` (so a host with the default calibration
reads back the scripted joint values to within one count). It writes to any non-blocking fd — the
controller side of a pseudo-terminal in :func:`run_pty` (``telesurg device emulate --pty``), or a
test's own pty — and can inject line noise and dropped frames.

Motions (``t`` in s since the emulator started):

* ``sine`` — joints 2-5 swing ±0.35, ±0.30, ±0.25, ±0.50 rad at 0.20-0.33 Hz, the finger slide
  ±10 mm at 0.4 Hz; joint 1 (a switch on the real device) stays 0 and its switch released;
* ``still`` — every joint at 0.

The pedal is an operator's: released until 1 s after the host opens the port (its HELLO_REQUEST;
an operator presses once the console is there, so the press is seen as one, never as a pedal
already held at start), then pressed, released for 0.3 s every ``clutch_repeat_s`` (5 s: a
re-clutch, as an operator does when the arms hold); the operator is present.
"""

from __future__ import annotations

import logging
import math
import os
import random
import threading
import time
from dataclasses import dataclass, field

from telesurg.shared.encoder_protocol import (
    SW_CLUTCH,
    SW_OPERATOR,
    T_US_MODULUS,
    Calibration,
    Hello,
    HelloRequest,
    Sample,
    decode_message,
    encode_message,
)
from telesurg.shared.errors import MessageError
from telesurg.shared.serial_link import SEQ_MODULUS

from .port import DevicePort, pty_device, serve_at

log = logging.getLogger(__name__)

MOTIONS = ("sine", "still")

# joint (0-based), amplitude (rad / m), frequency (Hz), phase (rad) of the sine motion
_SINE = (  # (joint index, amplitude rad / m, Hz, phase): a calm surgeon's hand, < 0.3 rad/s
    (1, 0.35, 0.10, 0.0),
    (2, 0.30, 0.13, 1.0),
    (3, 0.25, 0.17, 2.0),
    (4, 0.50, 0.08, 3.0),
    (5, 0.010, 0.2, 0.5),
)


def motion_joints(motion: str, t: float, joints: int = 6) -> tuple[float, ...]:
    """Joint values (rad / m) of ``motion`` at ``t`` s."""
    q = [0.0] * joints
    if motion == "sine":
        for j, amp, hz, phase in _SINE:
            if j < joints:
                q[j] = amp * math.sin(2.0 * math.pi * hz * t + phase)
    elif motion != "still":
        raise ValueError(f"motion {motion!r} unknown; valid: {', '.join(MOTIONS)}")
    return tuple(q)


def motion_switches(t: float, clutch_repeat_s: float = 0.0) -> int:
    """``sw`` bits ``t`` s after the host opened the port (negative: not yet): operator present
    always, clutch pressed from 1 s on; with ``clutch_repeat_s`` > 0 the pedal is released for
    0.3 s every that many seconds (re-clutching, as an operator does, e.g. after a hold)."""
    pressed = t >= 1.0
    if pressed and clutch_repeat_s > 0.0 and (t - 1.0) % clutch_repeat_s > clutch_repeat_s - 0.3:
        pressed = False
    return SW_OPERATOR | (SW_CLUTCH if pressed else 0)


@dataclass
class EmulatorOptions:
    """What the emulated board sends."""

    rate_hz: float = 500.0  # Hz: SAMPLE rate
    motion: str = "sine"  # sine | still
    garbage_every: int = 0  # after every N-th SAMPLE write 1-16 random bytes (0: never)
    drop_every: int = 0  # skip every N-th SAMPLE, its seq used up: the host sees a gap (0: never)
    hello_every_s: float = 1.0  # s: periodic HELLO (the firmware's HELLO_PERIOD_MS)
    seed: int = 0  # random garbage seed
    clutch_repeat_s: float = 5.0  # s: if > 0, the clutch is released for 0.3 s every this long
    calibration: Calibration = field(default_factory=Calibration)  # joints → counts / ADC
    model: str = "plas-master"  # HELLO model
    fw: str = "emulator"  # HELLO firmware version

    def validate(self) -> None:
        if not 1.0 <= self.rate_hz <= 5000.0:
            raise ValueError(f"rate {self.rate_hz} Hz outside [1, 5000]")
        if self.motion not in MOTIONS:
            raise ValueError(f"motion {self.motion!r} unknown; valid: {', '.join(MOTIONS)}")
        if self.garbage_every < 0 or self.drop_every < 0:
            raise ValueError("garbage_every and drop_every must be >= 0 (0: off)")
        if self.hello_every_s <= 0:
            raise ValueError("hello_every_s must be > 0")


@dataclass
class EmulatorStats:
    """What the emulator did."""

    samples: int = 0  # SAMPLEs written
    hellos: int = 0  # HELLOs written
    dropped: int = 0  # SAMPLEs skipped on purpose (drop_every)
    garbage: int = 0  # noise bursts written (garbage_every)
    requests: int = 0  # HELLO_REQUESTs received
    overflow_bytes: int = 0  # bytes discarded because nobody read the pty


class BoardEmulator:
    """An emulated encoder board writing to ``fd`` (set non-blocking here) and reading from it.

    One frame counter (``seq``) for every frame written, as a real board has. Not thread-safe:
    one thread calls :meth:`serve` (or :meth:`step`) at a time.
    """

    def __init__(self, fd: int, opts: EmulatorOptions | None = None) -> None:
        self.opts = opts or EmulatorOptions()
        self.opts.validate()
        self.port = DevicePort(fd)
        cal = self.opts.calibration
        self.hello = Hello(
            model=self.opts.model,
            fw=self.opts.fw,
            joints=cal.joints,
            encoders=cal.encoders,
            counts_per_rev=cal.counts_per_rev,
            rate_hz=round(self.opts.rate_hz),
        )
        self.stats = EmulatorStats()
        self.seq = 0
        self._t0 = time.monotonic()
        self._host_at: float | None = None  # time.monotonic() of the host's last HELLO_REQUEST
        self._next_hello = 0.0
        self._rng = random.Random(self.opts.seed)

    def serve(self, stop: threading.Event, seconds: float = 0.0) -> None:
        """Send frames at ``rate_hz`` until ``stop`` is set or ``seconds`` (> 0) have passed."""
        serve_at(self.opts.rate_hz, self.step, stop, seconds)

    def step(self) -> None:
        """Answer requests, send a HELLO if due, and one SAMPLE (or its planned drop / noise)."""
        t = time.monotonic() - self._t0
        self._read_requests()
        if t >= self._next_hello:
            self._next_hello = t + self.opts.hello_every_s
            self.send_hello()
        n = self.stats.samples + self.stats.dropped + 1  # this SAMPLE's number, from 1
        cal = self.opts.calibration
        counts, pot = cal.raw(motion_joints(self.opts.motion, t, cal.joints))
        sample = Sample(
            t_us=int(t * 1e6) % T_US_MODULUS,
            counts=counts,
            pot=pot,
            sw=motion_switches(self._operator_s(), self.opts.clutch_repeat_s),
        )
        if self.opts.drop_every and n % self.opts.drop_every == 0:
            self.seq = (self.seq + 1) % SEQ_MODULUS  # as if lost on the wire
            self.stats.dropped += 1
        else:
            self._send(encode_message(sample, self._next_seq()))
            self.stats.samples += 1
        if self.opts.garbage_every and n % self.opts.garbage_every == 0:
            self._send(self._rng.randbytes(self._rng.randint(1, 16)))
            self.stats.garbage += 1

    def _operator_s(self) -> float:
        """s since the host opened the port (its last HELLO_REQUEST); -1 before any."""
        return -1.0 if self._host_at is None else time.monotonic() - self._host_at

    def send_hello(self) -> None:
        self._send(encode_message(self.hello, self._next_seq()))
        self.stats.hellos += 1

    def _next_seq(self) -> int:
        seq = self.seq
        self.seq = (seq + 1) % SEQ_MODULUS
        return seq

    def _read_requests(self) -> None:
        for frame in self.port.read_frames():
            try:
                msg = decode_message(frame)
            except MessageError as exc:
                log.warning("ignored a frame from the host: %s", exc)
                continue
            if isinstance(msg, HelloRequest):  # the host opened the port: the operator sits down
                self.stats.requests += 1
                self._host_at = time.monotonic()
                self.send_hello()
            else:
                log.warning(
                    "ignored a %s from the host (a host only sends HELLO_REQUEST)", type(msg).__name__
                )

    def _send(self, data: bytes) -> None:
        self.stats.overflow_bytes += self.port.write(data)


def run_pty(
    opts: EmulatorOptions, stop: threading.Event, seconds: float = 0.0, link: str = ""
) -> EmulatorStats:
    """Serve on a new pseudo-terminal (its device path printed on stdout) until ``stop``. ``link``:
    a symlink to that path, made at once and removed at the end (a stable name for the host, as
    ``/dev/serial/by-id/…`` is for a real board)."""
    with pty_device() as (fd, path):
        if link:
            tmp = f"{link}.{os.getpid()}.tmp"
            os.symlink(path, tmp)
            os.replace(tmp, link)
        try:
            emulator = BoardEmulator(fd, opts)
            where = f"{path} ({link})" if link else path
            log.info("emulating %s on %s: %.0f Hz, motion %s", opts.model, where, opts.rate_hz, opts.motion)
            emulator.serve(stop, seconds)
            return emulator.stats
        finally:
            if link and os.path.islink(link) and os.readlink(link) == path:
                os.unlink(link)
