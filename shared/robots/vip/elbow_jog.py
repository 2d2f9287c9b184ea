"""The elbow (null-space) jog: the slave-side motion of an arm whose controlled point hangs from
an elbow (the VIP arms of Jang 2014; :attr:`~telesurg.shared.robots.ArmProfile.elbow`).

Step 2 of the paper's VIP selection ("adjust manually elbow (E) and wrist (W)") needs the elbow
moved off the current VIP line while the instrument stays where the surgeon put it. This motion
source moves the elbow on the forearm sphere about the wrist W, which stays where it was when the
jog started (the commanded joints keep W exactly; :func:`~telesurg.shared.kinematics.elbow.elbow_move`),
at ``jog_speed_mm_s``. The mapping's ``reallocate_vip`` then selects the new VIP from the joints
the slave measures (Steps 3-6), so the new VIP line goes through the moved elbow.

Operator commands on ``slave/<arm>/command`` (operator authority: ``elbow_jog`` starts a motion
and needs the console's confirmation; ``state`` is public, ``stop`` / ``abort`` stop):

* ``elbow_jog axis=x|y|z direction=1|-1 [mm=D]`` — move the elbow along the world (port-frame)
  axis, its part along the forearm dropped, for ``D`` mm (default 20, at most 100) or until
  ``stop``;
* ``elbow_jog axis=midrange [mm=D]`` — move the elbow the way that raises the smallest joint
  margin (Section V-B: joints "in the middle of range of motion as possible"), until no elbow
  move raises it any more (an ``elbow_jog_done`` event says how far it went) or ``D`` mm
  (default 100);
* ``stop`` / ``abort`` — stop the jog; ``state`` — elbow, wrist and the smallest joint margin.

Refused, with the reason: while the arm follows the master (release the clutch first), without a
lease allowing motion, under a latched e-stop, a direction along the forearm, or a first step that
would take a joint past its limit (the reply names the joint). While it runs, the arm core's rules
hold: it moves only under a valid lease (a lost lease stops it for good), and a step the IK cannot
solve within the limits stops it (``motion_stopped`` names the joint). After any jog the master
must engage anew (the core's follow rule).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from telesurg.shared.kinematics.elbow import ElbowChain, elbow_move, limit_margin, midrange_direction, tangent
from telesurg.shared.messages import Command
from telesurg.shared.robots.api import ArmHandle, ArmReading, AttachedSource, MotionError
from telesurg.shared.robots.registry import get

if TYPE_CHECKING:
    from telesurg.shared.robots.api import SlaveSettings
    from telesurg.shared.robots.registry import ArmProfile

#: Operator commands of an arm with an elbow.
COMMANDS = ("state", "elbow_jog", "stop", "abort")
#: Elbow jog axes: world (port-frame) axes, and the mid-range search.
AXES = ("x", "y", "z", "midrange")
AXIS_DEFAULT_MM = 20.0  # mm: an axis jog's travel when no mm= is given
MIDRANGE_DEFAULT_MM = 100.0  # mm: the mid-range search's longest travel
MAX_MM = 100.0  # mm: the longest travel a jog may ask for
#: mm: the mid-range search probes elbow moves this long in 12 directions around the forearm
MIDRANGE_PROBE_MM = 1.0
#: control periods between two mid-range searches (10 ms at 1 kHz: 0.1 mm of travel at 10 mm/s)
MIDRANGE_EVERY = 10
#: mm: a first step this long (or the jog's travel, if shorter) is tried before a jog is accepted:
#: a joint on or near its limit refuses it
TRIAL_MM = 2.0


@dataclass
class _Jog:
    """One running elbow jog (replaced, never mutated across threads without the core's lock)."""

    axis: str
    direction: np.ndarray  # world axis × sign; unused for midrange
    wrist: np.ndarray  # W held, m
    elbow0: np.ndarray  # E at the start, m
    margin0: float
    travel_m: float  # longest travel
    travelled_m: float = 0.0
    heading: np.ndarray | None = None  # midrange: the current direction
    periods: int = 0
    done: str = ""  # why it ended by itself ("" = running)


class ElbowJog(AttachedSource):
    """The elbow jog of one arm (a :class:`~telesurg.services.slave_control.arm.MotionSource`)."""

    def __init__(self, cfg: SlaveSettings, profile: ArmProfile) -> None:
        if profile.elbow is None:
            raise ValueError(f"arm {profile.arm} has no elbow")
        self.cfg, self.profile = cfg, profile
        self.chain: ElbowChain = profile.elbow
        self.speed = get(cfg.model).make_config(cfg.robot).jog_speed_mm_s / 1e3  # m/s
        self.core: ArmHandle | None = None
        self.jog: _Jog | None = None

    # -- MotionSource ---------------------------------------------------------------------------
    @property
    def control_mode(self) -> str:
        return "joint"

    def state_fields(self) -> tuple[float, tuple[float, float, float]]:
        return 0.0, (0.0, 0.0, 0.0)

    def active(self) -> bool:
        return self.jog is not None

    def blocks_following(self) -> str:
        return ""

    def stop(self, reason: str) -> None:
        self.jog = None

    def braking(self, q_cmd: np.ndarray, dt: float, allowed: bool) -> np.ndarray | None:
        return None  # an elbow jog stops where it is

    def measure(self, reading: ArmReading, q_cmd: np.ndarray) -> None:
        return None

    def follow_keepout(self, q_from: np.ndarray, q_to: np.ndarray) -> tuple[np.ndarray, str]:
        """Nothing to clamp: the VIP instrument crosses the abdominal wall only at the port R, by
        its kinematics (the shaft and the elbow E = q3·z3 lie on the line through R, for every
        joint value and every elbow jog); inside, the tissue is the surgical field
        (docs/safety.md, the patient keep-out)."""
        return q_to, ""

    def next(self, q_cmd: np.ndarray, reading: ArmReading, dt: float) -> np.ndarray:
        """The joints of this period: the elbow a speed-limited step further, the wrist held."""
        with self._core.lock:
            jog = self.jog
        if jog is None or jog.done:
            return q_cmd
        step = min(self.speed * dt, jog.travel_m - jog.travelled_m)
        try:
            if jog.axis == "midrange":
                if jog.heading is None or jog.periods % MIDRANGE_EVERY == 0:
                    jog.heading = midrange_direction(self.chain, q_cmd, jog.wrist, MIDRANGE_PROBE_MM / 1e3)
                jog.periods += 1
                if jog.heading is None:
                    jog.done = "no elbow move raises the smallest joint margin any more"
                    return q_cmd
                d = jog.heading
            else:
                d = tangent(self.chain, q_cmd, jog.wrist, jog.direction)
            q = elbow_move(self.chain, q_cmd, jog.wrist, step * d)
        except ValueError as exc:  # IKError / KinematicsError (a JointLimitError names the joint)
            raise MotionError(f"elbow jog {jog.axis}: {exc}") from exc
        jog.travelled_m += step
        if jog.travelled_m >= jog.travel_m - 1e-12:
            jog.done = f"travelled {jog.travel_m * 1e3:.1f} mm"
        return q

    def reached(self, q_out: np.ndarray, reading: ArmReading) -> None:
        core = self._core
        jog = self.jog
        if jog is None or not jog.done:
            return
        with core.lock:
            if self.jog is jog:
                self.jog = None
        E = self.chain.elbow(q_out)
        margin = limit_margin(q_out, self.chain.lower, self.chain.upper)
        core.event(
            "elbow_jog_done",
            f"elbow jog {jog.axis} ended ({jog.done}): elbow moved "
            f"{np.linalg.norm(E - jog.elbow0) * 1e3:.1f} mm, wrist held at ({_mm(jog.wrist)}) mm, "
            f"smallest joint margin {jog.margin0 * 100:.1f} % → {margin * 100:.1f} % of its range",
        )

    def command(self, cmd: Command) -> tuple[bool, str]:
        """Answer one operator command (zenoh thread)."""
        with self._core.lock:
            return self._command(cmd)

    # -- commands (the core's lock held) ---------------------------------------------------------
    def _command(self, cmd: Command) -> tuple[bool, str]:
        core, a = self._core, cmd.arg_map()
        if core.estop and cmd.name not in ("state", "stop", "abort"):
            return False, f"{cmd.name} refused: {core.estop} (reset first)"
        q = core.q_cmd
        if cmd.name == "state":
            E, W = self.chain.elbow(q), self.chain.wrist(q)
            margin = limit_margin(q, self.chain.lower, self.chain.upper)
            what = f"elbow jog {self.jog.axis} running" if self.jog is not None else "no elbow jog"
            follow = "following" if core.ctl.following else core.ctl.reason or "not following"
            return True, (
                f"joint slave, {follow}; {what}; elbow ({_mm(E)}) mm, wrist ({_mm(W)}) mm; smallest "
                f"joint margin {margin * 100:.1f} % of its range"
            )
        if cmd.name in ("stop", "abort"):
            if self.jog is None:
                return True, "no elbow jog running"
            self.jog = None
            return True, "elbow jog stopped"
        if cmd.name != "elbow_jog":
            return False, f"unknown command {cmd.name!r}; valid: {', '.join(COMMANDS)}"
        axis = a.get("axis", "")
        if axis not in AXES:
            return False, f"elbow_jog refused: axis {axis!r} not supported; valid: {', '.join(AXES)}"
        try:
            sign = int(a.get("direction", "1"))
            mm = float(a.get("mm", MIDRANGE_DEFAULT_MM if axis == "midrange" else AXIS_DEFAULT_MM))
        except ValueError:
            return False, "elbow_jog refused: direction must be 1 or -1 and mm a number"
        if sign not in (1, -1):
            return False, f"elbow_jog refused: direction {sign} must be 1 or -1"
        if not (math.isfinite(mm) and 0.0 < mm <= MAX_MM):
            return False, f"elbow_jog refused: mm={mm:g} outside (0, {MAX_MM:g}]"
        if core.ctl.following:
            return False, "elbow_jog refused: the arm follows the master (release the clutch first)"
        if not core.ctl.lease_valid:
            return False, f"elbow_jog refused: the slave may not move ({core.ctl.reason or 'no lease'})"
        W = self.chain.wrist(q)
        direction = np.zeros(3)
        if axis != "midrange":
            direction["xyz".index(axis)] = float(sign)
        try:  # a first step: a joint on its limit, or a direction along the forearm, refuses it
            if axis == "midrange":
                heading = midrange_direction(self.chain, q, W, MIDRANGE_PROBE_MM / 1e3)
                if heading is None:
                    margin = limit_margin(q, self.chain.lower, self.chain.upper)
                    return False, (
                        "elbow_jog refused: the joints are as mid-range as this wrist allows "
                        f"(smallest margin {margin * 100:.1f} % of its range)"
                    )
            else:
                heading = tangent(self.chain, q, W, direction)
            elbow_move(self.chain, q, W, min(TRIAL_MM, mm) / 1e3 * heading)
        except ValueError as exc:
            return False, f"elbow_jog refused: {exc}"
        self.jog = _Jog(
            axis,
            direction,
            W,
            self.chain.elbow(q),
            limit_margin(q, self.chain.lower, self.chain.upper),
            mm / 1e3,
        )
        what = "toward mid-range joints" if axis == "midrange" else f"along {'+' if sign > 0 else '-'}{axis}"
        return True, (
            f"elbow jog {what} for at most {mm:g} mm at {self.speed * 1e3:g} mm/s, "
            f"wrist held at ({_mm(W)}) mm"
        )


def _mm(p: np.ndarray) -> str:
    return ", ".join(f"{v * 1e3:.1f}" for v in p)
