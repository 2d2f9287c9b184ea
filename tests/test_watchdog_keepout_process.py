"""The watchdog holds a slave-side motion headed into the patient (issue #20: "and while it runs,
the watchdog checks commanded joints of slave-side motions too"), through the running services.

The pipeline is deploy/local's (router, watchdog, slave_control on MuJoCo, mapping); the test is
the console (operator commands) and an idle master (clutch released, operator present). To show
the watchdog's check on its own, the slave's own keep-out must miss the crossing: **test-only**,
slave_control's ``patient_box_*_mm`` is moved 2 m away from the patient (a slave with a wrong
patient box), while the watchdog keeps the site's default box. The arm starts 120 mm below its
home pose (tip at (835, 0, 181) mm, the forceps pitched 29° down toward the torso) and is jogged
straight down in the base frame at 20 mm/s: about 30 mm lower the shaft would cross the top of the
torso 230 mm from the trocar.

What a user notices: the watchdog goes to HOLD naming the patient keep-out, the jog stops (the
slave's event says why) and the arm stands still, its forceps a few millimetres into the
(margined) patient box instead of going on down.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from helpers import operator_command
from telesurg.services.watchdog import WatchdogConfig
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import (
    CartesianPose,
    CommandReply,
    JointState,
    MasterButtons,
    OperatingState,
    SafetyEvent,
    SafetyState,
)
from telesurg.shared.robots import arm_profile
from telesurg.shared.robots.mh3f.keepout import PatientBox, shaft_inside_m
from telesurg.shared.robots.mh3f.kinematics import fk, ik
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process

PROFILE = arm_profile("mh3f", "arm1")
WD = WatchdogConfig()
BOX = PatientBox(  # the watchdog's (the site's default), with the scene's trocar
    (WD.patient_box_min_mm[0] / 1e3, WD.patient_box_min_mm[1] / 1e3, WD.patient_box_min_mm[2] / 1e3),
    (WD.patient_box_max_mm[0] / 1e3, WD.patient_box_max_mm[1] / 1e3, WD.patient_box_max_mm[2] / 1e3),
    (0.5, 0.0, 0.2),
)


def start_pose() -> list[float]:
    t = fk(np.array(PROFILE.home))
    t[2, 3] -= 0.12
    return [round(float(v), 6) for v in ik(t, np.array(PROFILE.home))]


class Console:
    def __init__(self, pipe: Pipeline, node: Node) -> None:
        self.pipe, self.node = pipe, node
        self.key = node.keys.command("arm1")
        self.lock = threading.Lock()
        self.lease, self.op = False, ""
        self.safety: list[tuple[float, str, tuple[str, ...]]] = []
        self.events: list[tuple[float, str, str]] = []
        self.js: list[tuple[float, np.ndarray]] = []
        self.inside: list[tuple[float, float]] = []  # (time, shaft inside the watchdog's box, m)
        self.commanded = 0
        k = node.keys
        node.subscribe(k.slave("arm1", "operating_state"), OperatingState, self._state)
        node.subscribe(k.safety("arm1", "state"), SafetyState, self._safety)
        node.subscribe(k.events("*"), SafetyEvent, self._event)
        node.subscribe(k.slave("arm1", "measured_js"), JointState, self._js)
        node.subscribe(k.slave("arm1", "setpoint_js"), JointState, self._commanded)

    def _state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.lease, self.op = m.lease_ok, m.state

    def _safety(self, m: SafetyState, key: str) -> None:
        with self.lock:
            self.safety.append((time.monotonic(), m.state, m.causes))

    def _event(self, m: SafetyEvent, key: str) -> None:
        with self.lock:
            self.events.append((time.monotonic(), m.kind, m.text))

    def _js(self, m: JointState, key: str) -> None:
        q = np.array(m.position)
        inside = shaft_inside_m(q, BOX)  # (here, once per sample: the master thread needs the CPU)
        with self.lock:
            t = time.monotonic()
            self.js.append((t, q))
            self.inside.append((t, inside))

    def deepest_mm(self, t0: float) -> float:
        """The measured shaft's deepest into the watchdog's patient box since ``t0``, mm."""
        with self.lock:
            return max((v for t, v in self.inside if t >= t0), default=0.0) * 1e3

    def _commanded(self, m: JointState, key: str) -> None:
        with self.lock:
            self.commanded += 1

    def send(self, name: str, *args: str) -> CommandReply:
        r: CommandReply = operator_command(self.node, self.key, "arm1", name, *args)
        print(f"{name} {' '.join(args)} -> {'accepted' if r.accepted else 'REFUSED'}: {r.reason}")
        return r

    def keepout_holds(self, since: float) -> list[tuple[float, tuple[str, ...]]]:
        with self.lock:
            return [
                (t, c)
                for t, s, c in self.safety
                if t >= since and s == "HOLD" and any("patient keep-out" in x for x in c)
            ]

    def joints_since(self, t0: float) -> list[tuple[float, np.ndarray]]:
        with self.lock:
            return [(t, q) for t, q in self.js if t >= t0]


def idle_master(node: Node, stop: threading.Event) -> None:
    """A master at rest with the clutch released (nobody engages master–slave in this test)."""
    pose = node.outlet(node.keys.master("m1", "measured_cp"))
    buttons = node.outlet(node.keys.master("m1", "buttons"))
    while not stop.wait(0.004):
        buttons.put(MasterButtons(buttons.header(), False, True))
        pose.put(CartesianPose(pose.header(), "master", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))


#: test-only: a patient box 2 m away from the patient (a keep-out that misses it)
AWAY = ["patient_box_min_mm=[-2100.0, -2100.0, -2100.0]", "patient_box_max_mm=[-2000.0, -2000.0, -2000.0]"]


@pytest.fixture
def console(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Console]:
    case = getattr(request, "param", "")
    overrides = {
        # the slave's own keep-out misses the patient
        "slave_control": [f"q_home={start_pose()}", "robot.jog_speed_mm_s=20.0", *AWAY],
        # the control case (blind_watchdog): the watchdog's misses it too
        "watchdog": list(AWAY) if case == "blind_watchdog" else [],
    }
    if case == "sparse":  # setpoint_js every 100 ms, the watchdog wants one every 50 ms
        overrides["slave_control"].append("setpoint_js_hz=10.0")
        overrides["watchdog"].append("setpoint_js_deadline_ms=50.0")
    stop = threading.Event()
    with (
        Pipeline(
            tmp_path / "logs", mirror=False, impair=False, master=False, probe=False, overrides=overrides
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as master,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as node,
    ):
        th = threading.Thread(target=idle_master, args=(master, stop), daemon=True)
        th.start()
        try:
            yield Console(p, node)
        finally:
            stop.set()
            th.join(2)
    for f in sorted((tmp_path / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-2000:]}")


def test_the_watchdog_holds_a_jog_into_the_patient_that_the_slave_missed(console: Console) -> None:
    c, pipe = console, console.pipe
    assert pipe.wait(lambda: c.lease and len(c.js) > 10, 30), "no lease"
    q0 = c.js[-1][1]
    assert shaft_inside_m(q0, BOX) == 0.0, "the start pose already crosses the patient box"
    assert c.send("set_motion_mode", "mode=jog").accepted
    t0 = time.monotonic()
    for _ in range(4):  # re-commanded after a load hold that is not the keep-out (stale stream)
        assert pipe.wait(lambda: c.lease, 30), "no lease"
        assert c.send("jog", "frame=base", "axis=z", "direction=-1").accepted
        if pipe.wait(lambda: c.keepout_holds(t0), 10):
            break
        c.send("stop")
    holds = c.keepout_holds(t0)
    assert holds, "the watchdog never held on the patient keep-out"
    t_hold, causes = holds[0]
    print("watchdog:", "; ".join(causes))
    assert any("outside the trocar" in x for x in causes)

    # the slave stopped the jog, and says it was the watchdog's hold
    def slave_held() -> list[str]:
        with c.lock:
            return [x for t, k, x in c.events if t >= t0 and k == "hold" and "patient keep-out" in x]

    assert pipe.wait(slave_held, 5), "the slave did not stop the jog on the keep-out hold"
    stopped = slave_held()
    print("slave:", stopped[0])
    # the arm stands still afterwards (the jog was cancelled; even when the lease comes back)
    time.sleep(2.0)
    after = c.joints_since(t_hold + 0.5)
    assert len(after) > 100
    tips = np.array([fk(q)[:3, 3] for _, q in after])
    drift = float(np.ptp(tips, axis=0).max()) * 1e3
    print(f"tip motion from 0.5 s after the hold: {drift:.3f} mm over {len(after)} samples")
    assert drift < 0.5, "the arm went on moving after the keep-out hold"
    # how far the forceps got into the watchdog's patient box (the box has 2-6 mm of margin
    # around the torso); the jog alone would have gone on down, tens of mm
    deepest = c.deepest_mm(t0)
    z_drop = (fk(q0)[2, 3] - tips[-1][2]) * 1e3
    print(f"measured shaft inside the patient box: max {deepest:.1f} mm; the tip went {z_drop:.1f} mm down")
    print(f"setpoint_js samples seen: {c.commanded}")
    assert c.commanded > 0
    assert deepest < 40.0, "the forceps went deep into the patient before the hold"


@pytest.mark.parametrize("console", ["blind_watchdog"], indirect=True)
def test_without_the_watchdog_check_the_same_jog_goes_into_the_patient(console: Console) -> None:
    """The control case: with the watchdog's box moved away as well, nothing stops the jog."""
    c, pipe = console, console.pipe
    assert pipe.wait(lambda: c.lease and len(c.js) > 10, 30), "no lease"
    assert c.send("set_motion_mode", "mode=jog").accepted
    t0 = time.monotonic()
    deepest = 0.0
    for _ in range(10):  # (each load hold stops the jog; commanded again, it goes on from there)
        assert pipe.wait(lambda: c.lease, 30), "no lease"
        assert c.send("jog", "frame=base", "axis=z", "direction=-1").accepted
        pipe.wait(lambda: c.deepest_mm(t0) > 20.0, 6)
        deepest = c.deepest_mm(t0)
        if deepest > 20.0:
            break
    c.send("stop")
    print(f"measured shaft inside the patient box: max {deepest:.1f} mm")
    assert not c.keepout_holds(t0)
    assert deepest > 20.0


@pytest.mark.parametrize("console", ["sparse"], indirect=True)
def test_a_slave_side_motion_without_fresh_setpoint_js_is_held(console: Console) -> None:
    """Any doubt → hold: while the slave reports a slave-side motion, its commanded joints must
    come within ``setpoint_js_deadline_ms`` (here 50 ms, the slave sending them every 100 ms)."""
    c, pipe = console, console.pipe
    assert pipe.wait(lambda: c.lease and len(c.js) > 10, 30), "no lease"
    assert c.send("set_motion_mode", "mode=jog").accepted
    t0 = time.monotonic()

    def stale() -> list[str]:
        with c.lock:
            return [
                x for t, s, cs in c.safety if t >= t0 and s == "HOLD" for x in cs if "setpoint_js stale" in x
            ]

    for _ in range(4):
        assert pipe.wait(lambda: c.lease, 30), "no lease"
        assert c.send("jog", "frame=base", "axis=y", "direction=1").accepted
        if pipe.wait(stale, 5):
            break
    c.send("stop")
    print("watchdog:", stale()[:1])
    assert stale(), "the watchdog did not hold on the missing setpoint_js"
