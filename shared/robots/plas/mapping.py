"""PLAS all-joints mapping (``mode = "all_joints"``, Shim 2015): master joints → slave joints.

Master ``measured_js`` increments become slave joint increments, integrated per sample
(:func:`telesurg.shared.robots.plas.kinematics.map_step`, Table-6 factors or the tip-exact
alternative, the robot knob ``all_joints_mode``); the master's joint 1 is the on/off switch driving
slave d1 at ``d1_speed_mm_s``; joint limits clamp and report (one event per clamping episode).
"""

from __future__ import annotations

import time

import numpy as np
from telesurg.shared.errors import KinematicsError
from telesurg.shared.messages import JointState, Message
from telesurg.shared.robots.api import PairContext
from telesurg.shared.robots.joint_mapping import JointStrategy
from telesurg.shared.robots.registry import get


class AllJointsMapping(JointStrategy):
    """Master joints → slave joints by the Table-6 factors (see the module docstring)."""

    MASTER_INPUT: tuple[str, type[Message]] = ("measured_js", JointState)  # the master stream it maps

    def __init__(self, gate: PairContext) -> None:
        from telesurg.shared.robots.plas import kinematics as plas

        super().__init__(gate)
        self.plas = plas
        rcfg = get(gate.cfg.model).make_config(gate.cfg.robot)
        self.config = plas.MappingConfig(mode=rcfg.all_joints_mode, d1_speed=rcfg.d1_speed_mm_s / 1e3)
        self.pending: JointState | None = None
        self.qm_prev: np.ndarray | None = None
        self.t_prev = 0

    def on_master(self, msg: JointState, key: str) -> None:
        if len(msg.position) != 6:
            return
        with self.gate.lock:
            if self.pending is not None:
                self.gate.conflated += 1
            self.pending = msg
            self.gate.master_rx = time.monotonic()
        self.gate.work.set()

    def _engaged(self) -> None:
        self.qm_prev = None

    def process(self) -> None:
        with self.gate.lock:
            msg, self.pending = self.pending, None
            if self.gate.want_engage and not self.gate.following:
                self._try_engage()
            if msg is None:
                return
            qm = np.array(msg.position)
            if self.gate.following and self.q_cmd is not None:
                if self.qm_prev is not None:
                    dt = min(max((msg.header.stamp_ns - self.t_prev) / 1e9, 0.0), 0.1)
                    switch = 1 if qm[0] >= 0.5 else 0
                    dq = (qm - self.qm_prev) * self.gate.safety_scale
                    try:
                        step = self.plas.map_step(
                            self.q_cmd,
                            self.qm_prev,
                            dq,
                            dt=dt * self.gate.safety_scale,
                            switch=switch,
                            config=self.config,
                        )
                        self.q_cmd = step.q
                        self._report_clamp(step.clamped)
                    except KinematicsError as exc:
                        self.gate.ik_failures += 1
                        if self.gate.ik_failures <= 5:
                            self.gate.node.event(
                                "ik_failure", f"holding: {exc}", arm=self.gate.slave, severity="warning"
                            )
                self.qm_prev, self.t_prev = qm, msg.header.stamp_ns
            self._put(msg.header.stamp_ns)
