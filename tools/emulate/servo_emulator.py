"""Joint-servo controller emulator: a slave arm's controller speaking :mod:`telesurg.shared.servo_protocol`.

:class:`ServoEmulator` behaves like the reference firmware (``firmware/servo_controller``) in front
of a robot of :mod:`telesurg.shared.robots` (``mh3f``, ``plas``, ``vip``: every joint of every arm, limits
and speed limits from the profiles, start at the profiles' home pose):

* a HELLO at start and on HELLO_REQUEST, a STATE every ``1 / rate_hz`` s;
* per-joint servo dynamics: each joint moves toward its target with a first-order lag
  (time constant ``lag_ms``) and never faster than its speed limit; the "current" is
  proportional to the position error (2 A/rad, clipped at ±3 A);
* its own watchdog: once a SETPOINT has been applied, if no newer one arrives within its
  ``timeout_ms``, every joint holds where it is, ``watchdog_tripped`` is set, the controller
  disables, and "watchdog tripped" is logged (stderr) — until the next ENABLE;
* injectable faults, timed from the first ENABLE (when a host has taken control):
  ``fault_at`` raises a fault bit (``fault``: overcurrent, e-stop, …; latched, the joints stop),
  ``stall_at`` freezes joint ``stall_joint`` where it is (no fault bit: a stuck or slipping
  joint only a shadow model can notice), ``silence_at`` stops every frame the controller writes
  for ``silence_for`` s (0: for good; it still listens), ``garbage_every`` writes 1-16 random
  bytes after every N-th STATE, ``drop_every`` skips every N-th STATE (its frame seq used up: the
  host sees a gap).

It writes to any non-blocking fd — the controller side of a pseudo-terminal in :func:`run_pty`
(``telesurg device emulate-slave --pty``), or a test's own pty.
"""

from __future__ import annotations

import logging
import random
import threading
import time
from dataclasses import dataclass, field

import numpy as np
from telesurg.shared import robots
from telesurg.shared.errors import MessageError
from telesurg.shared.serial_link import SEQ_MODULUS, frame_seq_tracker
from telesurg.shared.servo_protocol import (
    FAULT_ESTOP,
    FAULT_FOLLOWING,
    FAULT_INTERNAL,
    FAULT_OVERCURRENT,
    FAULT_SETPOINT,
    FAULT_SUPPLY,
    U32_MODULUS,
    Disable,
    Enable,
    Hello,
    HelloRequest,
    ServoMessage,
    ServoRobot,
    Setpoint,
    State,
    decode_message,
    describe_faults,
    encode_message,
    seq_delta32,
)

from .port import DevicePort, pty_device, serve_at

log = logging.getLogger(__name__)

#: ``--fault`` names → fault bits.
FAULTS = {
    "overcurrent": FAULT_OVERCURRENT,
    "estop": FAULT_ESTOP,
    "following": FAULT_FOLLOWING,
    "supply": FAULT_SUPPLY,
    "internal": FAULT_INTERNAL,
}
#: A/rad: emulated motor current per unit of position error; clipped at CURRENT_MAX_A.
CURRENT_PER_RAD = 2.0
CURRENT_MAX_A = 3.0


