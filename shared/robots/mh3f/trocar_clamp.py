"""Trocar-mode master–slave in the Cartesian mapping: the nearest feasible target, said in events.

In trocar mode the mapping solves the trocar IK (the forceps pivots about the trocar). A master
target beyond the arm's reach, its joint limits, the insertion depth range or, within one master
sample, its joint speeds (Jinno 2014, Table 1) is not held: it is brought to the nearest feasible
target by :func:`~telesurg.shared.robots.mh3f.trocar_limits.clamped_trocar_ik` (the RCM stays
exact), and each clamping episode is an event ``trocar_clamped`` saying what was clamped and by
how much, with another when the target is feasible again.
"""

from __future__ import annotations

import numpy as np
from telesurg.shared.bus import Node
from telesurg.shared.robots.mh3f.kinematics import ArmGeometry
from telesurg.shared.robots.mh3f.trocar_limits import ClampedTarget, clamped_trocar_ik

FIRST_DT_S = 0.004  # s: the engage sample has no predecessor; one 250 Hz period
QUIET_SAMPLES = 50  # an episode ends after this many unclamped samples (no event per jitter blip)
MAX_DT_S = 0.012  # s: a longer gap between master samples counts as this much for the speed
# limit (a slave interpolating a larger step linearly in joint space would leave the RCM)


class TrocarClamp:
    """Per-pair state: the master clock of the last sample and the current clamping episode."""

    def __init__(self, node: Node, slave: str, geom: ArmGeometry, depth_mm: tuple[float, float]) -> None:
        self.node, self.slave, self.geom = node, slave, geom
        self.min_depth, self.max_depth = depth_mm[0] / 1e3, depth_mm[1] / 1e3
        self.last_stamp_ns: int | None = None
        self.fresh = True  # the next sample is the first of an engagement
        self.quiet = 0  # unclamped samples since the last clamped one
        self.episode: tuple[str, ...] = ()
        self.samples = 0  # samples clamped in the current episode
        self.clamped_total = 0  # samples clamped since start

    def reset(self, stamp_ns: int) -> None:
        """A new engagement: the master clock starts at ``stamp_ns``."""
        self.last_stamp_ns = stamp_ns
        self.fresh = True
        self.episode = ()
        self.samples = 0

    def solve(self, tip: np.ndarray, trocar: np.ndarray, q_last: np.ndarray, stamp_ns: int) -> ClampedTarget:
        """The joints for this master sample (``stamp_ns``: its master-clock stamp)."""
        if self.last_stamp_ns is None or self.fresh:  # the engage sample: one nominal period
            dt = FIRST_DT_S
        else:
            dt = min(max((stamp_ns - self.last_stamp_ns) * 1e-9, 0.0), MAX_DT_S)
        self.fresh = False
        r = clamped_trocar_ik(
            tip, trocar, q_last, dt, self.geom, min_depth=self.min_depth, max_depth=self.max_depth
        )
        self.last_stamp_ns = stamp_ns
        if r.clamped:
            self.samples += 1
            self.clamped_total += 1
            if not self.episode or any(k not in self.episode for k in r.clamped):
                self.episode = tuple(sorted(set(self.episode) | set(r.clamped)))
                self.node.event(
                    "trocar_clamped",
                    f"trocar-mode target clamped ({', '.join(r.clamped)}): {r.detail}"[:480],
                    arm=self.slave,
                    severity="warning",
                )
            self.quiet = 0
            return r
        if not self.episode:
            return r
        self.quiet += 1
        if self.quiet >= QUIET_SAMPLES:
            self.node.event(
                "trocar_clamped",
                f"trocar-mode target feasible again ({self.samples} samples clamped in the episode) "
                f"({', '.join(self.episode)})",
                arm=self.slave,
            )
            self.episode = ()
            self.samples = 0
        return r
