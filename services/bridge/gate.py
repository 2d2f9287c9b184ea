"""What the bridge lets through from a ROS 2 console: the checks of every inbound command and the
console's engage state. No I/O (the bridge, :mod:`telesurg.services.bridge.ros2`, calls these).

**Checks** (:func:`check_joints`, :func:`check_pose`): a ``servo_jp`` must carry exactly the arm's
joint count, the arm's joint names in its order (or no names: positional), finite positions
inside the joint limits and — while engaged — no more than ``max_step_rad`` from the previous
forwarded setpoint; a ``servo_cp`` a finite position, a unit quaternion and the ``base`` frame
(or none), and an IK solution. Anything else raises :class:`Rejected` with the reason; the
bridge counts, logs and drops it (never forwarded).

**Engage** (:class:`Console`, the CRTK ``state_command``): ``enable`` (or ``resume``) engages —
the next forwarded setpoint starts a follow (the slave sees a ``follow`` false → true edge, as
from the mapping's clutch); ``disable`` (or ``pause``) disengages. The console disengages by
itself when its ``servo_jp`` stream goes silent for ``servo_timeout_ms`` or when the slave stops
following (a hold: the operator enables again, as a clutch press after a hold). ``home`` and
anything else are refused with the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from telesurg.shared.errors import TelesurgError
from telesurg.shared.robots import ArmProfile

#: state_command values and what they do; anything else is refused
ENGAGE = ("enable", "resume")
DISENGAGE = ("disable", "pause")
REFUSED = {
    "home": "the arm is homed at start (operating_state is_homed); move it with servo_jp, or with "
    "`telesurg cmd begin_posture_adjust` from the operator console",
    "unhome": "unhoming is not supported",
}
FRAMES = ("", "base")  # servo_cp frame_id: the slave's base frame


class Rejected(TelesurgError):
    """An inbound ROS 2 command that is not forwarded; the message says why."""


def check_joints(
    profile: ArmProfile,
    names: tuple[str, ...],
    position: tuple[float, ...],
    previous: np.ndarray | None = None,
    max_step_rad: float = 0.1,
) -> np.ndarray:
    """The joint setpoint ``position`` as an array, or :class:`Rejected`."""
    n = len(profile.joint_names)
    if len(position) != n:
        raise Rejected(f"wrong joint count: {len(position)} positions, the arm has {n}")
    if names and tuple(names) != profile.joint_names:
        raise Rejected(f"joint names {list(names)} are not the arm's {list(profile.joint_names)}")
    for j, v, lo, hi in zip(profile.joint_names, position, profile.lower, profile.upper, strict=True):
        if not math.isfinite(v):
            raise Rejected(f"joint {j} is not finite ({v})")
        if not lo <= v <= hi:
            raise Rejected(f"joint {j}={v:.4f} outside its limits [{lo:.4f}, {hi:.4f}]")
    q = np.array(position, dtype=np.float64)
    if previous is not None:
        step = float(np.max(np.abs(q - previous)))
        if step > max_step_rad:
            raise Rejected(f"a jump of {step:.3f} from the previous setpoint (limit {max_step_rad:g})")
    return q


def check_pose(
    profile: ArmProfile,
    frame: str,
    position: tuple[float, float, float],
    quat: tuple[float, float, float, float],
    q_near: np.ndarray,
) -> np.ndarray:
    """Joints for the Cartesian setpoint (IK nearest ``q_near``), or :class:`Rejected`."""
    from telesurg.shared.kinematics.transforms import matrix_from_quat

    if frame not in FRAMES:
        raise Rejected(f"servo_cp frame_id {frame!r}; valid: 'base' (or empty)")
    if not all(math.isfinite(v) for v in (*position, *quat)):
        raise Rejected("servo_cp has a non-finite number")
    norm = math.sqrt(sum(v * v for v in quat))
    if abs(norm - 1.0) > 1e-3:
        raise Rejected(f"servo_cp orientation is not a unit quaternion (norm {norm:.4f})")
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(quat)
    T[:3, 3] = position
    try:
        return profile.ik(T, q_near)
    except TelesurgError as exc:
        raise Rejected(f"servo_cp has no IK solution: {exc}") from None


@dataclass
class Console:
    """The ROS 2 console's engage state (one per arm). Times: monotonic s."""

    servo_timeout_s: float = 0.1
    enabled: bool = False
    edge: bool = False  # the next forwarded setpoint must first say follow=false
    last_rx: float | None = None  # last accepted servo command
    slave_followed: bool = False  # the slave followed since the last engage
    notes: list[str] = field(default_factory=list)  # disengages to report (drained by the bridge)

    def command(self, text: str) -> tuple[bool, str]:
        """A ``state_command``: ``(accepted, reason or note)``."""
        word = text.strip().lower()
        if word in ENGAGE:
            self.enabled, self.edge, self.slave_followed = True, True, False
            return True, "engaged: servo_jp / servo_cp are followed under the watchdog's lease"
        if word in DISENGAGE:
            self.enabled = False
            return True, "disengaged: the slave holds"
        if word in REFUSED:
            return False, f"{word}: {REFUSED[word]}"
        valid = ", ".join((*ENGAGE, *DISENGAGE))
        return False, f"unknown state_command {text[:40]!r}; valid: {valid}"

    def present(self, now: float) -> bool:
        """The console's servo stream is fresh."""
        return self.last_rx is not None and now - self.last_rx <= self.servo_timeout_s

    def on_servo(self, now: float) -> tuple[bool, bool]:
        """An accepted servo command arrived: ``(follow, send a follow=false first)``."""
        self.last_rx = now
        first, self.edge = self.edge and self.enabled, False
        return self.enabled, first

    def tick(self, now: float) -> bool:
        """Disengage on a silent console; True when it just did."""
        if self.enabled and self.last_rx is not None and not self.present(now):
            self.enabled = False
            self.notes.append(
                f"servo_jp from the ROS 2 console silent for > {self.servo_timeout_s * 1e3:.0f} ms"
            )
            return True
        return False

    def on_slave(self, following: bool, reason: str) -> bool:
        """The slave's operating state; disengage when it stops following (True when it just did)."""
        if following:
            self.slave_followed = self.enabled
            return False
        if self.enabled and self.slave_followed:
            self.enabled, self.slave_followed = False, False
            self.notes.append(f"the slave stopped following ({reason or 'hold'}); send enable again")
            return True
        return False
