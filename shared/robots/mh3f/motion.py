"""Slave-side motion sources for the non-master-slave motion modes (Jinno 2014): PTP and jog.

Each source turns the current commanded joints into the next joint target once per control
period; slave_control rate-limits it to the joint speed limits and runs it only under a valid
lease. Pure (kinematics only), so it can be tested on its own.

* :class:`PtpMotion` — point-to-point synchronous joint motion (posture adjustment of J4/J5):
  every joint arrives at the same time, on the straight joint-space line, with a smooth (cosine)
  start and stop; :class:`JointBrake` — its controlled stop along the same line.
* :func:`jog_step` — one period of a jog: translation of the tip along an axis of the base
  (``world``, ``base``), the work frame (the laparoscope view, :mod:`.work_frame`) or the
  forceps frame at ``speed_m_s``, orientation kept;
  a rotation ``rx``/``ry``/``rz`` about that axis through the tip at ``joint_speed_rad_s``, tip
  kept; or one joint at ``joint_speed_rad_s``. In trocar mode a translation goes through the
  trocar IK, so the forceps keeps pivoting about the trocar, and the only rotation is the roll
  about the shaft (forceps ``rx``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from telesurg.shared.errors import IKError
from telesurg.shared.kinematics.transforms import matrix_from_rotvec
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, ik
from telesurg.shared.robots.mh3f.trocar import forceps_roll, trocar_ik

_AXES = {"x": 0, "y": 1, "z": 2, "rx": 0, "ry": 1, "rz": 2}
#: Jog axes this slave can execute.
SUPPORTED_JOG_AXES = ("x", "y", "z", "rx", "ry", "rz", "j1", "j2", "j3", "j4", "j5", "j6")


def smooth(s: float) -> float:
    """The PTP's time profile: the fraction of the path at the fraction ``s`` of its duration
    (cosine: zero speed at both ends, peak speed π/2 × the mean)."""
    return 0.5 - 0.5 * math.cos(math.pi * min(max(s, 0.0), 1.0))


def smooth_rate(s: float) -> float:
    """d smooth / d s at ``s`` (π/2 at mid-path, 0 at both ends)."""
    return 0.5 * math.pi * math.sin(math.pi * min(max(s, 0.0), 1.0))


#: peak speed of the :func:`smooth` profile over its mean speed
SMOOTH_PEAK = math.pi / 2


@dataclass
class JointBrake:
    """A controlled stop of a straight joint-space motion ``q_from → q_to``: from the fraction
    ``s`` of the path, moving at ``rate`` (fraction of the path per second), the speed ramps down
    linearly to zero over ``ramp_s`` — on the same line, never past ``q_to``.

    A joint PTP whose command simply froze left its (checked) path: the MuJoCo arm at 0.8 × the
    joint limits, stopped at once, strayed up to 15 mrad off the line (J5 at its force limit while
    the other joints stopped sooner); ramped down over 30 ms, within 0.8 mrad (docs/trocar.md).
    """

    q_from: np.ndarray
    q_to: np.ndarray
    s: float
    rate: float
    ramp_s: float
    elapsed_s: float = 0.0

    def next(self, dt: float) -> np.ndarray:
        """Joint target after another ``dt`` seconds of the stop."""
        t0 = self.elapsed_s
        t1 = self.elapsed_s = min(t0 + dt, self.ramp_s)
        r = self.rate / self.ramp_s if self.ramp_s > 0 else 0.0
        self.s = min(1.0, self.s + self.rate * (t1 - t0) - 0.5 * r * (t1 * t1 - t0 * t0))
        out: np.ndarray = self.q_from + self.s * (self.q_to - self.q_from)
        return out

    @classmethod
    def under_way(
        cls, q_from: np.ndarray, q_to: np.ndarray, elapsed_s: float, duration_s: float, ramp_s: float
    ) -> JointBrake:
        """The stop of a :func:`smooth` motion ``q_from → q_to`` of ``duration_s``, ``elapsed_s``
        into it."""
        s = 1.0 if duration_s <= 0 else elapsed_s / duration_s
        rate = 0.0 if duration_s <= 0 else smooth_rate(s) / duration_s
        return cls(q_from, q_to, smooth(s), rate, ramp_s)

    @property
    def done(self) -> bool:
        """The speed is down to zero (or the path's end is reached)."""
        return self.elapsed_s >= self.ramp_s or self.s >= 1.0


@dataclass
class PtpMotion:
    """Synchronous joint motion from ``q_from`` to ``q_to`` over ``duration_s`` (:func:`smooth`
    profile: the servos of the MuJoCo arm follow it within 0.6 mrad of the line at 0.8 × the joint
    limits; a constant-speed PTP that stopped at once at its end overshot by 20 mrad)."""

    q_from: np.ndarray
    q_to: np.ndarray
    duration_s: float
    elapsed_s: float = 0.0

    def _s(self) -> float:
        return 1.0 if self.duration_s <= 0 else self.elapsed_s / self.duration_s

    def next(self, dt: float) -> np.ndarray:
        """Joint target after another ``dt`` seconds."""
        self.elapsed_s = min(self.elapsed_s + dt, self.duration_s)
        out: np.ndarray = self.q_from + smooth(self._s()) * (self.q_to - self.q_from)
        return out

    def brake(self, ramp_s: float) -> JointBrake:
        """Its controlled stop from where it is now (see :class:`JointBrake`)."""
        return JointBrake.under_way(self.q_from, self.q_to, self.elapsed_s, self.duration_s, ramp_s)

    @property
    def done(self) -> bool:
        """The target has been reached."""
        return self.elapsed_s >= self.duration_s


def ptp_duration(q_from: np.ndarray, q_to: np.ndarray, speed_fraction: float = 0.2) -> float:
    """Duration (s) of a synchronous PTP whose fastest joint peaks at ``speed_fraction`` of its
    limit (the :func:`smooth` profile: π/2 × the constant-speed duration)."""
    vmax = np.array(MH3F.max_velocity) * speed_fraction
    return SMOOTH_PEAK * float(np.max(np.abs(q_to - q_from) / vmax))


def jog_step(
    q: np.ndarray,
    frame: str,
    axis: str,
    direction: int,
    dt: float,
    *,
    speed_m_s: float,
    joint_speed_rad_s: float,
    trocar: np.ndarray | None,
    work: np.ndarray | None = None,
) -> np.ndarray:
    """Joint target one period ``dt`` further along the jog (raises IKError at a limit/reach).

    ``trocar`` (m) given: translations keep the forceps through it (trocar-mode IK). ``work``:
    the work frame's rotation ``(3, 3)`` in the base frame (None: the base frame).
    """
    if axis.startswith("j"):
        out = q.copy()
        out[int(axis[1:]) - 1] += direction * joint_speed_rad_s * dt
        return out
    if axis not in _AXES:
        raise IKError(f"jog about {axis} is not implemented")
    T = fk(q, MH3F)
    # forceps: the TCP frame's axis; work: the work frame's (laparoscope view); world, base: base
    if frame == "forceps":
        d = T[:3, _AXES[axis]]
    elif frame == "work" and work is not None:
        d = work[:, _AXES[axis]]
    else:
        d = np.eye(3)[_AXES[axis]]
    T_next = T.copy()
    if axis.startswith("r"):
        angle = direction * joint_speed_rad_s * dt
        if trocar is not None:
            if (frame, axis) != ("forceps", "rx"):
                raise IKError(
                    f"in trocar mode the only rotation is the roll (forceps rx), not {frame} {axis}"
                )
            return trocar_ik(T[:3, 3], trocar, q, roll=forceps_roll(q, MH3F) + angle)
        T_next[:3, :3] = matrix_from_rotvec(d * angle) @ T[:3, :3]
        return ik(T_next, q, MH3F)
    T_next[:3, 3] = T[:3, 3] + direction * speed_m_s * dt * d
    if trocar is not None:
        return trocar_ik(T_next[:3, 3], trocar, q)
    return ik(T_next, q, MH3F)
