"""The trocar motion family: the slave-side motions of a 6-axis forceps arm (Jinno 2014).

:class:`TrocarMotions` is the :class:`~telesurg.services.slave_control.arm.MotionSource` of an
arm whose robot has the trocar motion family (the MH3F): the control modes (non-trocar /
transitional / trocar, :mod:`~telesurg.shared.robots.mh3f.modes`), the motion modes with their
slave-side motions — PTP posture adjustment and jog (:mod:`~telesurg.shared.robots.mh3f.motion`),
direct teach and playback (:mod:`~telesurg.shared.robots.mh3f.teach`) — and the operator
commands on ``slave/<arm>/command`` that drive them. Lease, e-stop, faults, following the master
and the speed limit are the arm core's (:mod:`~telesurg.services.slave_control.arm`): the core
asks this source each period whether it drives the arm and for its joint target.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics.work_frame import ConfiguredWorkFrame, WorkFrame
from telesurg.shared.messages import Command
from telesurg.shared.robots.api import PUSH_POINTS, ArmHandle, ArmReading, AttachedSource, MotionError
from telesurg.shared.robots.mh3f.config import Mh3fConfig
from telesurg.shared.robots.mh3f.keepout import PatientBox, clamp_step, path_problem, pose_problem
from telesurg.shared.robots.mh3f.modes import ControlMode, ControlModes, Jog, MotionMode, Phase
from telesurg.shared.robots.mh3f.motion import (
    SUPPORTED_JOG_AXES,
    JointBrake,
    PtpMotion,
    jog_step,
    ptp_duration,
)
from telesurg.shared.robots.mh3f.teach import (
    NAME_RE,
    Playback,
    TaughtPoint,
    TeachStore,
    direct_teach_step,
    playback_problem,
)
from telesurg.shared.robots.mh3f.trocar import axis_angle_to_trocar, pose_to_trocar, posture_adjust
from telesurg.shared.robots.mh3f.trocar_limits import remove_step
from telesurg.shared.robots.registry import get

if TYPE_CHECKING:
    from collections.abc import Callable

    from telesurg.shared.robots.api import SlaveSettings
    from telesurg.shared.robots.registry import ArmProfile


class TrocarMotions(AttachedSource):
    """The trocar motion family of one arm (a :class:`~telesurg.services.slave_control.arm.MotionSource`).

    Args:
        cfg: slave_control's config (trocar, jog, PTP, playback, teach keys).
        profile: the arm.
        push: the backend's simulated hand (``MujocoBackend.push``), None if it has none.
    """

    def __init__(
        self,
        cfg: SlaveSettings,
        profile: ArmProfile,
        push: Callable[[np.ndarray, float, str], None] | None = None,
    ) -> None:
        self.cfg, self.profile = cfg, profile
        self.rcfg: Mh3fConfig = get(cfg.model).make_config(cfg.robot)  # the robot's knobs
        self.core: ArmHandle | None = None  # set by attach()
        # control modes of Jinno 2014 and the slave-side motion sources (PTP, jog)
        self.modes = ControlModes()
        self.trocar = np.array(self.rcfg.trocar_mm) / 1e3
        self.trocar_taught = self.rcfg.trocar_taught
        self.ptp: PtpMotion | None = None
        self.playback: Playback | None = None
        # the controlled stop of a stopped joint PTP (posture PTP, playback outside trocar mode)
        self.brake: JointBrake | None = None
        self.playback_name = ""
        self.posture_target: np.ndarray | None = None  # joints after the posture adjustment
        self.store = TeachStore(self.rcfg.state_file or None, profile.arm)
        if self.store.current_trocar:
            self.trocar = np.array(self.store.trocars[self.store.current_trocar])
            self.trocar_taught = True
        self.backend_push = push
        # the work jog frame (the laparoscope view); a camera pose stream can replace it
        self.work_frame: WorkFrame = ConfiguredWorkFrame(cfg.work_frame_rpy_deg)
        self.rcm_error_m = 0.0  # last measured RCM error (set by update_modes)
        self._vmax = np.array(profile.max_velocity)
        # the RCM guard of slave-side motions with the forceps in the trocar (rcm_guard_problem)
        self._guarded: object = None  # the motion the guard watches (its floor is its own)
        self._rcm_floor_m = math.inf  # smallest RCM error measured since that motion started
        # a `remove` commanded while the watchdog holds: it starts when the lease is back (monotonic
        # deadline, s; 0 = none), see REMOVE_LEASE_WAIT_S
        self.remove_pending_until = 0.0

    # -- MotionSource ---------------------------------------------------------------------------
    @property
    def q_cmd(self) -> np.ndarray:
        """The arm's last command (the core's)."""
        return self._core.q_cmd

    @property
    def reading(self) -> ArmReading | None:
        """The arm's last reading (the core's)."""
        return self._core.reading

    @property
    def control_mode(self) -> str:
        return self.modes.control_mode

    def state_fields(self) -> tuple[float, tuple[float, float, float]]:
        t = self.trocar
        return round(self.rcm_error_m * 1e3, 4), (float(t[0]), float(t[1]), float(t[2]))

    def blocks_following(self) -> str:
        mode, motion = self.modes.control_mode, self.modes.motion
        if (mode == "non_trocar" and motion is None) or (
            mode in ("non_trocar", "trocar") and motion is MotionMode.MASTER_SLAVE
        ):
            return ""
        return f"master-slave not active in {mode} mode"

    def measure(self, reading: ArmReading, q_cmd: np.ndarray) -> None:
        core = self._core
        note = ""
        with core.lock:
            self.update_modes(reading)
            if self.remove_pending_until:
                note = self._pending_removal(time.monotonic())
            mode_events, self.modes.events = self.modes.events, []
        for kind, text in mode_events:
            core.event(kind, text)
        if note:
            core.event("remove_pending", note, "info" if note.startswith("lease back") else "warning")

    def _pending_removal(self, now: float) -> str:
        """Start the removal commanded during a hold once the lease is back (lock held); the
        event text, or "" while it still waits."""
        m = self.modes
        if m.phase is not Phase.REMOVE or m.jog_command is not None:
            self.remove_pending_until = 0.0  # left the removal or jogging already: nothing pending
            return ""
        if self._core.ctl.lease_valid and not self._core.estop:
            self.remove_pending_until = 0.0
            r = m.remove()
            return f"lease back: {r.reason}"
        if now > self.remove_pending_until:
            self.remove_pending_until = 0.0
            why = self._core.ctl.reason
            return f"remove: no lease within {REMOVE_LEASE_WAIT_S:g} s ({why}); send remove again"
        return ""

    def command(self, cmd: Command) -> tuple[bool, str]:
        """Answer one operator command (zenoh thread)."""
        with self._core.lock:
            return self._command(cmd)

    def next(self, q_cmd: np.ndarray, reading: ArmReading, dt: float) -> np.ndarray:
        """The joint target of this period's slave-side motion (PTP, jog, playback, direct teach)."""
        rcfg = self.rcfg
        with self._core.lock:
            self.brake = None  # a motion drives the arm: no stop of an earlier one goes on
            motion = self.modes.motion
            job = Internal(
                self.modes.jog_command,
                self.ptp,
                self.playback,
                motion is MotionMode.DIRECT_TEACH,
                self.modes.control_mode,
                self.modes.phase,
            )
        if stray := self.rcm_guard_problem(job):
            raise MotionError(stray)
        try:
            if job.ptp is not None:
                target = job.ptp.next(dt)
            elif job.playback is not None:
                target = job.playback.next(q_cmd, dt)
            elif job.jog is not None and job.phase is Phase.REMOVE and _is_retraction(job.jog):
                # the way out: straight back along the axis, pivoting about the trocar where the
                # straight way would leave the arm's reach (trocar_limits.remove_step)
                def removal(f: float) -> tuple[np.ndarray, bool]:
                    return remove_step(
                        q_cmd,
                        self.trocar,
                        f * rcfg.jog_speed_mm_s / 1e3 * dt,
                        pivot_rad=f * REMOVE_PIVOT_RAD_S * dt,
                    )

                target, pivoted = self.paced(job, q_cmd, dt, removal)
                if pivoted and not self.remove_pivoting:
                    self._core.event(
                        "remove_pivot",
                        "removal pivots about the trocar: the straight way out leaves the arm's reach",
                    )
                self.remove_pivoting = pivoted
            elif job.jog is not None:
                jog = job.jog

                def jogged(f: float) -> tuple[np.ndarray, bool]:
                    return jog_step(
                        q_cmd,
                        jog.frame.value,
                        jog.axis,
                        jog.direction,
                        dt,
                        speed_m_s=f * rcfg.jog_speed_mm_s / 1e3,
                        joint_speed_rad_s=f * np.radians(rcfg.jog_joint_speed_deg_s),
                        trocar=self.trocar if job.mode == "trocar" else None,
                        work=self.work_frame.rotation(),
                    ), False

                target = self.paced(job, q_cmd, dt, jogged)[0]
                pt = self.posture_target
                if job.phase is Phase.POSTURE and pt is not None and jog.axis in ("j4", "j5"):
                    j = int(jog.axis[1]) - 1  # a posture jog stops exactly at its target, never past it
                    if (target[j] - pt[j]) * jog.direction > 0:
                        target[j] = pt[j]
            else:
                tau = reading.external_torque
                if tau is None:
                    raise IKError("direct teach needs an external torque estimate from the backend")
                target = direct_teach_step(
                    q_cmd,
                    tau,
                    dt,
                    "posture" if job.phase is Phase.POSTURE else job.mode,
                    rcfg.teach,
                    trocar=self.trocar,
                    posture_target=self.posture_target,
                )
            p = self.profile
            if not all(lo <= v <= hi for v, lo, hi in zip(target.tolist(), p.lower, p.upper, strict=True)):
                raise IKError("a joint limit is reached")
            box = self.patient_box()  # checked before it is commanded; a pose already crossing
            # (a start inside the box) may move, or it could never get out
            if (problem := pose_problem(target, box)) and pose_problem(q_cmd, box) is None:
                raise IKError(f"patient keep-out: {problem}")
        except (IKError, KinematicsError) as exc:
            if job.teach:  # direct teach: do not follow this push, stay in the mode
                return q_cmd
            raise MotionError(str(exc)) from exc
        out: np.ndarray = target
        return out

    def patient_box(self) -> PatientBox:
        """The patient keep-out with the current trocar (no entry anywhere while none is taught)."""
        c = self.trocar
        trocar = (float(c[0]), float(c[1]), float(c[2])) if self.trocar_taught else None
        box = self._box
        if box is None or box.trocar != trocar:  # built again only when the trocar changes
            lo, hi = self.cfg.patient_box_min_mm, self.cfg.patient_box_max_mm
            box = self._box = PatientBox(
                (lo[0] / 1e3, lo[1] / 1e3, lo[2] / 1e3), (hi[0] / 1e3, hi[1] / 1e3, hi[2] / 1e3), trocar
            )
        return box

    _box: PatientBox | None = None

    def follow_keepout(self, q_from: np.ndarray, q_to: np.ndarray) -> tuple[np.ndarray, str]:
        """Master–slave in every control mode, and any ``servo_jp`` (a policy): the followed step
        is clamped at the patient box's surface unless the forceps enters through the trocar
        (:func:`~telesurg.shared.robots.mh3f.keepout.clamp_step`; trocar-mode setpoints, RCM-exact
        by the trocar IK, pass)."""
        q, why = clamp_step(q_from, q_to, self.patient_box(), explain=not self._follow_clamped)
        self._follow_clamped = why is not None  # (where it crosses: said once, at the clamp's start)
        return q, f"patient keep-out: {why}" if why else ""

    _follow_clamped = False  # the last followed step was clamped

    def rcm_guard_problem(self, job: Internal) -> str:
        """Why the slave-side motion ``job`` must stop for the RCM ("" = it may go on).

        With the forceps in the trocar (trocar mode, insertion, removal) the measured RCM error
        (MuJoCo's tip pose, 100 Hz) of a running motion may not exceed :data:`RCM_STOP_MM`, nor
        grow more than :data:`RCM_STOP_SLACK_MM` above the smallest error measured since the
        motion started — so a removal that starts off the trocar (the way out of an RCM hold) may
        run while it does not stray further, and any motion that strays is stopped before the
        shaft can leave the cannula (its command, RCM-exact, then pulls the arm back).
        """
        motion: object = job.ptp or job.playback or job.jog or ("teach" if job.teach else None)
        inside = job.mode == "trocar" or job.phase in (Phase.INSERT, Phase.REMOVE)
        if motion is None or not inside:
            self._guarded = None
            return ""
        if motion is not self._guarded:
            self._guarded, self._rcm_floor_m = motion, math.inf
        rcm = self.rcm_error_m
        self._rcm_floor_m = min(self._rcm_floor_m, rcm)
        limit = max(RCM_STOP_MM / 1e3, self._rcm_floor_m + RCM_STOP_SLACK_MM / 1e3)
        if rcm <= limit:
            return ""
        self._guarded = None
        return (
            f"RCM error {rcm * 1e3:.2f} mm > {limit * 1e3:.2f} mm (the forceps strays from the trocar; "
            f"stop at {RCM_STOP_MM:g} mm, or {RCM_STOP_SLACK_MM:g} mm above the motion's smallest)"
        )

    def paced(
        self,
        job: Internal,
        q_cmd: np.ndarray,
        dt: float,
        solve: Callable[[float], tuple[np.ndarray, bool]],
    ) -> tuple[np.ndarray, bool]:
        """One period of a jog, paced where the forceps is in the trocar (trocar mode, insertion,
        removal): ``solve(f)`` is the jog's step at the fraction ``f`` of its speed.

        The MuJoCo arm's position servos answer fast joint motion each at its own pace (force
        limits, inertia): a trocar-mode jog at 40 mm/s that asked for 2–4 rad/s, or for a
        speed-clipped joint step near the reach limit, left the measured RCM by up to 15 mm
        (offline, ``tests/test_trocar_jog_pace.py``) though every command was RCM-exact. So the
        jog starts over :data:`TROCAR_JOG_RAMP_S`, slows so no joint goes faster than
        :data:`TROCAR_JOG_SPEED_CAP` × its limit, and stops (with the reason) where a period would
        need more than :data:`TROCAR_JOG_JUMP` × the limits at full speed (the reach limit, a
        singularity: the step is no longer a small motion). Elsewhere ``solve(1.0)``.
        """
        if not (job.mode == "trocar" or job.phase in (Phase.INSERT, Phase.REMOVE)):
            return solve(1.0)
        if job.jog is not self._paced_jog:
            self._paced_jog, self._paced_s = job.jog, 0.0
        self._paced_s += dt
        f = min(1.0, self._paced_s / TROCAR_JOG_RAMP_S)
        target, extra = solve(f)
        ratio = np.abs(target - q_cmd) / (self._vmax * dt)
        worst = float(ratio.max())
        if worst / f > TROCAR_JOG_JUMP:
            j = int(np.argmax(ratio))
            raise IKError(
                f"the jog would move J{j + 1} at {worst / f:.1f}× its speed limit: near the reach "
                "limit or a singularity"
            )
        if worst > TROCAR_JOG_SPEED_CAP:
            target, extra = solve(f * TROCAR_JOG_SPEED_CAP / worst)
        return target, extra

    _paced_jog: object = None  # the jog being paced (its ramp is its own)
    _paced_s = 0.0  # s since it started
    remove_pivoting = False  # the removal is pivoting about the trocar (for its event)

    def reached(self, q_out: np.ndarray, reading: ArmReading) -> None:
        core = self._core
        ptp = self.ptp
        if ptp is not None and ptp.done and np.allclose(q_out, ptp.q_to, atol=1e-9):
            with core.lock:
                self.ptp = None
            core.event("ptp_done", "posture adjustment PTP reached its target")
        pb = self.playback
        if pb is not None:
            for i in pb.reached:
                err = float(np.linalg.norm(reading.tip_position - np.array(pb.points[i].tip))) * 1e3
                core.event(
                    "point_reached",
                    f"{self.playback_name} point {i + 1}/{len(pb.points)}: "
                    f"tip {err:.3f} mm from the taught point",
                )
            pb.reached.clear()
            if pb.done:
                with core.lock:
                    if self.playback is pb:
                        self.playback = None
                core.event("playback_done", f"playback of {self.playback_name} finished")

    def _command(self, cmd: Command) -> tuple[bool, str]:
        m, a = self.modes, cmd.arg_map()
        estop = self._core.estop
        if estop and cmd.name not in ("state", "stop", "abort"):
            return False, f"{cmd.name} refused: {estop} (reset first)"
        if cmd.name in STARTS_MOTION and self.brake is not None and not self.brake.done:
            return False, (
                f"{cmd.name} refused: the arm is still stopping (a stopped PTP ramps down over "
                f"{PTP_STOP_RAMP_S * 1e3:.0f} ms along its path); send it again"
            )
        if cmd.name == "state":
            allowed = "; ".join(f"{k}: {', '.join(v)}" for k, v in m.allowed().items() if v)
            return True, f"{m.label}, motion {m.motion or 'none'}; allowed: {allowed}"[:500]
        if cmd.name == "teach_trocar":
            name = a.get("name", "default")
            if not NAME_RE.match(name):
                return False, f"teach_trocar refused: invalid name {name!r}"
            r = m.teach_trocar()
            if r.accepted:
                tip = self.reading.tip_position.copy() if self.reading is not None else self.trocar
                self.trocar = tip.copy()
                self.trocar_taught = True
                self.store.trocars[name] = (float(tip[0]), float(tip[1]), float(tip[2]))
                self.store.current_trocar = name
                self.store.save()
                mm = ", ".join(f"{v * 1e3:.1f}" for v in self.trocar)
                return True, f"trocar {name!r} taught at ({mm}) mm"
            return r.accepted, r.reason
        if cmd.name == "begin_posture_adjust":
            return self._begin_posture(a.get("method", "ptp"), a.get("program", ""))
        if cmd.name in ("finish_posture_adjust", "insert", "remove"):
            if self.ptp is not None:
                return False, f"{cmd.name} refused: the PTP posture motion is still running"
            if self.playback is not None:
                return False, f"{cmd.name} refused: playback of {self.playback_name!r} is still running"
            r = getattr(m, cmd.name)()
            if r.accepted and cmd.name == "finish_posture_adjust":
                self.posture_target = None
            if r.accepted and cmd.name == "remove" and not self._core.ctl.lease_valid:
                # the watchdog holds (e.g. for the RCM error in trocar mode, which it does not judge
                # in transitional/remove): the removal waits for the lease, the arm does not move
                m.jog_command = None
                self.remove_pending_until = time.monotonic() + REMOVE_LEASE_WAIT_S
                return True, (
                    f"{r.reason}; no lease now ({self._core.ctl.reason or 'held'}): the removal starts "
                    f"when the watchdog allows motion (within {REMOVE_LEASE_WAIT_S:g} s, else remove again)"
                )
            return r.accepted, r.reason
        if cmd.name in ("stop", "abort", "jog", "set_motion_mode"):
            self.remove_pending_until = 0.0
        if cmd.name == "stop":
            if self.playback is not None:
                self._halt_joint_ptp()
                return True, f"playback of {self.playback_name!r} stopped"
            r = m.stop()
            return r.accepted, r.reason
        if cmd.name == "abort":
            self._halt_joint_ptp()
            r = m.abort(a.get("reason", "operator abort"))
            if m.phase is None:
                self.posture_target = None
            return r.accepted, r.reason
        if cmd.name == "set_motion_mode":
            before = m.motion
            r = m.set_motion_mode(a.get("mode", ""))
            if r.accepted and m.motion is not before:
                self._halt_joint_ptp()  # a new motion mode ends a running playback
            return r.accepted, r.reason
        if cmd.name in ("teach_point", "clear_program", "play"):
            return self._program_command(cmd.name, a.get("program", ""))
        if cmd.name == "programs":
            names = ", ".join(f"{k} ({len(v)} points)" for k, v in sorted(self.store.programs.items()))
            trocars = ", ".join(sorted(self.store.trocars))
            return True, f"programs: {names or 'none'}; trocars: {trocars or 'none'}"[:500]
        if cmd.name == "load_trocar":
            return self._load_trocar(a.get("name", ""))
        if cmd.name == "push":
            return self._push(a)
        if cmd.name == "jog":
            axis = a.get("axis", "")
            if axis not in SUPPORTED_JOG_AXES:
                return (
                    False,
                    f"jog refused: axis {axis!r} not supported; valid: {', '.join(SUPPORTED_JOG_AXES)}",
                )
            try:
                direction = int(a.get("direction", "1"))
            except ValueError:
                return False, f"jog refused: direction {a.get('direction')!r} must be 1 or -1"
            r = m.jog(a.get("frame", "base"), axis, direction)
            return r.accepted, r.reason
        return False, f"unknown command {cmd.name!r}; valid: {', '.join(COMMANDS)}"

    def _begin_posture(self, method: str, program: str) -> tuple[bool, str]:
        """begin_posture_adjust: target J4/J5 (ptp, jog, direct_teach) or an aligned program."""
        m = self.modes
        angle: float | None = None
        if method == "playback":
            pts = self.store.programs.get(program)
            if pts is None:
                return False, f"begin_posture_adjust refused: no program {program!r} (teach_point first)"
            if problem := playback_problem(pts, "non_trocar", self.trocar if self.trocar_taught else None):
                return False, f"begin_posture_adjust refused: program {program!r}: {problem}"
            angle = axis_angle_to_trocar(np.array(pts[-1].q), self.trocar)
            target = np.array(pts[-1].q)
        else:
            try:
                target = posture_adjust(self.q_cmd, self.trocar)
            except (IKError, KinematicsError) as exc:
                return False, f"begin_posture_adjust refused: {exc}"
        if method in ("ptp", "playback"):  # planned joint path, checked at fine steps before it starts
            path = [self.q_cmd, target]
            if method == "playback":
                path = [self.q_cmd] + [np.array(pt.q) for pt in self.store.programs[program]]
            for qa, qb in itertools.pairwise(path):
                if crossing := path_problem(qa, qb, self.patient_box()):
                    return False, f"begin_posture_adjust refused: patient keep-out: {crossing}"
        r = m.begin_posture_adjust(method, program_axis_angle_rad=angle)
        if not r.accepted:
            return r.accepted, r.reason
        self.posture_target = target
        if self.reading is not None:  # the machine knows the J4/J5 distance at once (posture jog)
            self.update_modes(self.reading)
        j45 = np.degrees(target[3:5] - self.q_cmd[3:5])
        to_go = f"J4 {j45[0]:+.1f}°, J5 {j45[1]:+.1f}° to go"
        if method == "ptp":
            duration = ptp_duration(self.q_cmd, target, self.rcfg.ptp_speed_fraction)
            self.ptp = PtpMotion(self.q_cmd.copy(), target, duration)
            return True, f"{r.reason}; PTP of J4/J5 over {duration:.1f} s"
        if method == "playback":
            self._start_playback(program, "non_trocar")
            return True, f"{r.reason}; playing {program!r} ({len(self.store.programs[program])} points)"
        if method == "jog":
            return True, f"{r.reason}; jog J4/J5 toward the target ({to_go})"
        return True, f"{r.reason}; push the forceps: J4/J5 follow toward the target ({to_go})"

    def _start_playback(self, program: str, mode: str) -> None:
        self.playback_name = program
        self.playback = Playback(
            list(self.store.programs[program]),
            mode,
            self.trocar.copy() if mode == "trocar" else None,
            self._vmax * self.rcfg.ptp_speed_fraction,
            self.rcfg.playback_speed_mm_s / 1e3,
            self.rcfg.playback_dwell_s,
        )

    def _program_command(self, name: str, program: str) -> tuple[bool, str]:
        """teach_point, clear_program, play (lock held)."""
        m = self.modes
        if not NAME_RE.match(program):
            return False, f"{name} refused: program={program!r} is not a valid name"
        if self.playback is not None:
            return False, f"{name} refused: playback of {self.playback_name!r} is running (stop it first)"
        if name == "clear_program":
            if self.store.programs.pop(program, None) is None:
                return False, f"clear_program refused: no program {program!r}"
            self.store.save()
            return True, f"program {program!r} cleared"
        if name == "teach_point":
            if self.reading is None:
                return False, "teach_point refused: no measurement yet"
            if self.active() and m.motion is not MotionMode.DIRECT_TEACH:
                return False, "teach_point refused: the arm is moving (stop first)"
            r = self.reading
            tip = (float(r.tip_position[0]), float(r.tip_position[1]), float(r.tip_position[2]))
            point = TaughtPoint(tuple(float(v) for v in r.position), tip, m.control_mode)
            if problem := self.store.add_point(program, point):
                return False, f"teach_point refused: {problem}"
            self.store.save()
            n = len(self.store.programs[program])
            mm = ", ".join(f"{v * 1e3:.1f}" for v in tip)
            return True, f"point {n} of {program!r} taught at ({mm}) mm in {m.control_mode} mode"
        # play
        if m.motion is not MotionMode.PLAYBACK or m.phase is not None:
            return False, (
                f"play refused in {m.label}: select the playback motion mode in non_trocar or trocar "
                "mode (posture adjustment by playback starts its program itself)"
            )
        pts = self.store.programs.get(program)
        if pts is None:
            return False, f"play refused: no program {program!r}"
        trocar = self.trocar if self.trocar_taught else None
        if problem := playback_problem(pts, m.control_mode, trocar):
            return False, f"play refused: program {program!r}: {problem}"
        if m.control_mode != "trocar":  # joint PTP moves: the planned path, checked before it starts
            path = [self.q_cmd] + [np.array(pt.q) for pt in pts]
            for qa, qb in itertools.pairwise(path):
                if crossing := path_problem(qa, qb, self.patient_box()):
                    return False, f"play refused: program {program!r}: patient keep-out: {crossing}"
        self._start_playback(program, m.control_mode)
        return True, f"playing {program!r} ({len(pts)} points) in {m.control_mode} mode"

    def _load_trocar(self, name: str) -> tuple[bool, str]:
        if name not in self.store.trocars:
            known = ", ".join(sorted(self.store.trocars)) or "none"
            return False, f"load_trocar refused: no trocar {name!r} (taught: {known})"
        if self.modes.control is not ControlMode.NON_TROCAR:
            where = self.modes.label
            return False, f"load_trocar refused in {where}: the trocar changes in non_trocar mode only"
        self.trocar = np.array(self.store.trocars[name])
        self.trocar_taught = True
        self.store.current_trocar = name
        self.store.save()
        mm = ", ".join(f"{v * 1e3:.1f}" for v in self.trocar)
        return True, f"trocar {name!r} loaded: ({mm}) mm"

    def _push(self, a: dict[str, str]) -> tuple[bool, str]:
        """Simulated hand: push the forceps tip (MuJoCo only)."""
        if self.backend_push is None:
            return False, f"push refused: the {self.cfg.backend} backend has no simulated hand"
        try:
            f = np.array([float(a.get(k, "0")) for k in ("fx", "fy", "fz")])
            seconds = float(a.get("seconds", "1"))
        except ValueError:
            return False, "push refused: fx, fy, fz (N) and seconds must be numbers"
        if not (np.all(np.isfinite(f)) and np.linalg.norm(f) <= 100.0 and 0.0 < seconds <= 10.0):
            return False, "push refused: |force| must be ≤ 100 N and 0 < seconds ≤ 10"
        at = a.get("at", "tip")
        if at not in PUSH_POINTS:
            return False, f"push refused: at={at!r}; valid: {', '.join(PUSH_POINTS)}"
        self.backend_push(f, seconds, at)
        return True, f"pushing the {at} with ({f[0]:.1f}, {f[1]:.1f}, {f[2]:.1f}) N for {seconds:.2f} s"

    def stop(self, reason: str = "stopped") -> None:
        """Cancel the slave-side motion (PTP, jog, playback, direct teach); the operator must
        command it again (the core's lock held). A joint PTP ramps down along its path
        (:meth:`braking`)."""
        self._halt_joint_ptp()
        if self.modes.jog_command is not None:
            self.modes.stop()
        if self.modes.motion is MotionMode.DIRECT_TEACH:
            self.modes.abort(reason)
            if self.modes.phase is None:
                self.posture_target = None

    def _halt_joint_ptp(self) -> None:
        """End the PTP and the playback (lock held); a joint PTP under way gets its controlled
        stop (:data:`PTP_STOP_RAMP_S`) along its path, checked before it started."""
        brake = self.ptp.brake(PTP_STOP_RAMP_S) if self.ptp is not None else None
        if brake is None and self.playback is not None:
            brake = self.playback.brake(PTP_STOP_RAMP_S)
        if brake is not None and self.brake is None:
            self.brake = brake
        self.ptp = self.playback = None

    def braking(self, q_cmd: np.ndarray, dt: float, allowed: bool) -> np.ndarray | None:
        """This period's target of a stopped joint PTP's controlled stop, or None (see
        :meth:`~telesurg.services.slave_control.arm.MotionSource.braking`). Every target is
        checked against the patient keep-out like a motion's: a crossing ends the stop at once."""
        with self._core.lock:
            brake = self.brake
            if brake is None:
                return None
            if not allowed or brake.done:
                self.brake = None
                return None
            target = brake.next(dt)
            box = self.patient_box()
            if pose_problem(target, box) and pose_problem(q_cmd, box) is None:
                self.brake = None
                return None
            return target

    def active(self) -> bool:
        """A slave-side motion is commanded (lock held by the caller): PTP, jog, playback, or
        direct teach (the arm moves when pushed)."""
        return (
            self.ptp is not None
            or self.modes.jog_command is not None
            or self.playback is not None
            or self.modes.motion is MotionMode.DIRECT_TEACH
        )

    def update_modes(self, reading: ArmReading) -> None:
        """Measure the forceps against the trocar and feed the control-mode machine (lock held).

        RCM error and depth come from the measured tip pose (MuJoCo's tip site); the axis angle
        from the measured joints. The RCM error is kept for ``operating_state``.
        """
        axis = reading.tip_pose[:3, 0]  # the forceps axis
        rcm, depth = pose_to_trocar(reading.tip_position, axis, self.trocar)
        self.rcm_error_m = rcm
        try:
            angle: float | None = axis_angle_to_trocar(reading.position, self.trocar)
        except KinematicsError:  # the trocar at the wrist centre: no direction to it
            angle = None
        j45 = None
        if self.posture_target is not None:
            d = self.posture_target[3:5] - reading.position[3:5]
            j45 = (float(d[0]), float(d[1]))
        self.modes.update(depth, angle, self.trocar_taught, j45_to_target_rad=j45)
        if self.modes.phase is None:
            self.posture_target = None


