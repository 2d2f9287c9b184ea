"""The ``serial`` slave backend: a real arm's joint-servo controller on a serial port.

:class:`SerialBackend` speaks :mod:`~telesurg.shared.servo_protocol` (frames of
:mod:`~telesurg.shared.serial_link`)
behind the same :class:`~telesurg.services.slave_control.backends.SlaveBackend` interface as MuJoCo, so
slave_control's lease and hold logic is the same for both. One control period
(``serial.rate_hz``) is one :meth:`~SerialBackend.step`: read every frame that has arrived, then
write one SETPOINT. No thread: the control loop owns the link.

Safety rules:

* Nothing but HELLO_REQUEST is written until a HELLO reports the expected model, joint count and
  joint limits (:meth:`~telesurg.shared.servo_protocol.ServoRobot.check_hello`). At start a different
  robot, a silent port or a port that cannot be opened is refused with an error naming what is
  wrong (:class:`~telesurg.shared.errors.DeviceConnectionError`: slave_control exits 1).
* Setpoints are limit-checked (clamped into the joint limits) and rate-checked (scaled down
  as a whole to ``serial.speed_fraction`` × the joint speed limits, measured from the previous
  setpoint) before they are written; both clamps are counted and logged
  (:attr:`SerialBackendStats.clipped_limit`, ``clipped_rate``; :attr:`SerialBackend.last_sent`).
* Link loss (no valid STATE for ``serial.stale_ms``, a read/write error), a controller fault bit,
  the controller's watchdog and an unexpected disable make ``read().fault`` non-empty with the
  cause: slave_control holds (:class:`~telesurg.services.slave_control.arm.FaultHold`) and no SETPOINT
  is written. A lost link is re-opened every ``serial.reconnect_s`` with a new handshake; a
  watchdog trip is answered by a new ENABLE after ``serial.reconnect_s``; a controller fault
  stays until the link is re-opened or the controller restarts. Either way the slave moves again
  only after a new engage.

:class:`ShadowedBackend` runs the MuJoCo model beside it (``shadow = true``), fed the setpoints
actually sent, and holds when predicted and measured joints diverge.

Example (the emulator on a pseudo-terminal)::

    telesurg device emulate-slave --pty --model mh3f               # prints /dev/pts/N
    telesurg slave-control --set backend=serial --set serial.port=/dev/pts/N --set shadow=true
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import math
import time
from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np
from telesurg.services.slave_control.backends import MujocoBackend, ShadowDivergence, SlaveReading
from telesurg.shared.errors import ConfigError, DeviceConnectionError, MessageError
from telesurg.shared.limits import limit_step
from telesurg.shared.robots import ArmProfile, arms_of
from telesurg.shared.servo_protocol import (
    ENCODER_KINDS,
    KIND_HELLO,
    MAX_TIMEOUT_MS,
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
    send_message,
    seq_delta32,
)
from telesurg.shared.streams import NEXT

if TYPE_CHECKING:
    from telesurg.services.slave_control import SlaveControlConfig
    from telesurg.shared.serial_link import Frame, SerialLink

log = logging.getLogger(__name__)

#: s between HELLO_REQUESTs while waiting for a HELLO.
HELLO_REQUEST_EVERY_S = 0.5
#: Longest fault text (causes travel in operating_state.reason and events, 512 chars at most).
MAX_CAUSE = 300

#: Connection phases (:attr:`SerialBackend.phase`).
PHASES = ("down", "handshake", "sync", "enabling", "running", "tripped", "faulted", "disabled")


@dataclass
class SerialBackendConfig:
    """slave_control's ``[slave_control.serial]`` table: the joint-servo controller on a serial port."""

    # serial port or pyserial URL: /dev/ttyACM0, /dev/serial/by-id/... (survives re-plugging),
    # /dev/pts/N (telesurg device emulate-slave), socket://host:port
    port: str = ""
    baud: int = 500_000  # bit/s: the firmware's BAUD (pseudo-terminals ignore it)
    rate_hz: float = 100.0  # Hz: control rate = one SETPOINT per period (the loop's rate)
    # ms: sent in every SETPOINT: the controller stops the joints if no newer one comes in time
    timeout_ms: float = 100.0
    stale_ms: float = 100.0  # ms: no valid STATE for this long → link lost: HOLD, re-open
    # ms: wait this long for the HELLO (an Arduino resets when the port opens: ~1.5 s boot)
    handshake_ms: float = 3000.0
    reconnect_s: float = 0.5  # s: re-open a lost port / re-enable after a watchdog trip this often
    # (0, 1]: setpoints are rate-limited to this fraction of the joint speed limits (bring-up: 0.1)
    speed_fraction: float = 1.0
    # false: handshake and read the arm but never ENABLE it (bring-up step 1: the slave holds
    # with that cause, measured_js shows the joints as you move the arm by hand)
    enable: bool = True

    @classmethod
    def from_slave_config(cls, cfg: SlaveControlConfig) -> SerialBackendConfig:
        """The ``serial`` table of a slave_control config."""
        return cfg.serial

    def validate(self) -> None:
        """Raise ConfigError naming the key and its valid range."""
        if not self.port:
            raise ConfigError(
                'backend = "serial" needs serial.port, e.g. /dev/ttyACM0, /dev/serial/by-id/..., '
                "/dev/pts/N (telesurg device emulate-slave)"
            )
        if self.baud <= 0:
            raise ConfigError(f"serial.baud={self.baud} must be > 0 (the firmware's BAUD, e.g. 500000)")
        if not 1.0 <= self.rate_hz <= 1000.0:
            raise ConfigError(f"serial.rate_hz={self.rate_hz} outside [1, 1000] Hz")
        period_ms = 1e3 / self.rate_hz
        if not 2 * period_ms <= self.timeout_ms <= MAX_TIMEOUT_MS:
            raise ConfigError(
                f"serial.timeout_ms={self.timeout_ms} outside [{2 * period_ms:g}, {MAX_TIMEOUT_MS}] ms "
                "(at least two control periods)"
            )
        if not 2 * period_ms <= self.stale_ms <= 10_000.0:
            raise ConfigError(f"serial.stale_ms={self.stale_ms} outside [{2 * period_ms:g}, 10000] ms")
        if not 10.0 <= self.handshake_ms <= 60_000.0:
            raise ConfigError(f"serial.handshake_ms={self.handshake_ms} outside [10, 60000] ms")
        if not 0.01 <= self.reconnect_s <= 60.0:
            raise ConfigError(f"serial.reconnect_s={self.reconnect_s} outside [0.01, 60] s")
        if not 0.0 < self.speed_fraction <= 1.0:
            raise ConfigError(f"serial.speed_fraction={self.speed_fraction} outside (0, 1]")