@dataclass
class ServoEmulatorOptions:
    """What the emulated controller drives and which faults it injects (times: s after the first ENABLE)."""

    model: str = "mh3f"  # robot model, a name in the robot registry (shared/robots.py): mh3f, plas, vip
    rate_hz: float = 200.0  # Hz: STATE rate (and dynamics step)
    lag_ms: float = 20.0  # ms: first-order servo lag time constant
    fault_at: float | None = None  # s: raise `fault` (None: never)
    fault: str = "overcurrent"  # which fault bit (FAULTS)
    stall_joint: int = 0  # 1-based joint that sticks at stall_at (0: none)
    stall_at: float = 0.0  # s
    silence_at: float | None = None  # s: stop writing frames (None: never)
    silence_for: float = 0.0  # s: how long (0: for good)
    garbage_every: int = 0  # after every N-th STATE write 1-16 random bytes (0: never)
    drop_every: int = 0  # skip every N-th STATE, its seq used up: the host sees a gap (0: never)
    seed: int = 0  # random garbage seed
    fw: str = "emulator"  # HELLO firmware version
    home: tuple[float, ...] = field(default_factory=tuple)  # start pose (empty: the profiles' home)

    def validate(self) -> None:
        robots.get(self.model)  # ConfigError (a ValueError) naming the registered robots
        if not 1.0 <= self.rate_hz <= 5000.0:
            raise ValueError(f"rate {self.rate_hz} Hz outside [1, 5000]")
        if not 0.0 <= self.lag_ms <= 10_000.0:
            raise ValueError(f"lag {self.lag_ms} ms outside [0, 10000]")
        if self.fault not in FAULTS:
            raise ValueError(f"fault {self.fault!r} unknown; valid: {', '.join(FAULTS)}")
        joints = ServoRobot.of(self.model).joints
        if not 0 <= self.stall_joint <= joints:
            raise ValueError(
                f"stall joint {self.stall_joint} outside [1, {joints}] (0: none) for {self.model}"
            )
        for name, t in (
            ("fault_at", self.fault_at),
            ("stall_at", self.stall_at),
            ("silence_at", self.silence_at),
        ):
            if t is not None and t < 0:
                raise ValueError(f"{name}={t} must be >= 0 s")
        if self.silence_for < 0 or self.garbage_every < 0 or self.drop_every < 0:
            raise ValueError("silence_for, garbage_every and drop_every must be >= 0 (0: for good / never)")
        if self.home and len(self.home) != joints:
            raise ValueError(f"home has {len(self.home)} values, {self.model} has {joints} joints")


@dataclass
class ServoEmulatorStats:
    """What the emulator did and received."""

    states: int = 0  # STATEs written
    hellos: int = 0  # HELLOs written
    requests: int = 0  # HELLO_REQUESTs received
    enables: int = 0  # ENABLEs received
    disables: int = 0  # DISABLEs received
    setpoints: int = 0  # SETPOINTs applied
    stale_setpoints: int = 0  # SETPOINTs ignored: not newer than last_seq_applied
    ignored_setpoints: int = 0  # SETPOINTs ignored: controller disabled
    bad_setpoints: int = 0  # SETPOINTs refused (limits, joint count): FAULT_SETPOINT
    watchdog_trips: int = 0
    corrupt: int = 0  # host frames dropped by framing
    invalid: int = 0  # host frames the protocol rejected
    gaps: int = 0  # gaps in the host's frame sequence numbers
    silent_frames: int = 0  # frames not written because of the injected silence
    dropped: int = 0  # STATEs skipped on purpose (drop_every)
    garbage: int = 0  # noise bursts written
    overflow_bytes: int = 0  # bytes discarded because nobody read the pty


