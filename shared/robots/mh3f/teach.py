"""Direct teach and teaching playback of the forceps-holding arm (Jinno 2014), pure and testable.

Direct teach
------------
The operator pushes the arm by hand; the slave turns the external joint torques the backend
estimates (MuJoCo: inverse dynamics minus the modelled forces; a real arm: joint torque sensing or
motor currents) into motion by joint-space *admittance*: ``q̇_cmd = gain · τ_ext`` outside a
deadband, speed-capped. Gravity is compensated by the arm model, so a released arm stays put.
What moves depends on the control mode (:func:`direct_teach_step`):

* ``non_trocar``: every joint follows the push;
* ``trocar``: J1–J3 follow the push; J4/J5 are then set by :func:`posture_adjust` so the
  forceps axis goes from the new wrist centre through the trocar (the RCM holds by construction);
  J6 keeps its angle. A push that would pull the tip out of the trocar (shallower than
  :data:`~telesurg.shared.robots.mh3f.trocar.MIN_TIP_DEPTH`) is not followed;
* ``posture`` (transitional, method direct_teach): J4/J5 only, each only toward its posture
  target and never past it (Jinno: "direct teach limited to J4/J5 toward the target").

Teaching playback
-----------------
A *program* is a named list of taught points (joints and the measured tip). It is played back as
one motion through its points (:class:`Playback`): outside the patient (``non_trocar``, posture
adjustment) as synchronous joint PTP moves; in ``trocar`` mode as straight tip lines solved by the
trocar IK, so the forceps keeps pivoting about the trocar. :func:`playback_problem` refuses a
program that would cross the trocar: in trocar mode every point must lie on the trocar (RCM error
≤ :data:`POINT_RCM_TOL`) and inside; outside it every point must have the tip outside.

Taught trocars and programs persist in a JSON file (:class:`TeachStore`).
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from telesurg.shared import jsonio
from telesurg.shared.errors import ConfigError, IKError
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk
from telesurg.shared.robots.mh3f.motion import SMOOTH_PEAK, JointBrake, smooth
from telesurg.shared.robots.mh3f.trocar import (
    MIN_TIP_DEPTH,
    insertion_depth,
    posture_adjust,
    rcm_error,
    trocar_ik,
)

#: Names of programs and trocars.
NAME_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,31}$")
MAX_POINTS = 64
MAX_PROGRAMS = 32
#: A program point played in trocar mode must be this close to the forceps axis through the trocar.
POINT_RCM_TOL = 0.001
STORE_VERSION = 1


@dataclass
class TeachConfig:
    """Direct-teach admittance.

    Attributes:
        gain_arm: J1–J3 admittance, (rad/s)/(N·m).
        gain_wrist: J4–J6 admittance, (rad/s)/(N·m).
        deadband_nm: external torques below this are ignored, N·m.
        max_speed_rad_s: joint speed cap while taught by hand, rad/s.
    """

    gain_arm: float = 0.008
    gain_wrist: float = 0.02
    deadband_nm: float = 0.3
    max_speed_rad_s: float = 0.25


def admittance(tau_ext: np.ndarray, cfg: TeachConfig) -> np.ndarray:
    """Joint velocity (rad/s) the push ``tau_ext`` (N·m) asks for: deadband, gain, speed cap."""
    tau = np.sign(tau_ext) * np.maximum(np.abs(tau_ext) - cfg.deadband_nm, 0.0)
    gains = np.array([cfg.gain_arm] * 3 + [cfg.gain_wrist] * (len(tau) - 3))
    out: np.ndarray = np.clip(gains * tau, -cfg.max_speed_rad_s, cfg.max_speed_rad_s)
    return out


def direct_teach_step(
    q_cmd: np.ndarray,
    tau_ext: np.ndarray,
    dt: float,
    mode: str,
    cfg: TeachConfig,
    *,
    trocar: np.ndarray | None = None,
    posture_target: np.ndarray | None = None,
) -> np.ndarray:
    """Joint command after one period ``dt`` of direct teach (see the module docstring).

    Args:
        q_cmd: current joint command, rad.
        tau_ext: estimated external joint torques, N·m.
        dt: period, s.
        mode: ``non_trocar``, ``trocar`` or ``posture``.
        cfg: admittance.
        trocar: trocar point, m (trocar mode).
        posture_target: joints after the posture adjustment, rad (posture mode).

    Raises:
        IKError: the push cannot be followed (a joint limit, the tip would leave the trocar);
            the caller keeps ``q_cmd``.
    """
    v = admittance(tau_ext, cfg)
    out = q_cmd.copy()
    if mode == "non_trocar":
        out += v * dt
    elif mode == "trocar":
        if trocar is None:
            raise IKError("direct teach in trocar mode needs the trocar")
        out[:3] += v[:3] * dt
        if np.array_equal(out, q_cmd):
            return out
        out = posture_adjust(out, trocar)
        depth = insertion_depth(out, trocar)
        if depth < MIN_TIP_DEPTH:
            raise IKError(f"the push would pull the tip out of the trocar (depth {depth * 1e3:.1f} mm)")
    elif mode == "posture":
        if posture_target is None:
            raise IKError("direct teach in the posture adjustment needs its target")
        for j in (3, 4):
            togo = posture_target[j] - q_cmd[j]
            step = v[j] * dt
            if step * togo > 0:  # toward the target only, never past it
                out[j] += math.copysign(min(abs(step), abs(togo)), togo)
    else:
        raise IKError(f"direct teach has no rule for mode {mode!r}")
    lo, hi = np.array(MH3F.lower), np.array(MH3F.upper)
    if np.any(out < lo) or np.any(out > hi):
        j = int(np.argmax(np.maximum(lo - out, out - hi)))
        raise IKError(f"direct teach stopped: J{j + 1} at its limit")
    return out


@dataclass(frozen=True)
class TaughtPoint:
    """One taught point: joints (rad) and the measured tip (m, base frame) when it was taught."""

    q: tuple[float, ...]
    tip: tuple[float, float, float]
    mode: str  # control mode when taught


def playback_problem(points: list[TaughtPoint], mode: str, trocar: np.ndarray | None) -> str:
    """Why this program may not be played in ``mode`` (``""`` if it may)."""
    if not points:
        return "the program has no points"
    for i, p in enumerate(points, 1):
        q = np.array(p.q)
        if mode == "trocar":
            assert trocar is not None
            rcm = rcm_error(q, trocar)
            depth = insertion_depth(q, trocar)
            if rcm > POINT_RCM_TOL or depth < MIN_TIP_DEPTH:
                return (
                    f"point {i} is not on the trocar (RCM error {rcm * 1e3:.1f} mm, depth "
                    f"{depth * 1e3:.1f} mm): trocar-mode programs must be taught in trocar mode"
                )
        elif trocar is not None and insertion_depth(q, trocar) >= 0.0 and rcm_error(q, trocar) < 0.02:
            return f"point {i} has the tip inside the trocar: play it in trocar mode"
    return ""


@dataclass
class Playback:
    """Plays a program through its points (see the module docstring).

    Attributes:
        points: the program.
        mode: ``trocar`` (tip lines through the trocar IK) or anything else (joint PTP).
        trocar: trocar point, m (trocar mode).
        joint_speed: PTP joint speeds, rad/s, per joint.
        tip_speed: trocar-mode tip speed, m/s.
        dwell_s: time the arm rests at each point before the next segment starts, s; a point
            counts as reached (``reached``) at the end of its dwell, when the caller measures it.
        index: the point being approached.
    """

    points: list[TaughtPoint]
    mode: str
    trocar: np.ndarray | None
    joint_speed: np.ndarray
    tip_speed: float
    dwell_s: float = 0.3
    index: int = 0
    _q_from: np.ndarray | None = None
    _tip_from: np.ndarray | None = None
    _elapsed: float = 0.0
    _duration: float = 0.0
    _dwell: float = -1.0  # time left resting at the current point (< 0: still moving)
    reached: list[int] = field(default_factory=list)  # indices reached since last drained

    def _start_segment(self, q_cmd: np.ndarray) -> None:
        p = self.points[self.index]
        self._q_from = q_cmd.copy()
        self._elapsed = 0.0
        if self.mode == "trocar":
            self._tip_from = fk(q_cmd, MH3F)[:3, 3]
            self._duration = float(np.linalg.norm(np.array(p.tip) - self._tip_from)) / self.tip_speed
        else:
            # the smooth profile peaks at π/2 × its mean speed: the fastest joint peaks at joint_speed
            self._duration = SMOOTH_PEAK * float(np.max(np.abs(np.array(p.q) - q_cmd) / self.joint_speed))

    @property
    def done(self) -> bool:
        return self.index >= len(self.points)

    def next(self, q_cmd: np.ndarray, dt: float) -> np.ndarray:
        """Joint target one period later (raises IKError if the path leaves the reachable set)."""
        if self.done:
            return q_cmd
        if self._dwell >= 0.0:  # resting at the point just reached
            self._dwell -= dt
            if self._dwell < 0.0:
                self.reached.append(self.index)
                self.index += 1
                self._q_from = None
            return q_cmd
        if self._q_from is None:
            self._start_segment(q_cmd)
        assert self._q_from is not None
        p = self.points[self.index]
        self._elapsed = min(self._elapsed + dt, self._duration)
        s = 1.0 if self._duration <= 0 else self._elapsed / self._duration
        s = smooth(s)  # smooth start and stop
        if self.mode == "trocar":
            assert self.trocar is not None and self._tip_from is not None
            tip = self._tip_from + s * (np.array(p.tip) - self._tip_from)
            target = trocar_ik(tip, self.trocar, q_cmd)
        else:
            target = self._q_from + s * (np.array(p.q) - self._q_from)
        if self._elapsed >= self._duration:
            self._dwell = self.dwell_s
        return target

    def brake(self, ramp_s: float) -> JointBrake | None:
        """The controlled stop of a joint PTP segment under way (:class:`JointBrake`), or None
        (trocar mode: the tip line through the trocar IK is no joint-space line; at rest)."""
        if self.mode == "trocar" or self.done or self._q_from is None or self._dwell >= 0.0:
            return None
        q_to = np.array(self.points[self.index].q)
        return JointBrake.under_way(self._q_from, q_to, self._elapsed, self._duration, ramp_s)


class TeachStore:
    """Taught trocars and programs of one arm, persisted as JSON (``path`` None: memory only).

    File format (version 1)::

        {"version": 1, "arm": "arm1", "trocars": {"port1": [x, y, z]}, "current_trocar": "port1",
         "programs": {"exchange": [{"q": [...], "tip": [x, y, z], "mode": "non_trocar"}]}}

    Positions in metres, joints in radians. Written atomically (temporary file + rename).
    """

    def __init__(self, path: str | Path | None, arm: str) -> None:
        self.path = Path(path) if path else None
        self.arm = arm
        self.trocars: dict[str, tuple[float, float, float]] = {}
        self.current_trocar = ""
        self.programs: dict[str, list[TaughtPoint]] = {}
        if self.path is not None and self.path.exists():
            self._load(self.path)

    def _load(self, path: Path) -> None:
        try:
            data = json.loads(path.read_text())
            if data.get("version") != STORE_VERSION:
                raise ConfigError(f"version {data.get('version')!r}, expected {STORE_VERSION}")
            if data.get("arm") != self.arm:
                raise ConfigError(f"it belongs to arm {data.get('arm')!r}, not {self.arm!r}")
            trocars = {str(k): _vec3(v) for k, v in data.get("trocars", {}).items()}
            programs = {str(k): [_point(p) for p in v] for k, v in data.get("programs", {}).items()}
            current = str(data.get("current_trocar", ""))
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ConfigError(f"teach store {path}: {exc}") from exc
        for name in [*trocars, *programs]:
            if not NAME_RE.match(name):
                raise ConfigError(f"teach store {path}: invalid name {name!r}")
        if any(len(p.q) != len(MH3F.joint_names) for v in programs.values() for p in v):
            raise ConfigError(f"teach store {path}: a program point has the wrong number of joints")
        if current and current not in trocars:
            raise ConfigError(f"teach store {path}: current trocar {current!r} is not stored")
        self.trocars, self.programs, self.current_trocar = trocars, programs, current

    def save(self) -> None:
        """Write the file (nothing without a path)."""
        if self.path is None:
            return
        data = {
            "version": STORE_VERSION,
            "arm": self.arm,
            "trocars": {k: list(v) for k, v in self.trocars.items()},
            "current_trocar": self.current_trocar,
            "programs": {k: [asdict(p) for p in v] for k, v in self.programs.items()},
        }
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(self.path.suffix + ".tmp")
        tmp.write_text(jsonio.dumps(data, indent=1))
        os.replace(tmp, self.path)

    def add_point(self, program: str, point: TaughtPoint) -> str:
        """Append a point; returns a refusal reason or ``""``."""
        if not NAME_RE.match(program):
            return f"invalid program name {program!r} (lower-case letters, digits, _ and -, ≤ 32)"
        if program not in self.programs and len(self.programs) >= MAX_PROGRAMS:
            return f"already {MAX_PROGRAMS} programs (clear one first)"
        pts = self.programs.setdefault(program, [])
        if len(pts) >= MAX_POINTS:
            return f"program {program!r} already has {MAX_POINTS} points"
        pts.append(point)
        return ""


def _point(p: dict[str, object]) -> TaughtPoint:
    q = p["q"]
    if not isinstance(q, list) or not all(isinstance(x, int | float) and math.isfinite(x) for x in q):
        raise ValueError(f"bad joints {q!r}")
    return TaughtPoint(tuple(float(x) for x in q), _vec3(p["tip"]), str(p["mode"]))


def _vec3(v: object) -> tuple[float, float, float]:
    if not isinstance(v, list | tuple) or len(v) != 3:
        raise ValueError(f"expected 3 numbers, got {v!r}")
    x, y, z = (float(a) for a in v)
    if not all(math.isfinite(a) for a in (x, y, z)):
        raise ValueError(f"non-finite position {v!r}")
    return (x, y, z)
