"""A console-side client of one slave arm: operator commands and what the slave reports.

Used by experiments and process tests the way a console uses the slave: commands go over the
``slave/<arm>/command`` queryable, state comes from ``operating_state``, ``measured_js``,
``measured_cp`` and slave_control's events. Every record carries the local monotonic time, s.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from telesurg.shared.authority import CONFIRM_ARG
from telesurg.shared.bus import Node
from telesurg.shared.messages import (
    CartesianPose,
    CartesianWrench,
    Command,
    CommandReply,
    JointState,
    OperatingState,
    SafetyEvent,
    Sequencer,
)


@dataclass
class ArmLog:
    """What the client has seen (append-only, guarded by ``lock``)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    # (t, control_mode, rcm_error_mm, lease_ok, follow)
    states: list[tuple[float, str, float, bool, bool]] = field(default_factory=list)
    tips: list[tuple[float, float, float, float]] = field(default_factory=list)  # (t, x, y, z) m
    joints: list[tuple[float, tuple[float, ...]]] = field(default_factory=list)  # (t, q) rad
    # the slave's own stamps (header stamp_ns, its wall clock): of each joints sample (same index)
    # and of each operating_state with its control mode — the order the slave measured them in,
    # which a client that was itself stalled receives in bursts, interleaved across the streams
    joint_stamps: list[int] = field(default_factory=list)
    mode_stamps: list[tuple[int, str]] = field(default_factory=list)
    forces: list[tuple[float, float, float, float]] = field(default_factory=list)  # (t, fx, fy, fz) N
    events: list[tuple[float, str, str]] = field(default_factory=list)  # (t, kind, text)
    replies: list[tuple[float, str, bool, str]] = field(default_factory=list)  # (t, name, ok, reason)


class ArmClient:
    """Commands and observations of one arm over an open :class:`~telesurg.shared.bus.Node`."""

    def __init__(self, node: Node, arm: str = "arm1", *, verbose: bool = False) -> None:
        """``node``: the commands go out as its service id — open it as the operator console
        (``console``: only it may command the arm, shared/authority.py). The client confirms
        motion-starting commands itself (``send(..., confirm=True)``), as an operator who answers
        yes."""
        self.node, self.arm, self.verbose = node, arm, verbose
        k = node.keys
        self.key = k.command(arm)
        self.out = node.outlet(self.key, control=False)
        self._seq = Sequencer(node.service)
        self.log = ArmLog()
        node.subscribe(k.slave(arm, "operating_state"), OperatingState, self._on_state)
        node.subscribe(k.slave(arm, "measured_cp"), CartesianPose, self._on_tip)
        node.subscribe(k.slave(arm, "measured_js"), JointState, self._on_js)
        node.subscribe(k.slave(arm, "measured_cf"), CartesianWrench, self._on_cf)
        node.subscribe(k.events("slave_control"), SafetyEvent, self._on_event)

    # -- inputs (zenoh threads)
    def _on_state(self, m: OperatingState, key: str) -> None:
        with self.log.lock:
            self.log.states.append((time.monotonic(), m.control_mode, m.rcm_error_mm, m.lease_ok, m.follow))
            self.log.mode_stamps.append((m.header.stamp_ns, m.control_mode))

    def _on_tip(self, m: CartesianPose, key: str) -> None:
        p = m.position
        with self.log.lock:
            self.log.tips.append((time.monotonic(), float(p[0]), float(p[1]), float(p[2])))

    def _on_cf(self, m: CartesianWrench, key: str) -> None:
        with self.log.lock:
            self.log.forces.append((time.monotonic(), *m.force))

    def _on_js(self, m: JointState, key: str) -> None:
        with self.log.lock:
            self.log.joints.append((time.monotonic(), tuple(m.position)))
            self.log.joint_stamps.append(m.header.stamp_ns)

    def _on_event(self, m: SafetyEvent, key: str) -> None:
        if m.arm not in ("", self.arm):
            return
        with self.log.lock:
            self.log.events.append((time.monotonic(), m.kind, m.text))

    # -- commands
    def send(self, name: str, *args: str, timeout: float = 5.0, confirm: bool = True) -> CommandReply:
        """Send one command and return the reply (raises TimeoutError without one, MessageError
        when the authority refuses it). ``confirm``: answer a ``confirm required`` reply by sending
        the command again with its token (else that reply is returned)."""
        r = self.node.request(
            self.key, Command(self._seq.next(), self.arm, name, args), CommandReply, timeout
        )
        if confirm and r.confirm:
            r = self.node.request(
                self.key,
                Command(self._seq.next(), self.arm, name, (*args, f"{CONFIRM_ARG}={r.confirm}")),
                CommandReply,
                timeout,
            )
        with self.log.lock:
            self.log.replies.append((time.monotonic(), name, r.accepted, r.reason))
        if self.verbose:
            print(f"{name} {' '.join(args)} -> {'accepted' if r.accepted else 'REFUSED'}: {r.reason}")
        return r

    def must(self, name: str, *args: str) -> CommandReply:
        """Send a command that must be accepted (raises RuntimeError with the reason if refused)."""
        r = self.send(name, *args)
        if not r.accepted:
            raise RuntimeError(f"{name} {' '.join(args)} refused: {r.reason}")
        return r

    # -- views
    def mode(self) -> str:
        with self.log.lock:
            return self.log.states[-1][1] if self.log.states else ""

    def lease_ok(self) -> bool:
        with self.log.lock:
            return bool(self.log.states) and self.log.states[-1][3]

    def tip(self) -> np.ndarray:
        """Latest measured tip, m."""
        with self.log.lock:
            return np.array(self.log.tips[-1][1:]) if self.log.tips else np.full(3, np.nan)

    def q(self) -> np.ndarray:
        """Latest measured joints, rad."""
        with self.log.lock:
            return np.array(self.log.joints[-1][1]) if self.log.joints else np.full(6, np.nan)

    def events_of(self, kind: str, since: float = 0.0) -> list[str]:
        with self.log.lock:
            return [text for t, k, text in self.log.events if k == kind and t >= since]

    def transitions(self) -> list[str]:
        return [t.split(":")[0] for t in self.events_of("mode_transition")]

    def wait(self, pred: Callable[[], bool], timeout: float) -> bool:
        """Poll ``pred()`` every 20 ms until true (True) or ``timeout`` s (False)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred():
                return True
            time.sleep(0.02)
        return False

    def wait_event(self, kind: str, since: float, timeout: float) -> bool:
        return self.wait(lambda: bool(self.events_of(kind, since)), timeout)

    def settle(self, tol_m: float = 2e-5, window_s: float = 0.2, timeout: float = 5.0) -> np.ndarray:
        """Wait until the tip moved less than ``tol_m`` over ``window_s``; returns the tip, m."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            time.sleep(window_s / 2)
            now = time.monotonic()
            with self.log.lock:
                recent = [p[1:] for p in self.log.tips if p[0] >= now - window_s]
            if len(recent) >= 5 and float(np.ptp(np.array(recent), axis=0).max()) < tol_m:
                return np.array(recent[-1])
        return self.tip()