#: Operator commands served on ``slave/<arm>/command`` (args as ``key=value``).
COMMANDS = (
    "state",
    "teach_trocar",
    "begin_posture_adjust",
    "finish_posture_adjust",
    "insert",
    "remove",
    "stop",
    "abort",
    "set_motion_mode",
    "jog",
    "teach_point",
    "clear_program",
    "programs",
    "play",
    "load_trocar",
    "push",
)


#: Commands that start a motion: refused while a stopped joint PTP still ramps down (its stop
#: runs from the command it had reached, not from where a new motion's path would be checked)
STARTS_MOTION = ("begin_posture_adjust", "finish_posture_adjust", "insert", "remove", "jog", "play", "push")


@dataclass
class Internal:
    """The slave-side motion of one control period (a snapshot taken under the lock)."""

    jog: Jog | None
    ptp: PtpMotion | None
    playback: Playback | None
    teach: bool  # direct teach: the arm follows a push
    mode: str  # control mode
    phase: Phase | None


REMOVE_PIVOT_RAD_S = 0.25  # rad/s: pivot speed of the forceps about the trocar during removal
#: Pacing of the jogs with the forceps in the trocar (TrocarMotions.paced): the fastest joint at
#: most this fraction of its speed limit (the mapping's trocar-mode master–slave: 0.7) ...
TROCAR_JOG_SPEED_CAP = 0.5
#: ... a step needing more than this × the limits at full jog speed stops the jog (reach, singularity)
TROCAR_JOG_JUMP = 4.0
#: s: ... and the jog speed ramps up over this time from its start (no velocity step for the servos)
TROCAR_JOG_RAMP_S = 0.15
#: mm: a slave-side motion with the forceps in the trocar stops when the measured RCM error
#: exceeds this (below the watchdog's 2 mm hold in trocar mode and the 5.5 mm cannula radius)
RCM_STOP_MM = 1.5
#: mm: ... or grows this much above the smallest error measured since the motion started (a
#: removal starting off the trocar may run while it does not stray further)
RCM_STOP_SLACK_MM = 0.25
#: s: a stopped joint PTP (posture PTP, playback outside trocar mode: stop, abort, a hold) ramps
#: its speed down to zero along its planned — checked — path over this time: the MuJoCo arm at 0.8
#: × the joint limits, its command frozen at once, left the path by up to 15 mrad (J5 at its force
#: limit); ramped over 30 ms, by at most 0.8 mrad (tests/test_ptp_tracking.py)
PTP_STOP_RAMP_S = 0.03
#: s: a `remove` commanded while the watchdog holds starts when the lease is back within this time
REMOVE_LEASE_WAIT_S = 5.0


def _is_retraction(jog: Jog) -> bool:
    """The removal jog: outward along the forceps axis."""
    return jog.frame.value == "forceps" and jog.axis == "x" and jog.direction < 0
