"""Control modes of one forceps-holding slave arm, free of I/O and kinematics so it can be tested.

After M. Jinno, "Master–slave manipulator for laparoscopic surgery using a 6-axis vertical
articulated robot", ROBOMECH Journal 1:23 (2014), Fig. 4 (control modes and state transitions)
and Fig. 5 (insert flow A–D).

:class:`ControlModes` owns the control mode of one arm and decides which commands are allowed.
It computes nothing geometric: each control cycle the caller passes the measurements in with
:meth:`ControlModes.update` (insertion depth, forceps axis angle to the trocar, whether a trocar
is taught, optionally the J4/J5 distance to the posture target) and executes what the machine
says (``motion``, ``jog_command``). Every command returns a :class:`Reply`; a refused command
changes nothing and says why, with numbers where relevant.

States (``control`` / ``phase``)
--------------------------------
* ``non_trocar`` (Fig. 5 A): forceps outside the patient; conventional IK. All four basic motion
  modes (``master_slave``, ``jog``, ``direct_teach``, ``playback``); jog in every frame.
* ``transitional`` / ``posture`` (B): the forceps axis is turned to the trocar by J4/J5 only,
  with the one method chosen in :meth:`~ControlModes.begin_posture_adjust`:

  - ``ptp``: synchronous point-to-point move of J4/J5 to their targets (motion ``ptp``);
  - ``jog``: joint jog of J4 or J5, each only in the direction of its target (the caller passes
    the remaining distance ``j45_to_target_rad``; the jog stops by itself at the target);
  - ``direct_teach``: J4/J5 moved by hand toward their targets (the controller limits the joints);
  - ``playback``: a program whose taught point is already aligned with the trocar (checked when
    the adjustment begins; all joints move).
* ``transitional`` / ``insert`` (C): only jog along the forceps axis (forceps frame ``x``;
  ``x+`` is toward the tip, i.e. inward), and inward only while the axis is aligned.
* ``trocar`` (D): forceps inside, remote centre of motion at the trocar. All four basic motion
  modes; jog: translations ``x``/``y``/``z`` in the Cartesian frames, the roll ``forceps rx``
  and joint ``j6`` (the trocar fixes the shaft direction, so no other rotation or joint).
* ``transitional`` / ``remove``: the way back out (this module's choice for the paper's
  "insert/remove motion" on the way out): only jog outward along the forceps axis (``x-``).

Commands and where they are accepted (N non_trocar, P posture, I insert, R remove, T trocar)::

    teach_trocar             N           (stores the trocar; the caller reports it in update)
    begin_posture_adjust(m)  N + trocar  → P (m); playback needs an aligned program
    finish_posture_adjust    P           → I; axis ≤ align_tolerance, tip outside
    insert                   I           inward axis jog; trocar, axis ≤ tolerance, depth known
    remove                   T → R, R    outward axis jog (in R: resume after a stop)
    set_motion_mode(mode)    N, T: the 4 basic modes; P: the method's mode; I, R: jog
    jog(frame, axis, ±1)     when motion is jog, restricted per state as above
    stop                     anywhere    stops the current jog
    abort                    anywhere    stops all motion; P → N; I → N if the tip is outside,
                                         else → R; N, R, T keep their state

Thresholds and hysteresis
-------------------------
* I → T exactly when ``depth_m >= trocar_depth_m`` (50 mm, the paper's rule). T is left only by
  the command :meth:`~ControlModes.remove`, never by the depth, so depth jitter around 50 mm
  cannot switch back.
* R → N when the tip has passed back out: ``depth_m < -exit_margin_m`` (default 2 mm beyond the
  trocar point on the outside, so that noise while the tip still sits in the trocar valve,
  ``depth ≈ 0``, cannot end the removal early). N is left only by commands, never by the depth.
* Each threshold is armed in one phase only (50 mm in I, the exit in R), so depth jitter around
  either threshold switches at most once per insert or remove. The same "tip outside" test
  (``depth_m < -exit_margin_m``) is required by ``finish_posture_adjust`` and decides where
  ``abort`` goes from I.

Safety rules: unknown or non-finite measurements count as missing, and anything that needs them
is refused. Losing the taught trocar (``trocar_taught`` falling to False in update) outside
``non_trocar`` aborts. A running inward jog stops when the depth is lost or the axis angle passes
``align_running_tolerance_rad`` (2°; starting needs ``align_tolerance_rad``, 0.05°); a
posture jog stops when its joint reaches (or passes) its target.

Events (``(kind, text)``, drained by the caller): ``mode_transition`` (``"A → B"``, with
``": cause"`` when not commanded, e.g. ``"transitional/insert → trocar: depth 50.0 mm ≥ 50.0 mm"``),
``motion_mode`` (``"jog → master_slave"``), ``trocar_taught``, ``jog_stopped``, ``abort``.
``transitions`` counts control-mode/phase changes only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TypeVar

from telesurg.shared.errors import ConfigError
from telesurg.shared.robots.mh3f.trocar import TROCAR_MODE_DEPTH

__all__ = [
    "BASIC_MOTION_MODES",
    "CARTESIAN_AXES",
    "FORCEPS_AXIS",
    "JOINT_AXES",
    "ControlMode",
    "ControlModes",
    "Frame",
    "Jog",
    "ModeConfig",
    "MotionMode",
    "Phase",
    "PostureMethod",
    "Reply",
]


class ControlMode(StrEnum):
    """The paper's three control modes (values as in ``OperatingState.control_mode``)."""

    NON_TROCAR = "non_trocar"
    TRANSITIONAL = "transitional"
    TROCAR = "trocar"