@dataclass
class SerialBackendStats:
    """Counters since the backend was made (they survive reconnections).

    Attributes:
        frames: frames that passed framing (COBS, CRC, version), every kind.
        corrupt: frames dropped by framing (line noise, a cut cable, a reset mid-frame).
        invalid: well-framed messages the protocol rejected, or a STATE of the wrong joint count.
        gaps / lost: gaps in the controller's frame sequence numbers, frames missing in them.
        restarts: the controller's frame sequence went backwards (a reset).
        states: STATEs accepted.
        setpoints: SETPOINTs written.
        clipped_limit: setpoints with a joint clamped into its limits.
        clipped_rate: setpoints scaled down to the speed limit.
        max_setpoint_lag: largest number of SETPOINTs written but not yet applied, as STATE told.
        reconnects: times the port was opened again after a loss.
        refused: HELLOs that did not match the expected robot.
        link_losses: links lost (silence, read/write error, handshake timeout).
        controller_faults: STATEs that brought a new controller fault.
        watchdog_trips: controller watchdog trips seen.
        enables: ENABLEs written.
    """

    frames: int = 0
    corrupt: int = 0
    invalid: int = 0
    gaps: int = 0
    lost: int = 0
    restarts: int = 0
    states: int = 0
    setpoints: int = 0
    clipped_limit: int = 0
    clipped_rate: int = 0
    max_setpoint_lag: int = 0
    reconnects: int = 0
    refused: int = 0
    link_losses: int = 0
    controller_faults: int = 0
    watchdog_trips: int = 0
    enables: int = 0


