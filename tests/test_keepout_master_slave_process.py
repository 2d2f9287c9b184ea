"""The patient's body is a keep-out for master–slave too (issue #39, acceptance 6), through the services.

Router, watchdog, slave_control on MuJoCo and the mapping in its Cartesian mode run as processes;
the test is the console and a scripted master (250 Hz, clutch it presses). First the forceps is
inserted through the trocar (posture PTP, ``insert``) and followed in trocar mode: insertion and
trocar-mode master–slave still work. Then, removed, it is played (a taught one-point program) to a
pose over the torso 150 mm from the trocar, and in non-trocar master–slave the master moves
160 mm down: at scale 0.5 that path would take the forceps tip 80 mm down, ~40 mm into the torso.

Judged independently of the slave's check, from the site's MJCF (``patient_torso``, the
``trocar`` site, the cannula's radius) with MuJoCo's kinematics of every ``measured_js`` sample
(``tests/test_keepout_process.py``'s :class:`Patient`): the measured forceps never enters the
torso outside the trocar (< 1 mm), it does reach the surface (the master's path was not stopped
short elsewhere), the mapping's last setpoint *was* through the torso, and the slave reported the
clamp (``keepout_clamped``).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from helpers import GoalMaster, operator_command
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import CommandReply, JointSetpoint, JointState, OperatingState, SafetyEvent
from telesurg.shared.robots.mh3f.kinematics import fk
from telesurg.tools.bench.harness import Pipeline
from test_keepout_process import Patient

pytestmark = [pytest.mark.process, pytest.mark.timeout(300)]

HOME = [0.0, -0.2, 0.6, 0.0, -0.3, 0.0]  # the forceps high above the patient (as the trocar tests)
#: the tip at (635, 69, 241) mm, 150 mm from the trocar, the forceps pointing down and out (+x)
OVER_TORSO = [0.258, -0.008, 0.397, -0.172, -1.229, -0.435]
DOWN_M = 0.16  # master travel down (m): 80 mm of the tip at scale 0.5


@dataclass
class Heard:
    lock: threading.Lock = field(default_factory=threading.Lock)
    js: list[tuple[float, tuple[float, ...]]] = field(default_factory=list)  # (arrival, position)
    # the mapping's followed servo_jp (arrival, position)
    servo: list[tuple[float, tuple[float, ...]]] = field(default_factory=list)
    mode: str = ""
    follow: bool = False
    lease: bool = False
    events: list[tuple[float, str, str]] = field(default_factory=list)

    def on_js(self, m: JointState, key: str) -> None:
        with self.lock:
            self.js.append((time.monotonic(), m.position))

    def on_servo(self, m: JointSetpoint, key: str) -> None:
        if m.follow:
            with self.lock:
                self.servo.append((time.monotonic(), m.position))

    def on_state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.mode, self.follow, self.lease = m.control_mode, m.follow, m.lease_ok

    def on_event(self, m: SafetyEvent, key: str) -> None:
        with self.lock:
            self.events.append((time.monotonic(), m.kind, m.text))

    def since(self, t: float, kind: str) -> list[str]:
        with self.lock:
            return [text for ts, k, text in self.events if ts >= t and k == kind]

    def joints(self, t0: float, t1: float = float("inf")) -> np.ndarray:
        with self.lock:
            return np.array([q for ts, q in self.js if t0 <= ts <= t1])


@dataclass
class Site:
    pipe: Pipeline
    console: Node
    master: GoalMaster
    heard: Heard


@pytest.fixture
def site(tmp_path: Path) -> Iterator[Site]:
    tmp = tmp_path
    store = tmp / "teach.json"
    program = {
        name: [{"q": q, "tip": [float(v) for v in fk(q)[:3, 3]], "mode": "non_trocar"}]
        for name, q in (("near", OVER_TORSO), ("home", HOME))
    }
    store.write_text(
        json.dumps({"version": 1, "arm": "arm1", "trocars": {}, "current_trocar": "", "programs": program})
    )
    overrides = {
        "slave_control": [
            f"q_home={json.dumps(HOME)}",
            f"robot.state_file={json.dumps(str(store))}",
            "robot.jog_speed_mm_s=40.0",
            "robot.playback_dwell_s=0.02",
            "robot.ptp_speed_fraction=0.6",  # (the PTPs between the cases: shorter, fewer stopped by holds)
        ]
    }
    with (
        Pipeline(
            tmp / "logs", mirror=False, impair=False, master=False, probe=False, overrides=overrides
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as master_node,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as console,
    ):
        heard = Heard()
        k = console.keys
        console.subscribe(k.slave("arm1", "measured_js"), JointState, heard.on_js)
        console.subscribe(k.slave("arm1", "servo_jp"), JointSetpoint, heard.on_servo)
        console.subscribe(k.slave("arm1", "operating_state"), OperatingState, heard.on_state)
        console.subscribe(k.events("slave_control"), SafetyEvent, heard.on_event)
        master = GoalMaster(master_node)
        master.start()
        try:
            yield Site(p, console, master, heard)
        finally:
            master.stop.set()
            master.join(2)
    for f in sorted((tmp / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-2000:]}")


def test_master_slave_stops_at_the_body_surface_and_enters_through_the_trocar(site: Site) -> None:
    """Under load the watchdog holds now and then: a hold stops a slave-side motion (the test
    commands it again, as an operator would) and master–slave following (the test engages again);
    the judgement covers every measured sample regardless."""
    pipe, heard, master, patient = site.pipe, site.heard, site.master, Patient()
    key = site.console.keys.command("arm1")

    def send(name: str, *args: str) -> CommandReply:
        assert pipe.wait(lambda: heard.lease, 60), "no lease for a minute"
        r = operator_command(site.console, key, "arm1", name, *args)
        print(f"{name} {' '.join(args)} -> {'accepted' if r.accepted else 'REFUSED'}: {r.reason}")
        return r

    def until(done: Callable[[], bool], *command: str, timeout: float = 60.0) -> None:
        """Send ``command`` until ``done``: again after a hold or a stop stopped its motion."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            t = time.monotonic()
            send(*command)
            stopped = lambda: heard.since(t, "hold") or heard.since(t, "motion_stopped")  # noqa: E731,B023
            pipe.wait(lambda: done() or bool(stopped()), 15)  # noqa: B023
            if done():
                return
            time.sleep(0.2)
        raise AssertionError(f"{command} never done")

    def follow(goal: Callable[[], bool], seconds: float) -> None:
        """Follow the master (engaging again after every hold) until ``goal``, then ``seconds``
        more; the clutch is released at the end."""
        deadline, reached = time.monotonic() + 60.0, 0.0
        while time.monotonic() < deadline:
            if not heard.follow:
                master.clutch = False
                time.sleep(0.2)
                master.clutch = True
                pipe.wait(lambda: heard.follow, 5)
            if not reached and goal():
                reached = time.monotonic()
            if reached and time.monotonic() > reached + seconds:
                break
            time.sleep(0.02)
        master.clutch = False
        assert reached, "the master–slave goal was never reached"
        time.sleep(0.3)

    assert pipe.wait(lambda: heard.lease and heard.js, 60), "no lease / no measured_js"

    # 1. to the pose over the torso, then non-trocar master–slave straight down through it
    assert send("set_motion_mode", "mode=playback").accepted
    t_play = time.monotonic()
    until(lambda: bool(heard.since(t_play, "playback_done")), "play", "program=near")
    assert send("set_motion_mode", "mode=master_slave").accepted
    t_down = time.monotonic()

    seen = [0, 0.0]  # followed setpoints judged so far, the deepest of them (m)

    def servo_depth() -> float:
        """The deepest followed setpoint since t_down: how far the master drove into the torso."""
        with heard.lock:
            new = [q for ts, q in heard.servo[seen[0] :] if ts >= t_down]
            seen[0] = len(heard.servo)
        if new:
            seen[1] = max(seen[1], float(patient.penetration(np.array(new[::5]))[0].max()))
        return seen[1]

    def through() -> bool:
        """A followed setpoint of the mapping went 20 mm into the torso; else the master goes on
        down (after a re-engage the mapping starts again from where the master is)."""
        if servo_depth() > 0.02:
            return True
        if np.linalg.norm(master.goal - master.p) < 0.01:
            master.goal = master.goal + np.array([0.0, 0.0, -0.02])
        return False

    master.goal = master.p + np.array([0.0, 0.0, -DOWN_M])
    follow(through, 1.0)
    q = heard.joints(t_down)
    pen, gap = patient.penetration(q)
    servo_pen = servo_depth()
    clamps = heard.since(t_down, "keepout_clamped")
    print(
        f"non-trocar master–slave: {len(q)} measured_js samples; the measured forceps in the torso "
        f"outside the trocar max {pen.max() * 1e3:.3f} mm, closest approach {gap.min() * 1e3:.2f} mm; "
        f"the mapping's deepest followed setpoint {servo_pen * 1e3:.1f} mm in; events: {clamps}"
    )
    assert servo_pen > 0.02  # the master's path went through the torso ...
    assert pen.max() < 1e-3  # ... the forceps did not (< 1 mm in, judged by MuJoCo on the MJCF)
    assert gap.min() < 5e-3  # it went down to the surface, not stopped short
    assert clamps and "clamped at the patient's surface" in clamps[0] and "outside the trocar" in clamps[0]

    # 2. back up (the master lifts the forceps out of the clamp), home, insertion through the
    # trocar, then master–slave in trocar mode
    t_up = time.monotonic()
    master.goal = master.p + np.array([0.0, 0.0, 0.12])

    def lifted() -> bool:
        """The shaft 20 mm clear of the torso; else the master goes on up."""
        q = heard.joints(t_up)
        if len(q) > 0 and float(patient.penetration(q[-1])[1][0]) > 0.02:
            return True
        if np.linalg.norm(master.goal - master.p) < 0.01:
            master.goal = master.goal + np.array([0.0, 0.0, 0.04])
        return False

    follow(lifted, 0.2)
    assert send("set_motion_mode", "mode=playback").accepted
    t_play = time.monotonic()
    until(lambda: bool(heard.since(t_play, "playback_done")), "play", "program=home")
    deadline = time.monotonic() + 60
    t_begin = time.monotonic()
    send("begin_posture_adjust", "method=ptp")
    while not send("finish_posture_adjust").accepted:
        assert time.monotonic() < deadline, "posture adjustment never finished"
        if heard.since(t_begin, "hold") or heard.since(t_begin, "motion_stopped"):  # stopped: again
            send("abort")
            t_begin = time.monotonic()
            send("begin_posture_adjust", "method=ptp")
        time.sleep(0.5)
    until(lambda: heard.mode == "trocar", "insert")
    assert send("set_motion_mode", "mode=master_slave").accepted
    t_trocar = time.monotonic()
    p0 = master.p.copy()

    def travelled() -> bool:
        """The tip moved 5 mm about the trocar; else the master goes on to and fro 20 mm (10 mm of
        the tip at scale 0.5) along y."""
        q = heard.joints(t_trocar)
        if len(q) and np.ptp([fk(qi)[:3, 3] for qi in q[::10]], axis=0).max() > 0.005:
            return True
        if np.linalg.norm(master.goal - master.p) < 1e-6:
            master.goal = p0 + (np.array([0.0, 0.02, 0.0]) if master.goal[1] <= p0[1] else 0.0)
        return False

    follow(travelled, 0.3)
    q_trocar = heard.joints(t_trocar)
    moved_mm = float(np.ptp([fk(q)[:3, 3] for q in q_trocar], axis=0).max() * 1e3)
    pen_trocar = patient.penetration(q_trocar)[0]
    print(
        f"trocar mode: tip moved {moved_mm:.1f} mm, the shaft in the torso outside the trocar "
        f"{pen_trocar.max() * 1e3:.3f} mm"
    )
    assert moved_mm > 3.0, "trocar-mode master–slave did not move the forceps"
    assert not heard.since(t_trocar, "keepout_clamped"), "a trocar-mode setpoint was clamped"
    assert pen_trocar.max() == 0.0
    until(lambda: heard.mode == "non_trocar", "remove")
    whole = patient.penetration(heard.joints(0.0))[0]  # every sample of the test, insertion included
    print(f"the whole test: {len(whole)} samples, deepest outside the trocar {whole.max() * 1e3:.3f} mm")
    assert whole.max() < 1e-3