class Phase(StrEnum):
    """Sub-phase of the transitional mode."""

    POSTURE = "posture"
    INSERT = "insert"
    REMOVE = "remove"


class PostureMethod(StrEnum):
    """The four posture adjustment methods (J4/J5 only, except playback)."""

    PTP = "ptp"
    JOG = "jog"
    DIRECT_TEACH = "direct_teach"
    PLAYBACK = "playback"


class MotionMode(StrEnum):
    """What drives the arm: the four basic motion modes, and ``ptp`` (posture adjustment only)."""

    MASTER_SLAVE = "master_slave"
    JOG = "jog"
    DIRECT_TEACH = "direct_teach"
    PLAYBACK = "playback"
    PTP = "ptp"


class Frame(StrEnum):
    """Jog coordinate systems."""

    WORLD = "world"
    BASE = "base"
    WORK = "work"
    FORCEPS = "forceps"
    JOINT = "joint"


BASIC_MOTION_MODES = (MotionMode.MASTER_SLAVE, MotionMode.JOG, MotionMode.DIRECT_TEACH, MotionMode.PLAYBACK)
CARTESIAN_AXES = ("x", "y", "z", "rx", "ry", "rz")
JOINT_AXES = ("j1", "j2", "j3", "j4", "j5", "j6")
#: The forceps axis is the forceps (TCP) frame x axis; ``+1`` points to the tip, i.e. inward.
FORCEPS_AXIS = "x"

_POSTURE_MOTION = {
    PostureMethod.PTP: MotionMode.PTP,
    PostureMethod.JOG: MotionMode.JOG,
    PostureMethod.DIRECT_TEACH: MotionMode.DIRECT_TEACH,
    PostureMethod.PLAYBACK: MotionMode.PLAYBACK,
}
_TROCAR_ROTATIONS = {(Frame.FORCEPS, "rx")}  # roll about the shaft: the only rotation with a trocar


_E = TypeVar("_E", bound=StrEnum)


def _parse(cls: type[_E], value: str) -> _E | None:
    """``cls(value)``, or None if ``value`` is not one of its values."""
    try:
        return cls(value)
    except ValueError:
        return None


def _deg(rad: float) -> str:
    d = math.degrees(rad)
    return f"{d:.2f}°" if abs(d) < 1.0 else f"{d:.1f}°"


def _mm(m: float) -> str:
    return f"{m * 1e3:.1f} mm"


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _axes(frame: Frame) -> tuple[str, ...]:
    return JOINT_AXES if frame is Frame.JOINT else CARTESIAN_AXES


@dataclass(frozen=True)
class Reply:
    """Answer to a command.

    Attributes:
        accepted: True if the command was carried out (or started).
        reason: why it was refused, or a short note when accepted.
    """

    accepted: bool
    reason: str