class ServoEmulator:
    """An emulated joint-servo controller on ``fd`` (set non-blocking here); see the module doc.

    Not thread-safe: one thread calls :meth:`serve` (or :meth:`step`) at a time; :attr:`q` and
    friends may be read from another thread for tests (numpy copies are atomic enough there).
    """

    def __init__(self, fd: int, opts: ServoEmulatorOptions | None = None) -> None:
        self.opts = opts or ServoEmulatorOptions()
        self.opts.validate()
        self.port = DevicePort(fd)
        self.robot = ServoRobot.of(self.opts.model)
        self.hello: Hello = self.robot.hello(round(self.opts.rate_hz), self.opts.fw)
        n = self.robot.joints
        self.lower, self.upper = np.array(self.robot.lower), np.array(self.robot.upper)
        self.vmax = np.array(self.robot.max_velocity)
        self.q = np.array(self.opts.home or self.robot.home, dtype=float)
        self.qd = np.zeros(n)
        self.current = np.zeros(n)
        self.target = self.q.copy()
        self.enabled = False
        self.fault = 0
        self.watchdog_tripped = False
        self.last_seq_applied = 0
        self.stats = ServoEmulatorStats()
        self.seq = 0
        self._t0 = time.monotonic()
        self._t_last = self._t0
        self._enabled_at: float | None = None  # monotonic s of the first ENABLE (fault timing)
        self._sp_deadline: float | None = None  # watchdog: monotonic s by which a SETPOINT must come
        self._sp_timeout_ms = 0
        self._last_sp_at = 0.0
        self._stalled = False
        self._fault_injected = False
        self._silent_logged = False
        self._host_seq = frame_seq_tracker()  # the host's frame numbers
        self._rng = random.Random(self.opts.seed)

    # ----------------------------------------------------------------- loop

    def serve(self, stop: threading.Event, seconds: float = 0.0) -> None:
        """Run at ``rate_hz`` until ``stop`` is set or ``seconds`` (> 0) have passed."""
        self.send(self.hello)  # at boot
        self.stats.hellos += 1
        serve_at(self.opts.rate_hz, self.step, stop, seconds)

    def step(self) -> None:
        """Read the host's frames, advance the joints, check the watchdog, write one STATE."""
        now = time.monotonic()
        self._read_host(now)
        self._inject(now)
        self._watchdog(now)
        self._move(now - self._t_last)
        self._t_last = now
        t_us = int((now - self._t0) * 1e6) % U32_MODULUS
        state = State(
            t_us,
            tuple(self.q.tolist()),
            tuple(self.qd.tolist()),
            tuple(self.current.tolist()),
            self.fault,
            self.last_seq_applied,
            self.watchdog_tripped,
            self.enabled,
        )
        n = self.stats.states + self.stats.dropped + 1  # this STATE's number, from 1
        if self.opts.drop_every and n % self.opts.drop_every == 0:
            self.seq = (self.seq + 1) % SEQ_MODULUS  # as if lost on the wire
            self.stats.dropped += 1
        else:
            self.send(state)
            self.stats.states += 1
        if self.opts.garbage_every and n % self.opts.garbage_every == 0:
            self._write(self._rng.randbytes(self._rng.randint(1, 16)))
            self.stats.garbage += 1

    def send(self, msg: ServoMessage) -> None:
        """Frame and write ``msg`` (unless silenced: then its seq is used up, nothing written)."""
        wire = encode_message(msg, self.seq)
        self.seq = (self.seq + 1) % SEQ_MODULUS
        if self._silent(time.monotonic()):
            self.stats.silent_frames += 1
            return
        self._write(wire)

    # ----------------------------------------------------------------- internals

    def _since_enable(self, now: float) -> float | None:
        return None if self._enabled_at is None else now - self._enabled_at

    def _silent(self, now: float) -> bool:
        o, t = self.opts, self._since_enable(now)
        if o.silence_at is None or t is None or t < o.silence_at:
            return False
        silent = o.silence_for <= 0 or t < o.silence_at + o.silence_for
        if silent and not self._silent_logged:
            self._silent_logged = True
            how = "for good" if o.silence_for <= 0 else f"for {o.silence_for:g} s"
            log.warning("silent from now on (%s): no frames written", how)
        elif not silent and self._silent_logged:
            self._silent_logged = False
            log.warning("talking again after %g s of silence", o.silence_for)
        return silent

    def _inject(self, now: float) -> None:
        o, t = self.opts, self._since_enable(now)
        if t is None:
            return
        if o.fault_at is not None and not self._fault_injected and t >= o.fault_at:
            self._fault_injected = True
            self._raise_fault(FAULTS[o.fault], "injected")
        if o.stall_joint and not self._stalled and t >= o.stall_at:
            self._stalled = True
            j = o.stall_joint - 1
            log.warning("joint %d (%s) stalled at %+.4f", o.stall_joint, self.robot.joint_names[j], self.q[j])

    def _raise_fault(self, bits: int, why: str) -> None:
        self.fault |= bits
        self.enabled = False
        self.target = self.q.copy()
        self._sp_deadline = None
        log.warning("fault %s (%s): joints stopped at %s", describe_faults(bits), why, _fmt(self.q))

    def _watchdog(self, now: float) -> None:
        if self.enabled and self._sp_deadline is not None and now > self._sp_deadline:
            self.watchdog_tripped = True
            self.enabled = False
            self.target = self.q.copy()
            self._sp_deadline = None
            self.stats.watchdog_trips += 1
            log.warning(
                "watchdog tripped: no SETPOINT for %.0f ms (timeout %d ms); joints stopped at %s",
                (now - self._last_sp_at) * 1e3,
                self._sp_timeout_ms,
                _fmt(self.q),
            )

    def _move(self, dt: float) -> None:
        """First-order lag toward the target, rate-limited; a stalled joint does not move."""
        if dt <= 0:
            return
        err = self.target - self.q
        tau = self.opts.lag_ms / 1e3
        v = err / tau if tau > 0 else err / dt
        v = np.clip(v, -self.vmax, self.vmax)
        step = v * dt
        over = np.abs(step) > np.abs(err)  # never past the target
        step[over] = err[over]
        if self._stalled:
            step[self.opts.stall_joint - 1] = 0.0
        self.q = self.q + step
        self.qd = step / dt
        self.current = np.clip(CURRENT_PER_RAD * (self.target - self.q), -CURRENT_MAX_A, CURRENT_MAX_A)

    def _read_host(self, now: float) -> None:
        before = self.port.reader.error_count
        frames = self.port.read_frames()
        self.stats.corrupt += self.port.reader.error_count - before
        for frame in frames:
            self._host_seq.add(frame.seq)
            self.stats.gaps = self._host_seq.gaps
            try:
                msg = decode_message(frame)
            except MessageError as exc:
                self.stats.invalid += 1
                log.warning("ignored a frame from the host: %s", exc)
                continue
            self._handle(msg, now)

    def _handle(self, msg: ServoMessage, now: float) -> None:
        if isinstance(msg, HelloRequest):
            self.stats.requests += 1
            self._host_seq.reset()  # a (new) host: its frame counter may start anywhere
            self.send(self.hello)
            self.stats.hellos += 1
        elif isinstance(msg, Enable):
            self.stats.enables += 1
            if self._enabled_at is None:
                self._enabled_at = now
            cleared = self.fault & ~self._present_faults()
            self.fault &= ~cleared
            self.watchdog_tripped = False
            self.target = self.q.copy()
            self.last_seq_applied = msg.seq
            self._sp_deadline = None
            self.enabled = not self.fault
            log.info(
                "ENABLE seq %d: %s",
                msg.seq,
                "enabled" if self.enabled else f"still faulted: {describe_faults(self.fault)}",
            )
        elif isinstance(msg, Disable):
            self.stats.disables += 1
            self.enabled = False
            self.target = self.q.copy()
            self._sp_deadline = None
            log.info("DISABLE: joints held at %s", _fmt(self.q))
        elif isinstance(msg, Setpoint):
            self._on_setpoint(msg, now)
        else:
            self.stats.invalid += 1
            log.warning("ignored a %s from the host (a controller sends it)", type(msg).__name__)

    def _present_faults(self) -> int:
        """Fault causes still present (an injected fault is gone once raised)."""
        return 0

    def _on_setpoint(self, sp: Setpoint, now: float) -> None:
        if not self.enabled:
            self.stats.ignored_setpoints += 1
            return
        if seq_delta32(self.last_seq_applied, sp.seq) <= 0:
            self.stats.stale_setpoints += 1
            return
        q = np.array(sp.q)
        if len(q) != self.robot.joints or np.any(q < self.lower) or np.any(q > self.upper):
            self.stats.bad_setpoints += 1
            self._raise_fault(FAULT_SETPOINT, f"SETPOINT seq {sp.seq} outside the limits or {len(q)} joints")
            return
        self.target = q
        self.last_seq_applied = sp.seq
        self._last_sp_at = now
        self._sp_timeout_ms = sp.timeout_ms
        self._sp_deadline = now + sp.timeout_ms / 1e3
        self.stats.setpoints += 1

    def _write(self, data: bytes) -> None:
        self.stats.overflow_bytes += self.port.write(data)


def _fmt(q: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:+.4f}" for v in q) + "]"


def run_pty(opts: ServoEmulatorOptions, stop: threading.Event, seconds: float = 0.0) -> ServoEmulatorStats:
    """Serve on a new pseudo-terminal (its device path printed on stdout) until ``stop``."""
    with pty_device() as (fd, path):
        emulator = ServoEmulator(fd, opts)
        log.info(
            "emulating the %s servo controller (%d joints) on %s: STATE at %.0f Hz, lag %.0f ms",
            opts.model,
            emulator.robot.joints,
            path,
            opts.rate_hz,
            opts.lag_ms,
        )
        emulator.serve(stop, seconds)
        return emulator.stats
