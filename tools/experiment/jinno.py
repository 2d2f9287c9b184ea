"""``telesurg experiment jinno-insertion``: Jinno 2014's evaluation, in simulation, through the services.

Reproduces the paper's "Results and discussion" with the trocar at (500, 0, 200) mm:

* **Fig. 9** — posture adjustment by point-to-point (PTP), jog and direct teach of J4/J5 from the
  same start, each followed by the insert motion through the trocar (and removal);
* **Fig. 10** — posture adjustment by PTP from three different starts, each followed by insertion;
  every insertion in Figs. 9 and 10 is followed by master–slave motion in trocar mode (a 20 mm
  master circle, one lap) before the removal;
* **Figs. 11–13** — after a last insertion, master–slave tracing of a target path (a circle drawn
  by the master) in trocar mode, with the RCM error from MuJoCo.

The master is the paper's (Fig. 7): the mapping runs ``master_mode = "virtual_trocar"``, the
master position is the handle of a dummy forceps pivoting in a virtual trocar and its tip is what
the slave tip follows. The RCM error is reported twice: from slave_control's ``operating_state``
(MuJoCo's tip pose, 20 Hz) and from the measured joints at their full rate (``measured_js``, by
forward kinematics), over all of trocar mode.

Everything runs as a user would run it: router, watchdog, slave_control (MuJoCo), mapping as
separate processes; this process is the operator console (commands over the command queryable,
the simulated hand for direct teach) and the master (pose + clutch pedal at 250 Hz, like
``master_capture``). The starts are programs in slave_control's teach store, reached by teaching
playback; after every removal the forceps backs off 60 mm along its axis before the next start.

The RCM error is slave_control's measurement from MuJoCo's tip-site pose (distance from the trocar
point to the forceps axis), never from commands. Output: ``metrics.json`` and PNG figures.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.services.mapping import MappingConfig
from telesurg.shared import jsonio
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import CartesianPose, MasterButtons
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, jacobian
from telesurg.shared.robots.mh3f.trocar import posture_adjust, rcm_error
from telesurg.shared.teleop.master import master_point
from telesurg.tools.experiment.client import ArmClient, ArmLog

log = logging.getLogger(__name__)

TROCAR_MM = (500.0, 0.0, 200.0)
TROCAR = np.array(TROCAR_MM) / 1e3
#: Starts (rad): B for Fig. 9, A, B, C for Fig. 10, A for the trace. From each, posture adjustment
#: turns J4 and J5 by 43–51° each. Every start's tip lies inside the local site's workspace box
#: (z 707–732 mm, under its 800 mm ceiling: deploy/local/site.toml), and its forceps point down
#: and away from the patient; the aligned postures (J4/J5 toward the trocar) are those of the
#: earlier starts, whose tips stood at z 860–1,225 mm (issue #20).
STARTS: dict[str, tuple[float, ...]] = {
    "start_a": (0.0, -0.2, 0.6, -0.8, -1.0, 0.0),  # tip (585, −356, 729) mm
    "start_b": (0.3, -0.15, 0.55, 0.65, -0.85, 0.0),  # tip (564, 455, 707) mm
    "start_c": (-0.35, -0.3, 0.5, -0.6, -0.9, 0.0),  # tip (492, −457, 732) mm
}
TRACE_RADIUS_M = 0.03  # master circle; × mapping scale 0.5 = a 15 mm circle at the slave tip
TRACE_PERIOD_S = 5.0
TRACE_ATTEMPTS = 5  # a trace interrupted by a hold is traced again, at most this often
TRACE_DEPTH_JOG_S = 1.5  # before the trace the forceps goes this long deeper (at 40 mm/s: +60 mm)
TRACE_LAPS = 2
MS_RADIUS_M = 0.010  # master circle of the master–slave motion after each Fig. 9/10 insertion
MS_LAPS = 1
UNTIL_ATTEMPTS = 40  # a slave-side motion stopped by a hold is commanded again, at most this often
LAP_PROGRAM = "lap_start"  # taught where each master–slave lap starts (trocar mode)

Progress = Callable[[str, float], None]


@dataclass
class Run:
    """One posture adjustment + insertion (+ optional trace) + removal."""

    name: str
    start: str
    method: str
    t0: float = 0.0
    t_aligned: float = 0.0
    t_trocar: float = 0.0
    t_end: float = 0.0
    t_ms_start: float = 0.0  # master–slave motion (or the trace) after the insertion: start
    t_ms_end: float = 0.0  # end of the master–slave motion after the insertion (0: none)
    ms_attempts: int = 0  # laps drawn (a hold of a starved host interrupts one: drawn again)
    ms_whole_lap: bool = True  # one lap was followed throughout
    inserted: bool = False
    removed: bool = False
    posture_s: float = 0.0
    final_axis_deg: float = math.nan
    moved_other_joints_deg: float = math.nan


class Master(threading.Thread):
    """The master console: pose and clutch at 250 Hz; draws the target circle when ``tracing``."""

    def __init__(self, node: Node) -> None:
        super().__init__(daemon=True)
        self.node, self.clutch, self.stop = node, False, threading.Event()
        self.trace_t0: float | None = None
        self.radius = TRACE_RADIUS_M
        k = node.keys
        self.pose = node.outlet(k.master("m1", "measured_cp"))
        self.buttons = node.outlet(k.master("m1", "buttons"))
        self.log: list[tuple[float, float, float, float]] = []  # (t, x, y, z) while tracing

    def target(self, t: float) -> tuple[float, float, float]:
        if self.trace_t0 is None:
            return (0.0, 0.0, 0.0)
        a = 2 * math.pi * (t - self.trace_t0) / TRACE_PERIOD_S
        # the handle circle lies on the +x side of the start; through the virtual trocar the
        # dummy tip (what the slave tip follows) moves on the -x side, toward the robot
        r = self.radius
        return (r * (1.0 - math.cos(a)), r * math.sin(a), 0.0)

    def run(self) -> None:
        t0 = time.monotonic()
        n = 0
        while not self.stop.is_set():
            now = time.monotonic()
            p = self.target(now)
            self.buttons.put(MasterButtons(self.buttons.header(), self.clutch, True))
            self.pose.put(CartesianPose(self.pose.header(), "master", p, (0.0, 0.0, 0.0, 1.0)))
            if self.trace_t0 is not None:
                self.log.append((now, *p))
            n += 1
            self.stop.wait(max(0.0, t0 + n / 250 - time.monotonic()))


def _write_store(path: Path) -> None:
    """Teach store with the trocar and one single-point program per start (joints → FK tip)."""
    from telesurg.shared.robots.mh3f.teach import TaughtPoint, TeachStore

    store = TeachStore(None, "arm1")
    store.path = path
    store.trocars["port"] = (float(TROCAR[0]), float(TROCAR[1]), float(TROCAR[2]))
    store.current_trocar = "port"
    for name, q in STARTS.items():
        tip = fk(np.array(q), MH3F)[:3, 3]
        store.add_point(name, TaughtPoint(q, (float(tip[0]), float(tip[1]), float(tip[2])), "non_trocar"))
    store.save()


class Experiment:
    """The operator's procedure (commands, pushes, master) over one running site."""

    def __init__(self, arm: ArmClient, master: Master, progress: Progress) -> None:
        self.arm, self.master, self.progress = arm, master, progress
        self.runs: list[Run] = []
        self.trace: tuple[float, float] = (0.0, 0.0)
        self.trace_attempts = 0

    def _must_wait(self, pred: Callable[[], bool], timeout: float, what: str) -> None:
        if not self.arm.wait(pred, timeout):
            raise RuntimeError(f"{what} (within {timeout:.0f} s)")

    def _finished(self, done: str, since: float, timeout: float = 30.0) -> bool:
        """Wait for the event ``done`` of a slave-side motion started at ``since``: True; False as
        soon as a hold (a scheduling stall of a busy host) or a stop ended it first."""
        a = self.arm

        def over() -> bool:
            return any(a.events_of(kind, since) for kind in (done, "hold", "motion_stopped"))

        a.wait(over, timeout)
        return bool(a.events_of(done, since))

    def _lease_back(self) -> None:
        """After a hold: wait until the lease has been back for 0.3 s (operating_state is 20 Hz;
        the watchdog keeps a HOLD latched a while after its cause clears)."""
        a = self.arm
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            if a.wait(a.lease_ok, 1) and not a.wait(lambda: not a.lease_ok(), 0.3):
                return

    def go_to(self, start: str) -> None:
        a = self.arm
        for _ in range(UNTIL_ATTEMPTS):  # a hold stops the playback: play it again, as an operator would
            self._lease_back()
            a.send("set_motion_mode", "mode=playback")
            t = time.monotonic()
            if a.send("play", f"program={start}").accepted and self._finished("playback_done", t):
                a.settle()
                return
        raise RuntimeError(f"playback of {start} never finished")

    def mark_lap_start(self) -> None:
        """Teach where a master–slave lap starts (trocar mode, program ``LAP_PROGRAM``)."""
        a = self.arm
        a.send("clear_program", f"program={LAP_PROGRAM}")  # (refused if there is none yet)
        a.must("teach_point", f"program={LAP_PROGRAM}")

    def back_to_lap_start(self) -> None:
        """After a lap a hold interrupted: back to where it started, by trocar-mode playback.

        The mapping is incremental: the slave stopped where the hold caught it while the master
        drew on, and the next lap starts from there. Without this, every interrupted lap moved
        the start by up to the circle's diameter, and after a few the forceps stood where the
        removal jog was infeasible ("the jog would move J3 at 12.8× its speed limit": never came
        back out). An operator brings the tool back before drawing again."""
        a = self.arm
        for _ in range(UNTIL_ATTEMPTS):
            self._lease_back()
            a.send("set_motion_mode", "mode=playback")
            t = time.monotonic()
            if a.send("play", f"program={LAP_PROGRAM}").accepted and self._finished("playback_done", t):
                break
        else:
            raise RuntimeError("the playback back to the lap's start never finished")
        a.settle()
        a.must("set_motion_mode", "mode=master_slave")
        time.sleep(0.3)

    def adjust(self, run: Run) -> None:
        """Posture adjustment by ``run.method``, until finish_posture_adjust is accepted."""
        a = self.arm
        q0 = a.q()
        target = posture_adjust(q0, TROCAR)
        t = t_begin = time.monotonic()
        a.must("begin_posture_adjust", f"method={run.method}")

        def in_posture() -> None:  # a hold aborts the posture adjustment: begin it again
            if a.mode() == "non_trocar":
                self._lease_back()
                if a.send("begin_posture_adjust", f"method={run.method}").accepted:
                    a.wait(lambda: a.mode() != "non_trocar", 2)  # (operating_state: 20 Hz)

        if run.method == "ptp":
            for _ in range(UNTIL_ATTEMPTS):  # a hold stops the PTP: back outside, adjust again
                if self._finished("ptp_done", t):
                    break
                a.send("abort", "reason=held during the PTP")
                self._lease_back()
                t = time.monotonic()
                a.must("begin_posture_adjust", f"method={run.method}")
            else:
                raise RuntimeError("the PTP never finished")
        elif run.method == "jog":
            for j in (4, 5):
                for _ in range(UNTIL_ATTEMPTS):  # a hold of a starved host stops the jog: jog again
                    togo = target[j - 1] - a.q()[j - 1]
                    if abs(togo) < math.radians(0.01):  # (slave_control's posture-jog deadband)
                        break
                    self._lease_back()
                    in_posture()
                    tj = time.monotonic()
                    a.must("jog", "frame=joint", f"axis=j{j}", f"direction={1 if togo > 0 else -1}")
                    if not a.wait_event("jog_stopped", tj, 40):  # the jog stops itself at the target
                        raise RuntimeError(f"the J{j} jog never reached its target")
                    a.settle()
        else:  # direct teach: push the tip the way J4/J5 must turn, as a person would
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                q = a.q()
                d45 = (target - q)[3:5]
                if np.max(np.abs(d45)) < math.radians(0.01):  # J4/J5 stop exactly at the target
                    break
                self._lease_back()
                in_posture()
                v = jacobian(q, MH3F)[:3, 3:5] @ d45
                f = 25.0 * v / np.linalg.norm(v)
                a.must("push", f"fx={f[0]:.2f}", f"fy={f[1]:.2f}", f"fz={f[2]:.2f}", "seconds=0.4")
                time.sleep(0.45)
        deadline = time.monotonic() + 5
        while not a.send("finish_posture_adjust").accepted:  # let the servo settle into alignment
            if run.method != "ptp":
                in_posture()  # (aborted by a hold at the very end: aligned already, begin again)
            if time.monotonic() > deadline:
                raise RuntimeError(f"finish_posture_adjust never accepted (mode {a.mode()})")
            time.sleep(0.1)
        run.t_aligned = time.monotonic()
        run.posture_s = run.t_aligned - t_begin  # (any attempts a hold cut short included)
        q1 = a.q()
        run.moved_other_joints_deg = float(np.degrees(np.abs(q1 - q0)[[0, 1, 2, 5]]).max())

    def insert(self, run: Run) -> None:
        self._until("insert", "trocar", "never reached trocar mode")
        run.t_trocar = time.monotonic()
        run.inserted = True

    def _until(self, command: str, mode: str, what: str) -> None:
        """Send ``command`` until the arm reaches ``mode``: a watchdog hold (a scheduling stall of a
        busy host) stops a slave-side motion, and the operator simply commands it again."""
        a = self.arm
        for _ in range(UNTIL_ATTEMPTS):
            t = time.monotonic()
            a.must(command)

            def done_or_stopped(t: float = t) -> bool:
                return a.mode() == mode or bool(a.events_of("hold", t) or a.events_of("motion_stopped", t))

            if a.wait(done_or_stopped, 30) and a.wait(lambda: a.mode() == mode, 0.3):
                return
            self._lease_back()  # stopped by a hold: command it again once the lease is back
        raise RuntimeError(what)

    def remove(self) -> None:
        a = self.arm
        self._until("remove", "non_trocar", "never came back out")
        a.must("set_motion_mode", "mode=jog")  # back off along the axis before moving elsewhere
        a.must("jog", "frame=forceps", "axis=x", "direction=-1")
        time.sleep(1.5)
        a.must("stop")
        a.settle()

    def trace_circle(self) -> None:
        a, m = self.arm, self.master
        a.must("set_motion_mode", "mode=jog")  # deeper first: ~110 mm, where surgery happens
        a.must("jog", "frame=forceps", "axis=x", "direction=1")
        time.sleep(TRACE_DEPTH_JOG_S)
        a.must("stop")
        a.settle()
        self.mark_lap_start()
        a.must("set_motion_mode", "mode=master_slave")
        time.sleep(0.3)
        # Like an operator, trace again if the slave stopped following during the lap (a hold on
        # a starved machine), from where the first lap started: the trace is judged on a lap the
        # slave followed throughout.
        for attempt in range(1, TRACE_ATTEMPTS + 1):
            self.trace_attempts = attempt
            if attempt > 1:
                self.back_to_lap_start()
            self._lease_back()
            m.clutch = True  # press the pedal: engage
            if not a.wait(lambda: bool(a.log.states) and a.log.states[-1][4], 5):
                m.clutch = False  # refused (a hold): release, and press again once the lease is back
                time.sleep(0.5)
                continue
            time.sleep(0.3)
            t0 = m.trace_t0 = time.monotonic()
            time.sleep(TRACE_LAPS * TRACE_PERIOD_S)  # whole laps: the master ends where it started
            self.trace = (t0, time.monotonic())
            m.clutch = False
            m.trace_t0 = None
            self._must_wait(lambda: not a.log.states[-1][4], 10, "the slave never let go")
            with a.log.lock:
                lost = [s for s in a.log.states if t0 <= s[0] <= self.trace[1] and not s[4]]
            if not lost:
                break
            log.warning("trace: the slave stopped following during attempt %d; tracing again", attempt)
        if self.trace == (0.0, 0.0):
            raise RuntimeError(f"the slave never followed the trace in {TRACE_ATTEMPTS} attempts")
        a.settle()
        # back out the extra depth in trocar mode before the removal (the pose it was inserted in)
        a.must("set_motion_mode", "mode=jog")
        a.must("jog", "frame=forceps", "axis=x", "direction=-1")
        time.sleep(TRACE_DEPTH_JOG_S)
        a.must("stop")
        a.settle()

    def master_slave(self, run: Run) -> None:
        """Master–slave in trocar mode after the insertion: one lap of a small master circle.

        Like the trace, drawn again (at most ``TRACE_ATTEMPTS`` times, from where the first lap
        started: :meth:`back_to_lap_start`) if a hold of a starved machine stopped the slave
        following."""
        a, m = self.arm, self.master
        self.mark_lap_start()
        a.must("set_motion_mode", "mode=master_slave")
        time.sleep(0.3)
        m.radius = MS_RADIUS_M
        try:
            for attempt in range(1, TRACE_ATTEMPTS + 1):
                run.ms_attempts = attempt
                if attempt > 1:
                    self.back_to_lap_start()
                self._lease_back()
                m.clutch = True
                if not a.wait(lambda: bool(a.log.states) and a.log.states[-1][4], 5):
                    m.clutch = False
                    time.sleep(0.5)
                    continue
                time.sleep(0.3)
                t0 = m.trace_t0 = time.monotonic()
                time.sleep(MS_LAPS * TRACE_PERIOD_S)
                m.clutch = False
                m.trace_t0 = None
                self._must_wait(lambda: not a.log.states[-1][4], 10, "the slave never let go")
                with a.log.lock:
                    lost = [
                        s for s in a.log.states if t0 <= s[0] <= t0 + MS_LAPS * TRACE_PERIOD_S and not s[4]
                    ]
                if not lost:
                    break
                log.warning("%s: the slave stopped following during the master–slave lap; again", run.name)
            else:  # recorded (ms_whole_lap false), not fatal: the insertion figures still stand
                log.warning("%s: master–slave never followed a whole lap", run.name)
                run.ms_whole_lap = False
        finally:
            m.clutch = False
            m.trace_t0 = None
            m.radius = TRACE_RADIUS_M
        run.t_ms_end = time.monotonic()
        a.settle()

    def one(self, name: str, start: str, method: str, *, trace: bool = False) -> Run:
        run = Run(name, start, method, t0=time.monotonic())
        self.go_to(start)
        run.t0 = time.monotonic()
        self.adjust(run)
        self.insert(run)
        run.t_ms_start = time.monotonic()
        if trace:
            self.trace_circle()
        else:
            self.master_slave(run)
        self.remove()
        run.removed = True
        run.t_end = time.monotonic()
        self.runs.append(run)
        return run


