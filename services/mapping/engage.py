"""The teleop state machine of one master → slave pair, shared by every mapping.

Safety first, the same for the Cartesian and the joint-space mappings:

* An engage needs a *new* pedal press: one seen after a release. A refused engage and any
  disengage the operator did not make himself (slave holding, operator absent, stale master
  stream, a change of the slave's control mode) need the pedal released and pressed again.
* It is refused, with its reason as an ``engage_refused`` event, unless the operator is present,
  the slave's measured joints are fresh and the slave's lease allows it to move.
* Releasing the pedal disengages at once (an operator's disengage: the next press engages).

These rules are a named state machine (the dVRK teleop pattern), one per pair::

    DISABLED  clutch released (or no buttons yet); a press now would be refused: operator
              absent, no fresh slave joints, slave not allowed to move
    IDLE      clutch released, nothing in the way: the next press engages
    ENGAGING  a new press seen; the engage is tried at the next master sample (the references
              are taken from it) → ENABLED, or HOLDING if it is refused
    ENABLED   the slave follows the mapped master
    HOLDING   clutch pressed but not following: a disengage the operator did not make, a
              refused engage, or the pedal was already down at start; release, then press

    DISABLED ⇄ IDLE          the checks of an engage fail / pass (re-judged every 10 ms)
    IDLE/DISABLED → ENGAGING  a press (after a release)
    ENGAGING → ENABLED        the checks pass at the next master sample
    ENGAGING → HOLDING        the checks fail (``engage_refused``)
    ENABLED → IDLE/DISABLED   the clutch is released (``disengage``, the operator's)
    ENABLED → HOLDING         operator absent, slave holding (no lease) or not following (it
                              stopped on its own: a stale setpoint stream, a refused engage),
                              slave mode change, master stale
    HOLDING/ENGAGING → IDLE/DISABLED  the clutch is released

The state, the state before it, the reason and the time of the last change and the scales in
use are published as a :class:`~telesurg.shared.messages.TeleopState` on
``mapping/<slave arm>/teleop_state`` at :data:`STATE_HZ` and on every change, and served to a
late joiner's query at once (a console that starts after the engage shows the truth).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

import numpy as np
from telesurg.shared.messages import (
    Command,
    CommandReply,
    JointState,
    MasterButtons,
    OperatingState,
    Sequencer,
    TeleopState,
    now_ns,
)
from telesurg.shared.teleop.scale import (
    SCALE_COMMANDS,
    WHILE_FOLLOWING,
    follow_step_problem,
    new_scale,
)

if TYPE_CHECKING:
    from telesurg.services.mapping import MappingConfig
    from telesurg.shared.bus import Node, Outlet

log = logging.getLogger(__name__)

DISABLED, IDLE, ENGAGING, ENABLED, HOLDING = "DISABLED", "IDLE", "ENGAGING", "ENABLED", "HOLDING"
#: The slave's reason while it waits, armed, for the engage's first following setpoint.
SLAVE_ARMED = "waiting for engage"
#: ns after an engage during which the slave's not-following states are its start, not a stop: its
#: states stamped later that say it is not following (lease intact) disengage the pair (HOLDING)
SLAVE_START_GRACE_NS = 500_000_000
#: Hz: the teleop state is re-sent this often (and on every change).
STATE_HZ = 10.0
#: After an engage the slave's jaws keep their closure until the master's grip comes within this
#: of it (0 open … 1 closed): an engage never opens the jaws on what they hold, nor snaps them shut.
GRIP_MATCH = 0.1


class EngageGate:
    """The teleop state of one pair and the inputs it is judged on. Thread-safe through
    :attr:`lock`: the ``on_*`` callbacks take it, the underscored methods expect it held.

    Attributes:
        state: one of ``DISABLED``, ``IDLE``, ``ENGAGING``, ``ENABLED``, ``HOLDING`` (module doc).
        previous: the state before the last change.
        reason: why the pair entered :attr:`state`.
        since_ns: wall-clock ns of the last change.
        scale: the operator's motion scale.
        safety_scale: the watchdog's factor on it.
    """

    def __init__(
        self,
        cfg: MappingConfig,
        node: Node,
        master: str,
        slave: str,
        work: threading.Event,
        joint_names: tuple[str, ...],
    ) -> None:
        self.cfg, self.node, self.master, self.slave, self.work = cfg, node, master, slave, work
        self.joint_names = joint_names
        self.lock = threading.Lock()
        self.buttons: MasterButtons | None = None
        self.q_meas: np.ndarray | None = None
        self.q_meas_rx = 0.0
        self.slave_state: OperatingState | None = None
        self.master_rx = 0.0
        self.state = self.previous = DISABLED
        self.reason = "no master buttons yet"
        self.since_ns = now_ns()
        self.scale = cfg.scale  # operator's motion scale (mapping/<arm>/command changes it)
        self.safety_scale = 1.0  # factor from the watchdog's safety state
        # R_ms the strategy maps master motion with, as a quaternion [x, y, z, w] for the teleop
        # state (a haptic master renders the slave's force through it); identity: joint space
        self.rotation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
        self.limit_wall: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # (set by the strategy)
        self.reply_seq = Sequencer(cfg.service)  # replies on mapping/<arm>/command
        self.ik_failures = 0  # samples whose target could not be solved (held)
        self.conflated = 0  # master samples skipped because a newer one had come
        self.clamped = 0  # samples whose target was clamped (workspace or joint limits)
        self._names_warned = False
        # the jaws wait for the master's grip to come to their closure (GRIP_MATCH) after each engage
        self.grip_locked = True
        self.state_out: Outlet = node.outlet(
            node.keys.mapping(slave, "teleop_state"), control=False, latest=True
        )
        self._state_period = 1.0 / STATE_HZ
        self._state_next = 0.0
        with self.lock:
            self._publish_state()

    @property
    def following(self) -> bool:
        """Engaged: the slave follows the mapped master (state ``ENABLED``)."""
        return self.state == ENABLED

    @property
    def want_engage(self) -> bool:
        """A new press arrived that may engage (state ``ENGAGING``; the service loop tries it)."""
        return self.state == ENGAGING

    def grip_command(self) -> float:
        """The jaws' closure to send with the next setpoint: the master's grip while engaged, once
        it has come within :data:`GRIP_MATCH` of the slave's jaws after the engage; -1 (the jaws
        keep theirs) before that, while not engaged, and for an arm without jaws."""
        b, op = self.buttons, self.slave_state
        if self.state != ENABLED or b is None or op is None or op.grip < 0.0:
            return -1.0
        if self.grip_locked:
            if abs(b.grip - op.grip) > GRIP_MATCH:
                return -1.0
            self.grip_locked = False
            self.node.event("grip", f"the jaws follow the grip (at {b.grip:.2f})", arm=self.slave)
        return b.grip

    # -- inputs -----------------------------------------------------------------------
    def on_buttons(self, msg: MasterButtons, key: str) -> None:
        with self.lock:
            first, self.buttons = self.buttons is None, msg
            if not msg.clutch:
                if self.state == ENABLED:
                    self._disengage("clutch released", operator=True)
                elif self.state in (HOLDING, ENGAGING) or first:
                    # (a press and its release in one poll: no engage)
                    self._released("clutch released")
            elif self.state == ENABLED:
                if not msg.operator_present:
                    self._disengage("operator not present")
            elif first:
                self._enter(HOLDING, "clutch pressed at start: release it, then press")
            elif self.state in (IDLE, DISABLED):
                self._enter(ENGAGING, "clutch pressed")

    def on_slave_js(self, msg: JointState, key: str) -> None:
        if msg.names != self.joint_names:
            if not self._names_warned:
                self._names_warned = True
                log.warning(
                    "slave %s joint names %s do not match %s", self.slave, msg.names, self.joint_names
                )
            return
        with self.lock:
            self.q_meas = np.array(msg.position)
            self.q_meas_rx = self.node.received(key)

    def on_slave_state(self, msg: OperatingState, key: str) -> None:
        with self.lock:
            old, self.slave_state = self.slave_state, msg
            if self.following and not msg.lease_ok:
                self._disengage(f"slave holding: {msg.reason or 'no lease'}")
            elif (
                self.following
                and not msg.follow
                and msg.reason not in ("", SLAVE_ARMED)
                and msg.header.stamp_ns > self.since_ns + SLAVE_START_GRACE_NS
            ):
                # the slave stopped following with its lease intact (its setpoint stream went
                # stale, or it refused the engage) and waits for a new press: say so, do not
                # stay ENABLED while the arm stands still
                self._disengage(f"slave not following: {msg.reason}")
            elif self.following and old is not None and old.control_mode != msg.control_mode:
                self._disengage(f"slave control mode {old.control_mode} → {msg.control_mode}")

    def check_timeouts(self) -> None:
        """Disengage on a stale master stream; re-judge IDLE / DISABLED (called every 10 ms from
        the service loop, not right after a stall)."""
        with self.lock:
            now = time.monotonic()
            age_ms = (now - self.master_rx) * 1e3
            if self.following and age_ms > self.cfg.master_timeout_ms:
                self._disengage(f"master stream stale ({age_ms:.0f} ms)")
            elif self.state in (IDLE, DISABLED) and self.buttons is not None:
                self._released("ready to engage" if self.state == DISABLED else self.reason)

    def publish_state(self) -> None:
        """Re-send the teleop state if :data:`STATE_HZ` says it is due (the service loop)."""
        with self.lock:
            if time.monotonic() >= self._state_next:
                self._publish_state()

    # -- rules (lock held) ----------------------------------------------------------------
    def _problem(self) -> str:
        """Why an engage would be refused now ("" if it would go ahead)."""
        b, now = self.buttons, time.monotonic()
        if b is None or not b.operator_present:
            return "operator not present"
        if self.q_meas is None or (now - self.q_meas_rx) * 1e3 > self.cfg.slave_timeout_ms:
            return "no fresh slave joint state"
        if self.slave_state is None or not self.slave_state.lease_ok:
            why = self.slave_state.reason if self.slave_state else "no slave state"
            return f"slave not allowed to move ({why})"
        return ""

    def _may_engage(self) -> bool:
        """Use up the press; True if the engage may go ahead (the caller takes its references and
        calls :meth:`_engaged_now`), else HOLDING and an ``engage_refused`` event."""
        problem = self._problem()
        if problem:
            self.node.event(
                "engage_refused", f"engage refused: {problem}", arm=self.slave, severity="warning"
            )
            self._enter(HOLDING, f"engage refused: {problem}")
        return not problem

    def _engaged_now(self, text: str) -> None:
        """The engage went ahead: ENABLED, and an ``engage`` event with ``text``."""
        self._enter(ENABLED, text)
        self.grip_locked = True
        self.node.event("engage", text, arm=self.slave)

    def _disengage(self, reason: str, *, operator: bool = False) -> None:
        sev = "info" if operator else "warning"
        self.node.event("disengage", f"disengaged: {reason}", arm=self.slave, severity=sev)
        if operator:
            self._released(reason)
        else:
            self._enter(HOLDING, reason)

    def _released(self, reason: str) -> None:
        """Clutch released: IDLE with ``reason``, or DISABLED with what would refuse a press."""
        problem = self._problem()
        if problem:
            self._enter(DISABLED, problem)
        else:
            self._enter(IDLE, reason)

    def _enter(self, state: str, reason: str) -> None:
        """Change to ``state`` (published at once). A new reason within the same state (e.g. the
        slave's hold reason changed while DISABLED) is published too, but keeps ``previous`` and
        ``since_ns``: they say when and from where the state was entered."""
        if state == self.state and reason == self.reason:
            return
        if state != self.state:
            log.info("[%s] teleop %s → %s: %s", self.slave, self.state, state, reason)
            self.previous, self.state = self.state, state
            self.since_ns = now_ns()
        self.reason = reason
        self._publish_state()

    def scale_command(self, cmd: Command, describe: str) -> CommandReply:
        """Answer ``state``, ``scale_up``, ``scale_down``, ``set_scale value=`` (the operator's motion
        scale, :mod:`~telesurg.shared.teleop.scale`) for every mapping mode: a new scale takes
        effect through :meth:`_rescaled` (the mode re-anchors, so it makes no jump) and is
        published in the teleop state at once. ``describe`` leads the ``state`` reply."""
        with self.lock:
            old, ok, reason = self.scale, True, ""
            if cmd.arm != self.slave:
                ok, reason = False, f"{cmd.name} refused: this mapping drives {self.slave}, not {cmd.arm}"
            elif cmd.name == "state":
                reason = (
                    f"{describe}scale {self.scale:.3g} (× safety {self.safety_scale:.3g}); "
                    f"{self.state}: {self.reason}"
                )
            elif cmd.name in SCALE_COMMANDS:
                new, reason = new_scale(cmd.name, cmd.arg_map(), self.scale)
                if new is None or (self.following and (reason := follow_step_problem(self.scale, new))):
                    ok = False
                else:
                    self.scale = new
                    self._rescaled()
                    self._publish_state()
                    reason = f"scale {old:.3g} → {new:.3g}" + (
                        f" {WHILE_FOLLOWING} (re-anchored)" if self.following else ""
                    )
            else:
                ok, reason = False, f"unknown command {cmd.name!r}; valid: state, {', '.join(SCALE_COMMANDS)}"
            seq = self.reply_seq.next()
        if ok and self.scale != old:
            self.node.event("scale", f"motion scale {reason} (operator)", arm=self.slave)
        return CommandReply(seq, self.slave, cmd.name, ok, reason)

    def _rescaled(self) -> None:
        """The operator's scale changed (lock held): re-anchor so the new scale makes no jump."""

    def _publish_state(self) -> None:
        out = self.state_out
        out.put(
            TeleopState(
                out.header(),
                self.master,
                self.slave,
                self.state,
                self.previous,
                self.reason[:200],
                self.since_ns,
                self.scale,
                self.safety_scale,
                self.cfg.mode,
                self.rotation,
                self.limit_wall if self.following else (0.0, 0.0, 0.0, 0.0),
            )
        )
        self._state_next = time.monotonic() + self._state_period
