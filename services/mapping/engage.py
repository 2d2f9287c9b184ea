"""Clutch, engage and disengage rules of one master → slave pair, shared by every mapping.

Safety first, the same for the Cartesian and the joint-space mappings:

* An engage needs a *new* pedal press: one seen after a release. A refused engage and any
  disengage the operator did not make himself (slave holding, operator absent, stale master
  stream, a change of the slave's control mode) need the pedal released and pressed again.
* It is refused, with its reason as an ``engage_refused`` event, unless the operator is present,
  the slave's measured joints are fresh and the slave's lease allows it to move.
* Releasing the pedal disengages at once (an operator's disengage: the next press engages).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

import numpy as np
from telesurg.shared.messages import JointState, MasterButtons, OperatingState

if TYPE_CHECKING:
    from telesurg.services.mapping import MappingConfig
    from telesurg.shared.bus import Node

log = logging.getLogger(__name__)


class EngageGate:
    """The engage state of one pair and the inputs it is judged on. Thread-safe through
    :attr:`lock`: the ``on_*`` callbacks take it, the underscored methods expect it held.

    Attributes:
        following: engaged (the slave follows the mapped master).
        need_release: the pedal must be released before a press engages.
        want_engage: a press arrived that may engage (the service loop tries it).
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
        self.following = False
        self.need_release = True
        self.want_engage = False
        self.safety_scale = 1.0  # factor from the watchdog's safety state
        self.ik_failures = 0  # samples whose target could not be solved (held)
        self.conflated = 0  # master samples skipped because a newer one had come
        self.clamped = 0  # samples whose target was clamped (workspace or joint limits)
        self._names_warned = False

    # -- inputs -----------------------------------------------------------------------
    def on_buttons(self, msg: MasterButtons, key: str) -> None:
        with self.lock:
            self.buttons = msg
            if not msg.clutch:
                self.need_release = False
                self.want_engage = False  # a press and its release in one poll: no engage
                if self.following:
                    self._disengage("clutch released", operator=True)
            elif not msg.operator_present and self.following:
                self._disengage("operator not present")
            elif not self.following and not self.need_release:
                self.want_engage = True

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
            elif self.following and old is not None and old.control_mode != msg.control_mode:
                self._disengage(f"slave control mode {old.control_mode} → {msg.control_mode}")

    def check_timeouts(self) -> None:
        """Disengage on a stale master stream (called at a low rate from the service loop)."""
        with self.lock:
            age_ms = (time.monotonic() - self.master_rx) * 1e3
            if self.following and age_ms > self.cfg.master_timeout_ms:
                self._disengage(f"master stream stale ({age_ms:.0f} ms)")

    # -- rules (lock held) ----------------------------------------------------------------
    def _may_engage(self) -> bool:
        """Use up the press; True if the engage may go ahead, else an ``engage_refused`` event."""
        self.want_engage = False
        self.need_release = True  # whatever happens, the next try needs a new press
        b, now = self.buttons, time.monotonic()
        problem = ""
        if b is None or not b.operator_present:
            problem = "operator not present"
        elif self.q_meas is None or (now - self.q_meas_rx) * 1e3 > self.cfg.slave_timeout_ms:
            problem = "no fresh slave joint state"
        elif self.slave_state is None or not self.slave_state.lease_ok:
            why = self.slave_state.reason if self.slave_state else "no slave state"
            problem = f"slave not allowed to move ({why})"
        if problem:
            self.node.event(
                "engage_refused", f"engage refused: {problem}", arm=self.slave, severity="warning"
            )
        return not problem

    def _disengage(self, reason: str, *, operator: bool = False) -> None:
        self.following = False
        self.need_release = not operator
        sev = "info" if operator else "warning"
        self.node.event("disengage", f"disengaged: {reason}", arm=self.slave, severity=sev)