@dataclass(frozen=True)
class Jog:
    """An active jog: move along ``axis`` of ``frame`` in ``direction`` (+1/-1) at jog speed."""

    frame: Frame
    axis: str
    direction: int

    def __str__(self) -> str:
        return f"{self.frame} {self.axis}{'+' if self.direction > 0 else '-'}"


@dataclass(frozen=True)
class ModeConfig:
    """Thresholds of the control-mode machine.

    Attributes:
        trocar_depth_m: insertion depth from which transitional/insert switches to trocar, m.
        exit_margin_m: the tip counts as outside (removal done) when ``depth < -exit_margin_m``, m.
        align_tolerance_rad: largest forceps-axis angle to the trocar direction to finish the
            posture adjustment and to insert, rad.
        joint_deadband_rad: a posture jog of J4/J5 is done when its remaining distance to the
            target is at most this, rad; below ``align_tolerance_rad``, so a jog a hold stopped
            just short of its target can be jogged on to it (0.1° used to leave it stuck
            0.09° short, more than the 0.05° alignment finish_posture_adjust asks).
        align_running_tolerance_rad: a running insertion stops when the axis angle exceeds
            this (hysteresis above ``align_tolerance_rad``: servo lag while the arm moves must not
            stop it), rad.
    """

    trocar_depth_m: float = TROCAR_MODE_DEPTH
    exit_margin_m: float = 0.002
    align_tolerance_rad: float = math.radians(0.05)
    joint_deadband_rad: float = math.radians(0.01)
    align_running_tolerance_rad: float = math.radians(2.0)

    def __post_init__(self) -> None:
        for name in (
            "trocar_depth_m",
            "align_tolerance_rad",
            "joint_deadband_rad",
            "align_running_tolerance_rad",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ConfigError(f"ModeConfig.{name} must be finite and > 0, got {v}")
        if not (math.isfinite(self.exit_margin_m) and self.exit_margin_m >= 0.0):
            raise ConfigError(f"ModeConfig.exit_margin_m must be finite and >= 0, got {self.exit_margin_m}")


@dataclass
class ControlModes:
    """Control mode state machine of one slave arm (see the module docstring for the rules).

    Attributes:
        config: thresholds.
        control: control mode (``control.value`` goes into ``OperatingState.control_mode``).
        phase: transitional sub-phase (None outside transitional).
        posture_method: the chosen method while in the posture phase (else None).
        motion: the motion mode driving the arm (None: nothing may move the arm).
        jog_command: the jog the caller must execute now (None: no jog).
        trocar_taught: a trocar position is stored (the caller's last word, or teach_trocar).
        depth_m: last insertion depth along the forceps axis from the trocar, m (+ inside).
        axis_angle_rad: last angle between the forceps axis and the wrist → trocar direction.
        j45_to_target_rad: last (J4, J5) target minus current, rad (posture jog), or None.
        transitions: accepted control-mode/phase changes.
        events: ``(kind, text)`` pairs, drained by the caller.
    """

    config: ModeConfig = field(default_factory=ModeConfig)
    control: ControlMode = ControlMode.NON_TROCAR
    phase: Phase | None = None
    posture_method: PostureMethod | None = None
    motion: MotionMode | None = None
    jog_command: Jog | None = None
    trocar_taught: bool = False
    depth_m: float | None = None
    axis_angle_rad: float | None = None
    j45_to_target_rad: tuple[float, float] | None = None
    transitions: int = 0
    events: list[tuple[str, str]] = field(default_factory=list)

    # ----------------------------------------------------------------------------- views

    @property
    def control_mode(self) -> str:
        """``"non_trocar"`` / ``"transitional"`` / ``"trocar"`` for ``OperatingState``."""
        return self.control.value

    @property
    def label(self) -> str:
        """The state as shown in events, e.g. ``"transitional/posture (ptp)"``."""
        if self.phase is None:
            return self.control.value
        text = f"{self.control.value}/{self.phase.value}"
        return f"{text} ({self.posture_method})" if self.posture_method is not None else text

    def _where(self) -> str:
        return self.label if self.phase is not None else f"{self.control.value} mode"

    def _tip_outside(self) -> bool:
        return self.depth_m is not None and self.depth_m < -self.config.exit_margin_m

    # ----------------------------------------------------------------------------- inputs

    def update(
        self,
        depth_m: float | None,
        axis_angle_rad: float | None,
        trocar_taught: bool,
        *,
        j45_to_target_rad: tuple[float, float] | None = None,
    ) -> None:
        """Take one control cycle's measurements and make the automatic transitions.

        Args:
            depth_m: insertion depth of the tip along the forceps axis from the trocar, m
                (positive inside); None if unknown (no trocar, no measurement).
            axis_angle_rad: angle between the forceps axis and the direction wrist → trocar,
                rad (its magnitude is used); None if unknown.
            trocar_taught: a trocar position is stored (authoritative each cycle).
            j45_to_target_rad: (J4, J5) posture target minus current, rad; needed for the
                posture jog only.
        """
        self.depth_m = _finite(depth_m)
        angle = _finite(axis_angle_rad)
        self.axis_angle_rad = None if angle is None else abs(angle)
        j = j45_to_target_rad
        self.j45_to_target_rad = (
            (float(j[0]), float(j[1])) if j is not None and all(math.isfinite(v) for v in j) else None
        )
        lost = self.trocar_taught and not trocar_taught
        self.trocar_taught = bool(trocar_taught)
        if lost and self.control is not ControlMode.NON_TROCAR:
            self.abort("trocar position lost")
        cfg = self.config
        if self.phase is Phase.POSTURE and self.jog_command is not None:
            problem = self._posture_jog_problem(self.jog_command.axis, self.jog_command.direction)
            if problem:
                self._stop_jog(problem)
        elif self.phase is Phase.INSERT:
            if self.depth_m is not None and self.depth_m >= cfg.trocar_depth_m:
                self._transition(
                    ControlMode.TROCAR,
                    None,
                    None,
                    self.motion,
                    f"depth {_mm(self.depth_m)} ≥ {_mm(cfg.trocar_depth_m)}",
                )
            elif self.jog_command is not None and self.jog_command.direction > 0:
                problem = self._alignment_problem(running=True)
                if problem:
                    self._stop_jog(problem)
        elif self.phase is Phase.REMOVE and self._tip_outside():
            assert self.depth_m is not None
            self._transition(
                ControlMode.NON_TROCAR,
                None,
                None,
                None,
                f"tip out of the trocar (depth {_mm(self.depth_m)} < {_mm(-cfg.exit_margin_m)})",
            )

    # ----------------------------------------------------------------------------- commands

    def teach_trocar(self) -> Reply:
        """Store the current tip position as the trocar (the caller stores it on acceptance)."""
        if problem := self._teach_problem():
            return Reply(False, problem)
        self.trocar_taught = True
        self.events.append(("trocar_taught", "trocar position taught"))
        return Reply(True, "trocar position taught")

    def begin_posture_adjust(self, method: str, *, program_axis_angle_rad: float | None = None) -> Reply:
        """non_trocar → transitional/posture with one of the four methods.

        Args:
            method: ``ptp``, ``jog``, ``direct_teach`` or ``playback``.
            program_axis_angle_rad: for ``playback``: angle between the forceps axis at the
                program's taught point and the trocar direction, rad (computed by the caller).
        """
        if problem := self._begin_problem(method, program_axis_angle_rad):
            return Reply(False, problem)
        m = PostureMethod(method)
        self._transition(ControlMode.TRANSITIONAL, Phase.POSTURE, m, _POSTURE_MOTION[m])
        return Reply(True, f"posture adjustment by {m}")

    def finish_posture_adjust(self) -> Reply:
        """transitional/posture → transitional/insert once the forceps points at the trocar."""
        if problem := self._finish_problem():
            return Reply(False, problem)
        self._transition(ControlMode.TRANSITIONAL, Phase.INSERT, None, MotionMode.JOG)
        return Reply(True, "aligned: insert along the forceps axis")

    def insert(self) -> Reply:
        """Jog inward along the forceps axis (transitional/insert only)."""
        if problem := self._insert_problem():
            return Reply(False, problem)
        self._set_motion(MotionMode.JOG)
        self.jog_command = Jog(Frame.FORCEPS, FORCEPS_AXIS, 1)
        return Reply(True, f"inserting ({self.jog_command})")

    def remove(self) -> Reply:
        """Jog outward along the forceps axis: trocar → transitional/remove, or resume in remove."""
        if problem := self._remove_problem():
            return Reply(False, problem)
        if self.control is ControlMode.TROCAR:
            self._transition(ControlMode.TRANSITIONAL, Phase.REMOVE, None, MotionMode.JOG)
        else:
            self._set_motion(MotionMode.JOG)
        self.jog_command = Jog(Frame.FORCEPS, FORCEPS_AXIS, -1)
        return Reply(True, f"removing ({self.jog_command})")

    def set_motion_mode(self, mode: str) -> Reply:
        """Select what drives the arm (restricted per control mode, see the module docstring)."""
        if problem := self._motion_problem(mode):
            return Reply(False, problem)
        m = MotionMode(mode)
        if m is self.motion:
            return Reply(True, f"{m} already active")
        self._set_motion(m)
        return Reply(True, f"motion mode {m}")

    def jog(self, frame: str, axis: str, direction: int) -> Reply:
        """Start jogging ``axis`` of ``frame`` in ``direction`` (+1 or -1); motion must be jog."""
        if problem := self._jog_problem(frame, axis, direction):
            return Reply(False, problem)
        self.jog_command = Jog(Frame(frame), axis, direction)
        return Reply(True, f"jogging {self.jog_command}")

    def stop(self) -> Reply:
        """Stop the current jog (always accepted; the motion mode stays)."""
        if self.jog_command is None:
            return Reply(True, "no jog to stop")
        self._stop_jog("stopped by the operator")
        return Reply(True, "jog stopped")

    def abort(self, reason: str = "operator abort") -> Reply:
        """Stop all motion and go to the safe state (always accepted).

        posture → non_trocar; insert → non_trocar if the tip is known to be outside, else
        transitional/remove (the forceps may be in the trocar: only the way out is allowed);
        non_trocar, remove and trocar keep their state. ``motion`` becomes None.
        """
        before = self.label
        if self.phase is Phase.POSTURE or (self.phase is Phase.INSERT and self._tip_outside()):
            self._transition(ControlMode.NON_TROCAR, None, None, None, f"abort ({reason})")
        elif self.phase is Phase.INSERT:
            depth = "unknown" if self.depth_m is None else _mm(self.depth_m)
            self._transition(
                ControlMode.TRANSITIONAL,
                Phase.REMOVE,
                None,
                None,
                f"abort ({reason}); tip not known to be outside (depth {depth})",
            )
        else:
            self._set_motion(None)
        after = self.label
        note = f"motion stopped, {after} kept" if after == before else f"motion stopped, {before} → {after}"
        self.events.append(("abort", f"{reason}: {note}"))
        return Reply(True, note)

    def allowed(self) -> dict[str, list[str]]:
        """What is allowed now, for a console.

        Returns:
            ``state``: ``[label]``; ``commands``: accepted commands (parametrised ones with the
            argument, e.g. ``begin_posture_adjust(ptp)``; playback assumes an aligned program);
            ``motion_modes``: accepted by :meth:`set_motion_mode`; ``jog``: accepted jogs as
            ``"frame axis±"`` (empty unless the motion mode is jog).
        """
        cmds: list[str] = []
        if not self._teach_problem():
            cmds.append("teach_trocar")
        cmds += [f"begin_posture_adjust({m})" for m in PostureMethod if not self._begin_problem(m, 0.0)]
        for name, problem in (
            ("finish_posture_adjust", self._finish_problem()),
            ("insert", self._insert_problem()),
            ("remove", self._remove_problem()),
        ):
            if not problem:
                cmds.append(name)
        modes = [m.value for m in MotionMode if not self._motion_problem(m)]
        jogs = [
            str(Jog(f, a, d))
            for f in Frame
            for a in _axes(f)
            for d in (1, -1)
            if not self._jog_problem(f, a, d)
        ]
        cmds += [f"set_motion_mode({m})" for m in modes]
        if jogs:
            cmds.append("jog")
        cmds += ["stop", "abort"]
        return {"state": [self.label], "commands": cmds, "motion_modes": modes, "jog": jogs}

    # ----------------------------------------------------------------------------- checks
    # Each returns the full refusal reason, or "" if the command is allowed now.

    def _teach_problem(self) -> str:
        if self.control is not ControlMode.NON_TROCAR:
            return f"teach_trocar refused in {self._where()}: the trocar is taught in non_trocar mode only"
        return ""

    def _begin_problem(self, method: str, program_axis_angle_rad: float | None) -> str:
        if _parse(PostureMethod, method) is None:
            names = ", ".join(PostureMethod)
            return f"posture adjustment refused: unknown method {method!r} (one of {names})"
        if self.phase is Phase.POSTURE:
            return f"posture adjustment refused in {self._where()}: already adjusting (abort to change)"
        if self.control is not ControlMode.NON_TROCAR:
            return f"posture adjustment refused in {self._where()}: it starts from non_trocar mode only"
        if not self.trocar_taught:
            return "posture adjustment refused: no trocar taught"
        if method == PostureMethod.PLAYBACK:
            a = _finite(program_axis_angle_rad)
            tol = self.config.align_tolerance_rad
            if a is None:
                return (
                    "posture adjustment (playback) refused: alignment of the program's taught point "
                    "unknown (pass program_axis_angle_rad)"
                )
            if abs(a) > tol:
                return (
                    f"posture adjustment (playback) refused: taught point {_deg(abs(a))} off the trocar "
                    f"direction (limit {_deg(tol)})"
                )
        return ""

    def _alignment_problem(self, *, running: bool = False) -> str:
        """Why inward motion along the forceps axis is not allowed now ("" if it is); ``running``:
        for an insertion already under way (the wider tolerance)."""
        cfg = self.config
        tol = cfg.align_running_tolerance_rad if running else cfg.align_tolerance_rad
        if not self.trocar_taught:
            return "no trocar taught"
        if self.axis_angle_rad is None:
            return "forceps axis angle to the trocar unknown"
        if self.axis_angle_rad > tol:
            return f"forceps axis {_deg(self.axis_angle_rad)} off the trocar direction (limit {_deg(tol)})"
        if self.depth_m is None:
            return "insertion depth unknown"
        return ""

    def _finish_problem(self) -> str:
        if self.phase is not Phase.POSTURE:
            return f"finish_posture_adjust refused in {self._where()}: no posture adjustment in progress"
        if problem := self._alignment_problem():
            return f"finish_posture_adjust refused: {problem}"
        if not self._tip_outside():
            assert self.depth_m is not None
            return (
                f"finish_posture_adjust refused: tip at depth {_mm(self.depth_m)}; insertion must start "
                f"with the tip outside (depth < {_mm(-self.config.exit_margin_m)})"
            )
        return ""

    def _insert_problem(self) -> str:
        where = self._where()
        if self.control is ControlMode.NON_TROCAR:
            if not self.trocar_taught:
                return "insert refused: no trocar taught"
            return f"insert refused in {where}: adjust the posture first (begin/finish_posture_adjust)"
        if self.control is ControlMode.TROCAR:
            return f"insert refused in {where}: the forceps is already inserted"
        if self.phase is Phase.POSTURE:
            return f"insert refused in {where}: finish the posture adjustment first"
        if self.phase is Phase.REMOVE:
            return f"insert refused in {where}: complete the removal (or abort) first"
        if problem := self._alignment_problem():
            return f"insert refused: {problem}"
        return ""

    def _remove_problem(self) -> str:
        if self.control is ControlMode.TROCAR or self.phase is Phase.REMOVE:
            return ""
        if self.phase is Phase.INSERT:
            return f"remove refused in {self._where()}: back out with jog(forceps, x, -1), or abort"
        return f"remove refused in {self._where()}: the forceps is not inserted"

    def _motion_problem(self, mode: str) -> str:
        if _parse(MotionMode, mode) is None:
            names = ", ".join(BASIC_MOTION_MODES)
            return f"set_motion_mode refused: unknown motion mode {mode!r} (one of {names})"
        m, where = MotionMode(mode), self._where()
        if self.phase is Phase.POSTURE:
            assert self.posture_method is not None
            allowed = _POSTURE_MOTION[self.posture_method]
            if m is not allowed:
                return f"{m} refused in {where}: only {allowed} (abort to change the method)"
        elif self.phase is not None:
            if m is not MotionMode.JOG:
                return f"{m} refused in transitional mode ({where}): only jog along the forceps axis"
        elif m is MotionMode.PTP:
            return f"ptp refused in {where}: point-to-point is a posture-adjustment method only"
        elif self.control is ControlMode.TROCAR and not self.trocar_taught:
            return f"{m} refused in {where}: no trocar taught"
        return ""

    def _posture_jog_problem(self, axis: str, direction: int) -> str:
        """Why a J4/J5 posture jog in ``direction`` does not move toward the target ("" if it does)."""
        joint = axis.upper()
        if self.j45_to_target_rad is None:
            return f"{joint} target unknown (no measurement)"
        togo = self.j45_to_target_rad[0 if axis == "j4" else 1]
        band = self.config.joint_deadband_rad
        if abs(togo) <= band:
            return f"{joint} at its target ({math.degrees(togo):+.2f}° to go, deadband {_deg(band)})"
        if (togo > 0) != (direction > 0):
            return f"{joint} must move toward its target ({math.degrees(togo):+.2f}° to go)"
        return ""

    def _jog_problem(self, frame: str, axis: str, direction: int) -> str:
        if _parse(Frame, frame) is None:
            return f"jog refused: unknown frame {frame!r} (one of {', '.join(Frame)})"
        f = Frame(frame)
        if axis not in _axes(f):
            return f"jog refused: {axis!r} is not an axis of the {f} frame ({', '.join(_axes(f))})"
        if isinstance(direction, bool) or direction not in (1, -1):
            return f"jog refused: direction must be +1 or -1, got {direction!r}"
        what, where = f"jog along {Jog(f, axis, direction)}", self._where()
        if self.phase is Phase.POSTURE:
            if self.posture_method is not PostureMethod.JOG:
                return f"{what} refused in {where}: jog is not the chosen posture method"
            if f is not Frame.JOINT or axis not in ("j4", "j5"):
                return f"{what} refused in {where}: only joints j4 and j5 may move"
            if problem := self._posture_jog_problem(axis, direction):
                return f"{what} refused in {where}: {problem}"
        elif self.phase is not None:
            if f is not Frame.FORCEPS or axis != FORCEPS_AXIS:
                return f"{what} refused in {where}: only the forceps axis (forceps {FORCEPS_AXIS}) is allowed"
            if self.phase is Phase.REMOVE and direction > 0:
                return f"{what} refused in {where}: only outward (forceps {FORCEPS_AXIS}-)"
            if self.phase is Phase.INSERT and direction > 0 and (problem := self._alignment_problem()):
                return f"{what} refused: {problem}"
        elif self.control is ControlMode.TROCAR:
            if not self.trocar_taught:
                return f"{what} refused in {where}: no trocar taught"
            if f is Frame.JOINT and axis != "j6":
                return f"{what} refused in {where}: of the joints only j6 (roll about the shaft) may jog"
            if f is not Frame.JOINT and axis.startswith("r") and (f, axis) not in _TROCAR_ROTATIONS:
                return (
                    f"{what} refused in {where}: the trocar fixes the shaft direction "
                    "(translations x/y/z and the roll forceps rx only)"
                )
        if self.motion is not MotionMode.JOG:
            return f"{what} refused: motion mode is {self.motion or 'none'} (select jog first)"
        return ""

    # ----------------------------------------------------------------------------- effects

    def _transition(
        self,
        control: ControlMode,
        phase: Phase | None,
        method: PostureMethod | None,
        motion: MotionMode | None,
        cause: str = "",
    ) -> None:
        before = self.label
        if self.jog_command is not None:
            self._stop_jog(f"leaving {before}")
        self.control, self.phase, self.posture_method = control, phase, method
        self.transitions += 1
        self.events.append(("mode_transition", f"{before} → {self.label}" + (f": {cause}" if cause else "")))
        self._set_motion(motion)

    def _set_motion(self, motion: MotionMode | None) -> None:
        if motion is self.motion:
            return
        if self.jog_command is not None:
            self._stop_jog(f"motion mode {motion or 'none'}")
        self.events.append(("motion_mode", f"{self.motion or 'none'} → {motion or 'none'}"))
        self.motion = motion

    def _stop_jog(self, why: str) -> None:
        self.events.append(("jog_stopped", f"jog {self.jog_command} stopped: {why}"))
        self.jog_command = None