#: the protocol: (run name, start, posture method, trace after the insertion)
PLAN: tuple[tuple[str, str, str, bool], ...] = (
    ("fig9_ptp", "start_b", "ptp", False),
    ("fig9_jog", "start_b", "jog", False),
    ("fig9_direct_teach", "start_b", "direct_teach", False),
    ("fig10_a", "start_a", "ptp", False),
    ("fig10_c", "start_c", "ptp", False),
    ("trace", "start_a", "ptp", True),
)
#: ``--quick``: each posture method once (PTP from the third start), then the trace
QUICK_PLAN = tuple(r for r in PLAN if r[0] in ("fig9_jog", "fig9_direct_teach", "fig10_c", "trace"))


def run(
    out: Path, progress: Progress | None = None, *, keep_logs: bool = True, quick: bool = False
) -> dict[str, Any]:
    """Run the experiment (``quick``: :data:`QUICK_PLAN`); write ``metrics.json`` and figures into
    ``out``; return the metrics."""
    from telesurg.tools.bench.harness import Pipeline

    out.mkdir(parents=True, exist_ok=True)
    say: Progress = progress or (lambda text, frac: None)
    store = out / "teach_store.json"
    _write_store(store)
    overrides = {
        "slave_control": [
            f"q_home=[{', '.join(str(v) for v in STARTS['start_a'])}]",
            "robot.jog_speed_mm_s=40.0",
            "robot.jog_joint_speed_deg_s=20.0",
            f"robot.state_file={json.dumps(str(store))}",
        ],
        "mapping": ["master_mode=virtual_trocar"],  # the master of the paper's Fig. 7
    }
    plan = QUICK_PLAN if quick else PLAN
    t_begin = time.monotonic()
    say("starting the services", 0.0)
    with (
        Pipeline(
            out / "logs", mirror=False, impair=False, master=False, probe=False, overrides=overrides
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as node,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as console,
    ):
        master = Master(node)
        master.start()
        try:
            arm = ArmClient(console)  # the operator's commands come from the console identity
            if not arm.wait(arm.lease_ok, 30):
                raise RuntimeError("no lease from the watchdog")
            exp = Experiment(arm, master, say)
            try:
                for i, (name, start, method, trace) in enumerate(plan):
                    say(
                        f"{name}: posture by {method} from {start}" + (", trace" if trace else ""),
                        i / len(plan),
                    )
                    exp.one(name, start, method, trace=trace)
            except Exception:
                _save_arm_log(out / "arm_log.npz", arm.log)  # what led there, for a closer look
                raise
            say("figures", 0.97)
        finally:
            master.stop.set()
            master.join(2)
    metrics = _metrics(exp, master, time.monotonic() - t_begin)
    _figures(out, exp, master)
    _rcm_figure(out, exp)
    _save_trace(out / "trace.npz", exp, master)
    _save_arm_log(out / "arm_log.npz", exp.arm.log)
    (out / "metrics.json").write_text(jsonio.dumps(metrics, indent=2) + "\n")
    say("done", 1.0)
    return metrics


def _metrics(exp: Experiment, master: Master, wall_s: float) -> dict[str, Any]:
    log = exp.arm.log
    t0, t1 = exp.trace
    with log.lock:
        states = list(log.states)
        tips = np.array([p for p in log.tips])
        transitions = [(t, text) for t, k, text in log.events if k == "mode_transition"]
        holds = [text for _, k, text in log.events if k == "hold"]
    trace_rcm = [s[2] for s in states if t0 <= s[0] <= t1 and s[1] == "trocar"]
    trocar_rcm = [s[2] for s in states if s[1] == "trocar"]
    full = _full_rate_rcm(log)
    full_trace = [e for t, e in full if t0 <= t <= t1]
    path = _dummy_path(master, t0)
    err = _tracking_error(tips, path, exp.trace)
    lag, path_rms, path_max = _lag_and_error(tips, path, exp.trace)

    def full_max(r: Run) -> float:  # the run's trocar mode, master–slave included
        sel = [e for t, e in full if r.t0 <= t <= r.t_end]
        return round(max(sel), 4) if sel else math.nan

    return {
        "rcm_full_rate_max_mm": round(max(e for _, e in full), 4) if full else math.nan,
        "rcm_full_rate_mean_mm": round(float(np.mean([e for _, e in full])), 4) if full else math.nan,
        "rcm_full_rate_samples": len(full),
        "rcm_full_rate_trace_max_mm": round(max(full_trace), 4) if full_trace else math.nan,
        "rcm_full_rate_trace_mean_mm": round(float(np.mean(full_trace)), 4) if full_trace else math.nan,
        "rcm_error_max_mm": round(max(trace_rcm), 4),
        "rcm_error_mean_mm": round(float(np.mean(trace_rcm)), 4),
        "rcm_error_samples": len(trace_rcm),
        "rcm_error_max_all_trocar_mm": round(max(trocar_rcm), 4),
        "insertions_succeeded": sum(r.inserted for r in exp.runs),
        "insertions_attempted": len(exp.runs),
        "removals_succeeded": sum(r.removed for r in exp.runs),
        "mode_transitions": len(transitions),
        "mode_transition_log": [text for _, text in transitions],
        "holds": len(holds),
        "trace_tracking_error_rms_mm": round(err[0], 3),
        "trace_tracking_error_max_mm": round(err[1], 3),
        "trace_lag_ms": round(lag * 1e3, 1),
        "trace_path_error_rms_mm": round(path_rms, 3),
        "trace_path_error_max_mm": round(path_max, 3),
        "trace_attempts": exp.trace_attempts,
        "runs": [
            {
                "name": r.name,
                "start": r.start,
                "method": r.method,
                "posture_s": round(r.posture_s, 2),
                "other_joints_moved_deg": round(r.moved_other_joints_deg, 4),
                "inserted": r.inserted,
                "insert_to_trocar_s": round(r.t_trocar - r.t_aligned, 2),
                "master_slave_attempts": r.ms_attempts,
                "master_slave_whole_lap": r.ms_whole_lap if r.ms_attempts else None,
                "rcm_full_rate_max_mm": full_max(r),
            }
            for r in exp.runs
        ],
        "trocar_mm": list(TROCAR_MM),
        "wall_time_s": round(wall_s, 1),
    }


def _full_rate_rcm(log: ArmLog) -> list[tuple[float, float]]:
    """``(t, RCM error mm)`` of every measured_js sample taken while the arm was in trocar mode
    (``t``: when the client received it, monotonic s).

    From the measured joints by forward kinematics (slave_control publishes them at its full
    control rate); the mode at a sample is that of the latest ``operating_state`` the slave
    stamped before it (by the slave's stamps: a client stalled by its host receives both streams
    in bursts, and a sample from before a mode change may reach it after the change's state).
    """
    with log.lock:
        modes = list(log.mode_stamps)
        joints = list(zip(log.joints, log.joint_stamps, strict=True))
    if not modes:
        return []
    order = sorted(range(len(modes)), key=lambda k: modes[k][0])
    ts = np.array([modes[k][0] for k in order])
    out = []
    for (t, q), stamp in joints:
        i = int(np.searchsorted(ts, stamp, side="right")) - 1
        if i >= 0 and modes[order[i]][1] == "trocar":
            out.append((t, rcm_error(np.array(q), TROCAR, MH3F) * 1e3))
    return out


def _save_arm_log(path: Path, log: ArmLog) -> None:
    """Everything the client saw of the arm (for a closer look at any figure): measured joints
    (receive time s, slave stamp ns, q), operating states (receive time, slave stamp, mode, RCM mm,
    lease, follow) and slave_control's events (receive time, kind, text), as ``.npz``."""
    with log.lock:
        joints = np.array([(t, st, *q) for (t, q), st in zip(log.joints, log.joint_stamps, strict=True)])
        states = np.array(
            [
                (s[0], st, s[1], s[2], s[3], s[4])
                for s, (st, _) in zip(log.states, log.mode_stamps, strict=True)
            ],
            dtype=object,
        )
        events = np.array(log.events, dtype=object)
    np.savez_compressed(path, joints=joints, states=states.astype(str), events=events.astype(str))


def _rcm_figure(out: Path, exp: Experiment) -> None:
    """``jinno-rcm.png``: the RCM error over all of trocar mode, from the measured joints at their
    full rate (forward kinematics, as the paper computes it) beside slave_control's 20 Hz MuJoCo
    figure; one panel per run, the master–slave motion shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = exp.arm.log
    with log.lock:
        states = list(log.states)
    full = np.array(_full_rate_rcm(log) or [(0.0, math.nan)])
    slow = np.array([(s[0], s[2]) for s in states if s[1] == "trocar"] or [(0.0, math.nan)])
    runs = exp.runs
    fig, axes = plt.subplots(1, len(runs), figsize=(3.2 * len(runs), 3.6), sharey=True, squeeze=False)
    for ax, r in zip(axes[0], runs, strict=True):
        f = full[(full[:, 0] >= r.t0) & (full[:, 0] <= r.t_end)]
        m = slow[(slow[:, 0] >= r.t0) & (slow[:, 0] <= r.t_end)]
        t_in = f[0, 0] if len(f) else r.t_trocar
        if len(f):
            label = f"measured_js ({len(f)}; max {f[:, 1].max():.3f} mm)"
            ax.plot(f[:, 0] - t_in, f[:, 1], lw=0.7, label=label)
        if len(m):
            ax.plot(m[:, 0] - t_in, m[:, 1], ".", ms=3, label="operating_state (MuJoCo tip, 20 Hz)")
        end = exp.trace[1] if r.name == "trace" else r.t_ms_end
        if r.t_ms_start and end:
            ax.axvspan(r.t_ms_start - t_in, end - t_in, alpha=0.12, color="g", label="master–slave")
        ax.axhline(1.0, color="r", ls="--", lw=1)
        ax.set_title(r.name, fontsize=9)
        ax.set_xlabel("time in trocar mode [s]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=6, loc="upper right")
    axes[0][0].set_ylabel("RCM error [mm] (trocar to forceps axis)")
    fig.suptitle("RCM error over all of trocar mode, from the measured joints at 250 Hz (red: 1 mm)")
    fig.tight_layout()
    fig.savefig(out / "jinno-rcm.png", dpi=110)
    plt.close(fig)


def _save_trace(path: Path, exp: Experiment, master: Master) -> None:
    """The trace's raw series (monotonic s): slave tip, master target, slave states."""
    arm_log = exp.arm.log
    with arm_log.lock:
        tips = np.array(arm_log.tips)
        states = np.array([(s[0], s[2], float(s[4])) for s in arm_log.states])  # t, rcm mm, follow
    window, m = np.array(exp.trace), np.array(master.log)
    np.savez_compressed(path, window=window, tips=tips, master=m, states=states)


#: The mapping's motion scale (the default; deploy/local/site.toml keeps it).
SCALE = 0.5


def _dummy_path(master: Master, t0: float) -> np.ndarray:
    """``(t, x, y, z)`` of every master sample from ``t0`` on (every lap is logged: the trace's are
    those from its start): the virtual-trocar master's dummy tip, what the slave tip follows,
    mapped once per sample."""
    ml = np.array(master.log)
    ml = ml[ml[:, 0] >= t0] if len(ml) else ml
    cfg = MappingConfig(master_mode="virtual_trocar")
    return np.array([(h[0], *master_point(cfg, (float(h[1]), float(h[2]), float(h[3])))) for h in ml])


def _tracking_error(
    tips: np.ndarray, path: np.ndarray, window: tuple[float, float], lag: float = 0.0
) -> tuple[float, float]:
    """RMS / max distance (mm) of the slave tip from the scaled master path (:func:`_dummy_path`,
    anchored at the start), each tip sample against the master at the same time (``lag`` = 0: the
    slave's latency counts as error) or ``lag`` s earlier (interpolated between master samples;
    before the trace began the master stood at its first)."""
    t0, t1 = window
    sel = tips[(tips[:, 0] >= t0) & (tips[:, 0] <= t1)]
    if len(path) < 10 or len(sel) < 10:
        return (math.nan, math.nan)
    want = np.stack([np.interp(sel[:, 0] - lag, path[:, 0], path[:, i]) for i in (1, 2, 3)], axis=1)
    d = np.linalg.norm(sel[:, 1:] - (sel[0, 1:] + SCALE * (want - path[0, 1:])), axis=1) * 1e3
    return (float(np.sqrt(np.mean(d**2))), float(d.max()))


def _lag_and_error(
    tips: np.ndarray, path: np.ndarray, window: tuple[float, float]
) -> tuple[float, float, float]:
    """How late and how well the slave tip traced the master's path over the trace: its lag (s: the
    constant shift, in 2 ms steps up to 0.5 s, that minimises the RMS of :func:`_tracking_error`)
    and the RMS / max distance (mm) of each tip sample from the nearest point of the scaled master
    path (250 Hz samples, ~0.08 mm apart at the slave), however late it got there."""
    best = (math.inf, 0.0)
    for lag in np.arange(0.0, 0.5, 0.002):
        rms, _ = _tracking_error(tips, path, window, float(lag))
        if rms < best[0]:
            best = (rms, float(lag))
    t0, t1 = window
    sel = tips[(tips[:, 0] >= t0) & (tips[:, 0] <= t1)]
    inside = path[path[:, 0] <= t1] if len(path) else path
    if len(inside) < 10 or len(sel) < 10:
        return (math.nan, math.nan, math.nan)
    points = sel[0, 1:] + SCALE * (inside[:, 1:] - inside[0, 1:])
    d = np.concatenate(
        [
            np.linalg.norm(c[:, None, :] - points[None, :, :], axis=2).min(axis=1)
            for c in np.array_split(sel[:, 1:], 20)
        ]
    )
    d *= 1e3
    return best[1], float(np.sqrt(np.mean(d**2))), float(d.max())


def _figures(out: Path, exp: Experiment, master: Master) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = exp.arm.log
    with log.lock:
        tips = np.array(log.tips)
        states = list(log.states)
        transitions = [(t, text) for t, k, text in log.events if k == "mode_transition"]
    tz = tips[0, 0] if len(tips) else 0.0

    def paths(runs: list[Run], fname: str, title: str) -> None:
        fig, (xy, xz) = plt.subplots(1, 2, figsize=(11, 5))
        for r in runs:
            t_end = max(r.t_trocar + 0.5, r.t_ms_end)  # insertion, then the master–slave motion
            sel = tips[(tips[:, 0] >= r.t0) & (tips[:, 0] <= t_end)] * 1e3
            label = f"{r.method} from {r.start}"
            xy.plot(sel[:, 1], sel[:, 2], label=label)
            xz.plot(sel[:, 1], sel[:, 3], label=label)
            for ax, j in ((xy, 2), (xz, 3)):
                ax.plot(sel[0, 1], sel[0, j], "o", color=ax.lines[-1].get_color())
        for ax, name in ((xy, "Y"), (xz, "Z")):
            ax.plot(TROCAR_MM[0], TROCAR_MM[1 if name == "Y" else 2], "kx", ms=12, mew=2, label="trocar")
            ax.set_xlabel("X [mm]")
            ax.set_ylabel(f"{name} [mm]")
            ax.set_aspect("equal", adjustable="datalim")
            ax.grid(True, alpha=0.3)
        xy.set_title("XY plane")
        xz.set_title("XZ plane")
        xz.legend(fontsize=8)
        fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=110)
        plt.close(fig)

    fig9 = [r for r in exp.runs if r.name.startswith("fig9")]
    fig10 = [exp.runs[0]] + [r for r in exp.runs if r.name.startswith("fig10")]
    title9 = "Fig. 9: posture adjustment by PTP, jog, direct teach (o = start), insertion, master–slave"
    paths(fig9, "jinno-fig9.png", title9)
    paths(fig10, "jinno-fig10.png", "Fig. 10: posture by PTP from three starts, insertion, master–slave")

    # Figs. 11–13: the trace and its RCM error
    t0, t1 = exp.trace
    sel = tips[(tips[:, 0] >= t0) & (tips[:, 0] <= t1)]
    rcm = np.array([(s[0], s[2]) for s in states if t0 - 1 <= s[0] <= t1 + 1 and s[1] == "trocar"])
    fig, (xy, xz, er) = plt.subplots(1, 3, figsize=(15, 4.5))
    xy.plot(sel[:, 1] * 1e3, sel[:, 2] * 1e3)
    xz.plot(sel[:, 1] * 1e3, sel[:, 3] * 1e3)
    for ax, name in ((xy, "Y"), (xz, "Z")):
        ax.set_xlabel("X [mm]")
        ax.set_ylabel(f"{name} [mm]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    xy.set_title("Fig. 11: slave tip while tracing (XY)")
    xz.set_title("slave tip while tracing (XZ)")
    if len(rcm):
        er.plot(rcm[:, 0] - t0, rcm[:, 1], ".-", ms=3)
    er.axhline(1.0, color="r", ls="--", label="paper's bound (1 mm)")
    er.set_xlabel("time since the trace started [s]")
    er.set_ylabel("RCM error [mm] (MuJoCo)")
    er.set_title("Fig. 13: trocar point to forceps axis")
    er.legend()
    er.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "jinno-trace.png", dpi=110)
    plt.close(fig)

    # mode timeline + RCM error over the whole session
    levels = {"non_trocar": 0, "transitional": 1, "trocar": 2}
    st = np.array([(s[0] - tz, levels.get(s[1], -1), s[2]) for s in states])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(12, 5), sharex=True)
    ax1.step(st[:, 0], st[:, 1], where="post")
    ax1.set_yticks([0, 1, 2], ["non_trocar", "transitional", "trocar"])
    for r in exp.runs:
        ax1.axvspan(r.t0 - tz, r.t_end - tz, alpha=0.08)
        ax1.text(r.t0 - tz, 2.25, r.name, fontsize=7)
    ax1.set_ylim(-0.3, 2.6)
    ax1.set_title(f"control mode ({len(transitions)} transitions)")
    ax2.plot(st[:, 0], np.where(st[:, 1] == 2, st[:, 2], np.nan), ".", ms=2)
    ax2.set_ylabel("RCM error in\ntrocar mode [mm]")
    ax2.set_xlabel("time [s]")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "jinno-timeline.png", dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:  # pragma: no cover - via telesurg.tools.experiment
    raise SystemExit("use: telesurg experiment jinno-insertion --out DIR")