class SerialBackend:
    """A slave arm behind a joint-servo controller; a :class:`SlaveBackend` (see the module doc).

    Args:
        cfg: port, rates and timeouts.
        robot: the robot expected behind the port (every joint of the model, in order).
        arms: the model's arm profiles (the tips in :meth:`read`).

    Attributes:
        joint_names: the model's joint names (the controller's joint order).
        dt: control period, s.
        stats: counters.
        hello: the HELLO of the current connection, once accepted.
    """

    def __init__(self, cfg: SerialBackendConfig, robot: ServoRobot, arms: tuple[ArmProfile, ...]) -> None:
        cfg.validate()
        if sum(len(a.model_joints) for a in arms) != robot.joints:
            raise ConfigError(f"arms of {robot.model} have other joints than {list(robot.joint_names)}")
        self.cfg, self.robot, self.arms = cfg, robot, arms
        self.joint_names: tuple[str, ...] = robot.joint_names
        self.dt = 1.0 / cfg.rate_hz
        self.realtime = True  # a real arm: its physics does not wait for the loop
        self.stats = SerialBackendStats()
        self.hello: Hello | None = None
        self._lower = np.array(robot.lower)
        self._upper = np.array(robot.upper)
        self._vmax = np.array(robot.max_velocity) * cfg.speed_fraction
        self._timeout_ms = round(cfg.timeout_ms)
        self._link: SerialLink | None = None
        self._phase = "down"
        self._fault = "not connected"
        self._refusal = ""  # the last HELLO refusal ("" = none)
        self._next_open = 0.0
        self._deadline = 0.0  # end of the handshake / sync / enabling phase, monotonic s
        self._next_request = 0.0
        self._retry_at = 0.0  # tripped: when to ENABLE again
        from telesurg.shared.serial_link import frame_seq_tracker

        self._rx_seq = frame_seq_tracker()  # the controller's frame numbers
        self._state: State | None = None
        self._state_at = 0.0  # monotonic s of the last accepted STATE
        self._t_us_last: int | None = None
        self._t_us_wraps = 0
        self._sp_seq = 0  # setpoint counter (ENABLE and SETPOINT seq), mod 2**32
        self._enable_seq = -1
        self._target: np.ndarray | None = None  # from command()
        self._sent: np.ndarray | None = None  # the last SETPOINT written (rate-limit reference)
        self._ever_opened = False
        self._closed_frames = 0
        self._closed_corrupt = 0
        self._clip_episode = False
        self._hello_again = False  # a HELLO arrived after the handshake (a restart?)
        self._tip_q: np.ndarray | None = None
        self._tip_cache: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None
        self._warned: dict[str, float] = {}
        starts = np.cumsum([0, *(len(a.model_joints) for a in arms)])
        #: each arm's joints in the joint vector, in ``arms`` order
        self.arm_slices = tuple(slice(int(i), int(j)) for i, j in itertools.pairwise(starts))

    # ----------------------------------------------------------------- SlaveBackend

    def __enter__(self) -> SerialBackend:
        """Open the port and complete the handshake (HELLO matched, first STATE, ENABLE applied).

        Raises:
            DeviceConnectionError: the port cannot be opened, the controller is refused (a
                different robot: the message names what differs), or it did not answer within
                ``serial.handshake_ms`` (twice that for the whole start).
        """
        now = time.monotonic()
        self._open(now, raise_errors=True)
        give_up = now + 2.0 * self.cfg.handshake_ms / 1e3
        try:
            while self._phase in ("handshake", "sync", "enabling"):
                if time.monotonic() > give_up:
                    raise DeviceConnectionError(
                        f"controller on {self.cfg.port} did not complete the handshake "
                        f"(stuck in {self._phase}): {self._fault}"
                    )
                time.sleep(0.002)
                self._pump(time.monotonic())
            if self._phase == "down":
                raise DeviceConnectionError(self._refusal or self._fault)
        except BaseException:
            self._close()
            raise
        log.info(
            "controller on %s: %s (fw %r), %d joints, STATE at %d Hz; %s",
            self.cfg.port,
            self.robot.model,
            self.hello.fw if self.hello else "?",
            self.robot.joints,
            self.hello.rate_hz if self.hello else 0,
            self._phase if not self._fault else f"{self._phase}: {self._fault}",
        )
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._link is not None and self._phase in ("running", "enabling", "tripped"):
            with contextlib.suppress(DeviceConnectionError):  # hold where you are (as its watchdog would)
                self._send(Disable())
        self._close()
        s = self.stats
        log.info(
            "serial backend stopped: %d SETPOINTs, %d STATEs, %d frames corrupt, %d invalid, %d gaps "
            "(%d lost), %d reconnects, %d link losses, %d controller faults, %d watchdog trips, "
            "clipped %d (limit) / %d (rate), largest setpoint lag %d",
            s.setpoints,
            s.states,
            s.corrupt,
            s.invalid,
            s.gaps,
            s.lost,
            s.reconnects,
            s.link_losses,
            s.controller_faults,
            s.watchdog_trips,
            s.clipped_limit,
            s.clipped_rate,
            s.max_setpoint_lag,
        )

    def command(self, q: np.ndarray) -> None:
        """Joint targets (rad / m) for the next :meth:`step`; checked there before they are sent."""
        self._target = np.array(q, dtype=float)

    def step(self, n: int = 1) -> None:
        """One exchange: read what the controller sent, then write one SETPOINT (if running).

        ``n``: control periods since the last step (the loop's catch-up); the rate check allows
        ``n`` periods of motion.
        """
        self._pump(time.monotonic())
        if self._phase != "running" or self._target is None or self._sent is None:
            return
        q = self._checked(self._target, max(n, 1))
        if q is None:
            return
        self._sp_seq = (self._sp_seq + 1) % U32_MODULUS
        try:
            self._send(Setpoint(self._sp_seq, tuple(q.tolist()), self._timeout_ms))
        except (DeviceConnectionError, MessageError) as exc:
            self._lose(f"serial link to the controller on {self.cfg.port} lost: {exc}")
            return
        self._sent = q
        self.stats.setpoints += 1

    def read(self) -> SlaveReading:
        """The latest STATE as a reading, with the current fault ("" = none).

        ``effort`` holds the motor currents (A, the controller's ``current``), the tip is the forward
        kinematics of the measured joints, ``external_torque`` is None. Before the first STATE:
        the robot's home pose.
        """
        s = self._state
        if s is None:  # not connected yet: the robot's home, faulted
            q = np.array(self.robot.home)
            qd = cur = np.zeros(len(q))
            t = 0.0
        else:
            q, qd, cur = np.array(s.q), np.array(s.qd), np.array(s.current)
            t = (self._t_us_wraps * U32_MODULUS + s.t_us) / 1e6
        if self._tip_cache is None or self._tip_q is None or not np.array_equal(self._tip_q, q):
            self._tip_q, self._tip_cache = q, self._tips(q)
        tip, quat, sites = self._tip_cache
        return SlaveReading(
            q, qd, cur, tip.copy(), quat.copy(), t, None, None if sites is None else sites.copy(), self._fault
        )

    # ----------------------------------------------------------------- inspection

    @property
    def phase(self) -> str:
        """One of :data:`PHASES`."""
        return self._phase

    @property
    def fault(self) -> str:
        """Why the arm must hold now ("" = running normally)."""
        return self._fault

    @property
    def last_sent(self) -> np.ndarray | None:
        """The joints of the last SETPOINT written (after the clamps), rad / m."""
        return None if self._sent is None else self._sent.copy()

    @property
    def state(self) -> State | None:
        """The last accepted STATE."""
        return self._state

    @property
    def state_age(self) -> float:
        """s since the last STATE was accepted (inf before the first)."""
        return time.monotonic() - self._state_at if self._state is not None else math.inf

    # ----------------------------------------------------------------- internals

    def _tips(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The first arm's controlled point (position, quaternion) and every arm's position, from
        the forward kinematics of the measured joints (``ArmProfile.pose``)."""
        from telesurg.shared.kinematics import quat_from_matrix

        poses = [a.pose(q[s]) for a, s in zip(self.arms, self.arm_slices, strict=True)]
        sites = np.array([t[:3, 3] for t in poses])
        return sites[0].copy(), quat_from_matrix(poses[0][:3, :3]), sites

    def _checked(self, target: np.ndarray, n: int) -> np.ndarray | None:
        """``target`` clamped into the joint limits, then its step from the last setpoint scaled
        to the speed limit; None (nothing sent) if it is not finite."""
        assert self._sent is not None
        if target.shape != self._lower.shape or not np.all(np.isfinite(target)):
            self._warn(
                "target", f"setpoint {target.tolist()} not sent: need {len(self._lower)} finite values"
            )
            return None
        q: np.ndarray = np.clip(target, self._lower, self._upper)
        if np.any(q != target):
            self.stats.clipped_limit += 1
            bad = [
                f"{name} {t:+.4f}→{c:+.4f}"
                for name, t, c in zip(self.joint_names, target, q, strict=True)
                if t != c
            ]
            self._warn("limit", f"setpoint clamped into the joint limits: {', '.join(bad)}")
        want = q - self._sent
        lim = self._vmax * self.dt * n
        if float(np.max(np.abs(want) / lim)) <= 1.0:
            self._clip_episode = False
            return q
        out: np.ndarray = self._sent + limit_step(want, lim)
        self.stats.clipped_rate += 1
        if not self._clip_episode:
            j = int(np.argmax(np.abs(want) / self._vmax))
            self._warn(
                "rate",
                f"setpoint rate-limited to {self.cfg.speed_fraction:g} × the speed limits: "
                f"{self.joint_names[j]} asked {want[j] / (self.dt * n):+.3f}/s, limit {self._vmax[j]:.3f}/s",
            )
        self._clip_episode = True
        return out

    def _warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        if now - self._warned.get(key, -math.inf) >= 1.0:  # at most one line per second and key
            self._warned[key] = now
            log.warning("%s (repeats within 1 s not logged)", text)

    def _send(self, msg: ServoMessage) -> None:
        if self._link is None:
            raise DeviceConnectionError(f"serial port {self.cfg.port!r} is not open")
        send_message(self._link, msg)

    def _set_fault(self, cause: str) -> None:
        cause = cause[:MAX_CAUSE]
        if cause != self._fault:
            if cause:
                log.warning("%s", cause)
            else:
                log.info("controller on %s running", self.cfg.port)
        self._fault = cause

    def _open(self, now: float, *, raise_errors: bool = False) -> None:
        from telesurg.shared.serial_link import SerialLink

        try:
            link = SerialLink(self.cfg.port, baudrate=self.cfg.baud)
        except DeviceConnectionError as exc:
            self._next_open = now + self.cfg.reconnect_s
            if raise_errors:
                raise
            self._set_fault(f"controller port: {exc}; retrying every {self.cfg.reconnect_s:g} s")
            return
        self._link = link
        self._rx_seq.reset()
        self._t_us_last = None
        if self._ever_opened:
            self.stats.reconnects += 1
        self._ever_opened = True
        self._phase = "handshake"
        self._deadline = now + self.cfg.handshake_ms / 1e3
        self._next_request = now
        self._pump_handshake(now)

    def _close(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            self._closed_frames += link.reader.frames
            self._closed_corrupt += link.reader.error_count
            link.close()

    def _lose(self, cause: str, now: float | None = None) -> None:
        """Close the link, hold with ``cause``, re-open after ``reconnect_s``."""
        if self._phase != "down":
            self.stats.link_losses += 1
        self._close()
        self._phase = "down"
        self._sent = None
        self._next_open = (time.monotonic() if now is None else now) + self.cfg.reconnect_s
        self._set_fault(cause)

    def _pump(self, now: float) -> None:
        """Read and handle every frame, run the phase's timers, re-open a lost link when due."""
        link = self._link
        if link is None:
            if now >= self._next_open:
                self._open(now)
            return
        try:
            frames = link.poll()
        except DeviceConnectionError as exc:
            self._lose(f"serial link to the controller on {self.cfg.port} lost: {exc}", now)
            return
        for frame in frames:
            self._handle(frame, now)
            if self._link is None:
                return
        self.stats.frames = self._closed_frames + link.reader.frames
        self.stats.corrupt = self._closed_corrupt + link.reader.error_count
        phase = self._phase
        if phase == "handshake":
            self._pump_handshake(now)
        elif phase in ("sync", "enabling"):
            if now > self._deadline:
                what = "no STATE" if phase == "sync" else "ENABLE not applied"
                self._lose(
                    f"controller on {self.cfg.port}: {what} within {self.cfg.handshake_ms:.0f} ms "
                    f"({self._fault}); re-opening",
                    now,
                )
        else:
            age = now - self._state_at
            if age * 1e3 > self.cfg.stale_ms:
                self._lose(
                    f"serial link lost: no valid STATE from the controller on {self.cfg.port} "
                    f"for {age * 1e3:.0f} ms (limit {self.cfg.stale_ms:.0f} ms)",
                    now,
                )
            elif phase == "tripped" and now >= self._retry_at:
                self._send_enable(now)

    def _pump_handshake(self, now: float) -> None:
        if now > self._deadline:
            self._lose(
                f"no HELLO from the controller on {self.cfg.port} within {self.cfg.handshake_ms:.0f} ms: "
                f"is a servo controller there, powered, at {self.cfg.baud} bit/s?",
                now,
            )
            return
        if now >= self._next_request:
            self._next_request = now + HELLO_REQUEST_EVERY_S
            try:
                self._send(HelloRequest())
            except DeviceConnectionError as exc:
                self._lose(f"serial link to the controller on {self.cfg.port} lost: {exc}", now)

    def _handle(self, frame: Frame, now: float) -> None:
        t, s = self._rx_seq, self.stats
        if t.add(frame.seq) is not NEXT:
            s.gaps, s.lost, s.restarts = t.gaps, t.lost, t.restarts
        try:
            msg = decode_message(frame)
        except MessageError as exc:
            self.stats.invalid += 1
            if self._phase == "handshake" and (frame.kind == KIND_HELLO or frame.kind in ENCODER_KINDS):
                self._refuse(f"HELLO not understood: {exc}", now)  # another protocol or version
                return
            self._warn("invalid", f"dropped a frame from {self.cfg.port}: {exc}")
            return
        if isinstance(msg, Hello):
            self._on_hello(msg, now)
        elif isinstance(msg, State):
            self._on_state(msg, now)
        else:
            self.stats.invalid += 1
            self._warn(
                "host-msg",
                f"{self.cfg.port} sent {type(msg).__name__}, which only a host sends: looped back?",
            )

    def _refuse(self, why: str, now: float) -> None:
        self.stats.refused += 1
        self._refusal = f"refused the controller on {self.cfg.port}: {why}"
        self._lose(self._refusal, now)

    def _on_hello(self, hello: Hello, now: float) -> None:
        try:
            self.robot.check_hello(hello)
        except MessageError as exc:
            self._refuse(str(exc), now)
            return
        self._refusal = ""
        self.hello = hello
        if self._phase != "handshake":
            # A second HELLO: the answer to an earlier HELLO_REQUEST, or the controller restarted
            # (its boot HELLO). A restarted controller is disabled with last_seq_applied 0: the
            # next STATE tells (_on_state).
            self._hello_again = True
            return
        ctl_vmax = np.array(hello.max_velocity)
        slower = [
            f"{n} {c:.3g} < {p:.3g}"
            for n, c, p in zip(self.joint_names, ctl_vmax, self.robot.max_velocity, strict=True)
            if c < p
        ]
        if slower:
            log.warning("controller is slower than the %s profile: %s", self.robot.model, ", ".join(slower))
        self._vmax = np.minimum(np.array(self.robot.max_velocity), ctl_vmax) * self.cfg.speed_fraction
        self._phase = "sync"
        self._deadline = now + self.cfg.handshake_ms / 1e3

    def _on_state(self, s: State, now: float) -> None:
        if len(s.q) != self.robot.joints:
            self.stats.invalid += 1
            self._warn("joints", f"STATE with {len(s.q)} joints dropped, expected {self.robot.joints}")
            return
        phase = self._phase
        if phase == "handshake":
            return  # not yet known to be our robot
        self.stats.states += 1
        self._state, self._state_at = s, now
        if self._t_us_last is not None and s.t_us < self._t_us_last:
            self._t_us_wraps += 1
        self._t_us_last = s.t_us
        restarted = self._hello_again and not s.enabled and not s.fault and s.last_seq_applied == 0
        if restarted and phase in ("running", "tripped", "faulted"):
            log.warning("controller on %s restarted (HELLO, then disabled)", self.cfg.port)
            self._hello_again = False
            self._sent = None
            self._set_fault(f"controller on {self.cfg.port} restarted; enabling it again")
            self._send_enable(now)
            return
        if phase == "sync":
            if not self.cfg.enable:
                self._phase = "disabled"
                self._set_fault("controller kept disabled: serial.enable = false (bring-up)")
            else:
                self._send_enable(now)
        elif phase == "enabling":
            if s.last_seq_applied != self._enable_seq:
                return  # a STATE from before the ENABLE
            if s.enabled and not s.fault and not s.watchdog_tripped:
                self._phase = "running"
                self._hello_again = False
                self._sent = np.array(s.q)
                self._target = None  # a command from before the fault must not be sent
                self._set_fault("")
            elif s.fault:
                self._controller_fault(s)
            else:
                self._phase = "faulted"
                self._set_fault(f"controller on {self.cfg.port} did not enable (no fault reported)")
        elif phase == "running":
            lag = seq_delta32(s.last_seq_applied, self._sp_seq)
            if lag < 0:
                self.stats.invalid += 1
                self._warn(
                    "lag", f"controller applied setpoint {s.last_seq_applied}, the host sent {self._sp_seq}"
                )
            self.stats.max_setpoint_lag = max(self.stats.max_setpoint_lag, lag)
            if s.fault:
                self._controller_fault(s)
            elif s.watchdog_tripped:
                self.stats.watchdog_trips += 1
                self._phase = "tripped"
                self._retry_at = now + self.cfg.reconnect_s
                self._set_fault(
                    f"controller watchdog tripped: no SETPOINT within {self._timeout_ms} ms, joints stopped; "
                    f"re-enabling in {self.cfg.reconnect_s:g} s"
                )
            elif not s.enabled:
                self._phase = "faulted"
                self._set_fault("controller disabled itself (its own input or a reset)")

    def _controller_fault(self, s: State) -> None:
        self.stats.controller_faults += 1
        self._phase = "faulted"
        self._set_fault(f"controller fault: {describe_faults(s.fault)}")
        try:
            self._send(Disable())
        except DeviceConnectionError as exc:
            self._lose(f"serial link to the controller on {self.cfg.port} lost: {exc}")

    def _send_enable(self, now: float) -> None:
        self._sp_seq = (self._sp_seq + 1) % U32_MODULUS
        self._enable_seq = self._sp_seq
        try:
            self._send(Enable(self._sp_seq))
        except DeviceConnectionError as exc:
            self._lose(f"serial link to the controller on {self.cfg.port} lost: {exc}", now)
            return
        self.stats.enables += 1
        self._phase = "enabling"
        self._deadline = now + self.cfg.handshake_ms / 1e3


# --------------------------------------------------------------------------- MuJoCo shadow


@dataclass
class ShadowConfig:
    """The ``shadow_*`` keys of slave_control."""

    limit_rad: float = 0.05  # rad / m: divergence limit on any joint
    grace_ms: float = 200.0  # ms: how long it may be exceeded before the hold

    def validate(self) -> None:
        if not 0.0 < self.limit_rad <= 1.0:
            raise ConfigError(f"shadow_limit_rad={self.limit_rad} outside (0, 1]")
        if not 0.0 <= self.grace_ms <= 10_000.0:
            raise ConfigError(f"shadow_grace_ms={self.grace_ms} outside [0, 10000]")


class ShadowedBackend:
    """A real backend with its MuJoCo model running beside it, fed the setpoints actually sent.

    :meth:`read` is the real arm's reading plus ``divergence`` (predicted − measured). When the
    largest joint divergence stays above ``limit_rad`` for longer than ``grace_ms``, the reading's
    ``fault`` becomes ``"shadow divergence …"`` (a stuck or slipping joint; the loop holds) until it
    falls below half the limit. Only fresh measurements (a STATE within the last three control or
    STATE periods) are compared; while the real backend itself is faulted nothing is, and when its
    fault clears the model is put back at the measured joints.
    """

    def __init__(
        self,
        real: SerialBackend,
        sim: MujocoBackend,
        cfg: ShadowConfig,
    ) -> None:
        cfg.validate()
        self.real, self.sim, self.cfg = real, sim, cfg
        self.joint_names = real.joint_names
        self.dt = real.dt
        self.realtime = True
        self.divergence: ShadowDivergence | None = None
        self.max_divergence = 0.0  # largest joint divergence seen while compared, rad / m
        self._idx = np.zeros(0, dtype=int)
        self._ctrl = np.zeros(0)
        self._substeps = 1
        self._over_since: float | None = None
        self._fault = ""
        self._resync = True

    def __enter__(self) -> ShadowedBackend:
        self.sim.__enter__()  # first: compiling the model takes a while, the arm must not wait
        missing = [n for n in self.joint_names if n not in self.sim.joint_names]
        if missing:
            raise ConfigError(f"the MuJoCo shadow has no joints {missing}")
        self._idx = np.array([self.sim.joint_names.index(n) for n in self.joint_names])
        self._substeps = max(1, round(self.real.dt / self.sim.dt))
        self._ctrl = self.sim.read().position.copy()
        try:
            self.real.__enter__()
        except BaseException:
            self.sim.__exit__(None, None, None)
            raise
        self._sync(self.real.read().position)
        log.info(
            "MuJoCo shadow beside the arm: %d steps of %.1f ms per period, limit %.3f rad for %.0f ms",
            self._substeps,
            self.sim.dt * 1e3,
            self.cfg.limit_rad,
            self.cfg.grace_ms,
        )
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            self.sim.__exit__(exc_type, exc, tb)
        finally:
            self.real.__exit__(exc_type, exc, tb)
        log.info("MuJoCo shadow: largest divergence %.4f rad", self.max_divergence)

    def command(self, q: np.ndarray) -> None:
        self.real.command(q)

    def step(self, n: int = 1) -> None:
        self.real.step(n)
        sent = self.real.last_sent
        if sent is not None:
            self._ctrl[self._idx] = sent
            self.sim.command(self._ctrl)
        self.sim.step(n * self._substeps)

    def read(self) -> SlaveReading:
        r = self.real.read()
        if r.fault:
            self._resync, self._over_since, self._fault, self.divergence = True, None, "", None
            return r
        if self._resync:
            self._sync(r.position)
        hello = self.real.hello
        period = max(self.dt, 1.0 / hello.rate_hz if hello else 0.0)
        if self.real.state_age > 3 * period:  # an old measurement: nothing to compare now
            return dataclasses.replace(r, fault=self._fault, divergence=self.divergence)
        pred = self.sim.read().position[self._idx]
        err = np.abs(pred - r.position)
        j = int(np.argmax(err))
        tip = self._tip_distance(pred, r.position)
        div = self.divergence = ShadowDivergence(
            float(err[j]), self.joint_names[j], float(pred[j]), float(r.position[j]), tip
        )
        self.max_divergence = max(self.max_divergence, div.max_rad)
        now = time.monotonic()
        if div.max_rad > self.cfg.limit_rad:
            if self._over_since is None:
                self._over_since = now
            over_ms = (now - self._over_since) * 1e3
            if over_ms > self.cfg.grace_ms and not self._fault:
                self._fault = (
                    f"shadow divergence {div.describe()}: above {self.cfg.limit_rad:g} rad for "
                    f"{over_ms:.0f} ms (a stuck or slipping joint?)"
                )
        else:
            self._over_since = None
            if div.max_rad < 0.5 * self.cfg.limit_rad:
                self._fault = ""
        return dataclasses.replace(r, fault=self._fault, divergence=div)

    def _sync(self, q: np.ndarray) -> None:
        self._ctrl[self._idx] = q
        self.sim.reset(self._ctrl)
        self._resync = False

    def _tip_distance(self, pred: np.ndarray, meas: np.ndarray) -> float:
        d = 0.0
        for a, s in zip(self.real.arms, self.real.arm_slices, strict=True):
            d = max(d, float(np.linalg.norm(a.tip(pred[s]) - a.tip(meas[s]))))
        return d


def make_serial_backend(cfg: SlaveControlConfig) -> SerialBackend | ShadowedBackend:
    """The ``serial`` backend of a slave_control config (with its MuJoCo shadow if ``shadow``)."""
    arms = arms_of(cfg.model, cfg.arm)
    real = SerialBackend(SerialBackendConfig.from_slave_config(cfg), ServoRobot.of(cfg.model, cfg.arm), arms)
    if not cfg.shadow:
        return real
    shadow = ShadowConfig(cfg.shadow_limit_rad, cfg.shadow_grace_ms)
    sites = tuple(a.tip_site for a in arms)
    home = tuple(v for a in arms for v in a.home)
    return ShadowedBackend(real, MujocoBackend(cfg.model, (), sites, home), shadow)
