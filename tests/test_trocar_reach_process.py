"""Trocar-mode master–slave with the virtual-trocar master as Jinno 2014 runs it (issue #20, acceptance 1).

From each start posture of ``telesurg experiment jinno-insertion`` the test, as the console and
the master (a 250 Hz pose and clutch it publishes itself), adjusts the posture by PTP, inserts
into trocar mode (50 mm), jogs 60 mm deeper (as the experiment's trace does), engages
master–slave with the mapping's ``virtual_trocar`` master at scale 0.5 and draws a 60 mm master
circle on the side that used to take the arm past its reach, then an 80 mm figure-eight;
releases the clutch and removes the forceps.

What a user notices: the slave never sits in an IK hold (the longest run of an unchanged joint
setpoint while the master moves, on the master's clock), the watchdog never goes DEGRADED for joint
speed, the RCM error computed from the measured joints at their full rate stays < 1 mm over all
of trocar mode, and ``remove`` brings the forceps out.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from helpers import MasterHand, operator_command
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import (
    CommandReply,
    JointSetpoint,
    JointState,
    OperatingState,
    SafetyEvent,
    SafetyState,
)
from telesurg.shared.robots.mh3f.kinematics import MH3F
from telesurg.shared.robots.mh3f.trocar import rcm_error
from telesurg.tools.bench.harness import Pipeline
from telesurg.tools.experiment.jinno import STARTS

pytestmark = pytest.mark.process

CIRCLE_R_M = 0.030  # 60 mm master circle
CIRCLE_S = 5.0
EIGHT_HALF_WIDTH_M = 0.040  # 80 mm figure-eight
EIGHT_S = 6.0


def handle(t: float) -> tuple[float, float, float]:
    """Master handle position at ``t`` s after the start of the drawing: circle, then eight, then rest."""
    if t < 0.0:
        return (0.0, 0.0, 0.0)
    if t < CIRCLE_S:  # one-sided: +x handle → −x dummy tip, toward the robot (past its reach before)
        a = 2 * math.pi * t / CIRCLE_S
        return (CIRCLE_R_M * (1.0 - math.cos(a)), CIRCLE_R_M * math.sin(a), 0.0)
    t -= CIRCLE_S
    if t < EIGHT_S:
        a = 2 * math.pi * t / EIGHT_S
        return (EIGHT_HALF_WIDTH_M * math.sin(a), 0.5 * EIGHT_HALF_WIDTH_M * math.sin(2 * a), 0.0)
    return (0.0, 0.0, 0.0)


class Master(MasterHand):
    """250 Hz master pose and clutch; draws :func:`handle` from ``t0``."""

    t0 = math.inf

    def position(self, now: float) -> tuple[float, float, float]:
        return handle(now - self.t0)


@dataclass
class Record:
    """What the test hears on the bus."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    mode: str = ""
    trocar: tuple[float, float, float] = (0.0, 0.0, 0.0)
    follow: bool = False
    lease: bool = False
    rcm_mm: list[float] = field(default_factory=list)  # from measured_js while in trocar mode
    setpoints: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)  # following
    speed_causes: list[str] = field(default_factory=list)
    events: list[tuple[str, str]] = field(default_factory=list)
    event_times: list[float] = field(default_factory=list)  # monotonic s, one per event

    follow_log: list[tuple[float, bool]] = field(default_factory=list)

    def on_state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.mode, self.trocar, self.follow, self.lease = m.control_mode, m.trocar, m.follow, m.lease_ok
            self.follow_log.append((time.monotonic(), m.follow))

    def on_js(self, m: JointState, key: str) -> None:
        with self.lock:
            if self.mode == "trocar":
                self.rcm_mm.append(rcm_error(np.array(m.position), np.array(self.trocar), MH3F) * 1e3)

    def on_sp(self, m: JointSetpoint, key: str) -> None:
        if m.follow:
            with self.lock:
                self.setpoints.append((m.origin_ns, m.position))

    def on_safety(self, m: SafetyState, key: str) -> None:
        if m.state == "DEGRADED":
            with self.lock:
                self.speed_causes += [c for c in m.causes if "rad/s" in c]

    def on_event(self, m: SafetyEvent, key: str) -> None:
        with self.lock:
            self.events.append((m.kind, m.text))
            self.event_times.append(time.monotonic())


def longest_hold_ms(setpoints: list[tuple[int, tuple[float, ...]]], t_from: int, t_to: int) -> float:
    """Longest span [ms, master clock] over which the followed setpoint did not change."""
    sel = [(t, q) for t, q in setpoints if t_from <= t <= t_to]
    longest, run_start = 0.0, None
    for (t0, q0), (t1, q1) in itertools.pairwise(sel):
        if q1 == q0:
            run_start = t0 if run_start is None else run_start
            longest = max(longest, (t1 - run_start) / 1e6)
        else:
            run_start = None
    return longest


@pytest.fixture(params=sorted(STARTS))
def site(
    request: pytest.FixtureRequest, tmp_path: Path
) -> Iterator[tuple[Pipeline, Node, Master, Record, Node]]:
    q = list(STARTS[request.param])
    overrides = {
        "slave_control": [f"q_home={q}", "robot.jog_speed_mm_s=40.0"],
        "mapping": ["master_mode=virtual_trocar", "scale=0.5"],
    }
    with (
        Pipeline(
            tmp_path / "logs", mirror=False, impair=False, master=False, probe=False, overrides=overrides
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as node,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as console,
    ):
        rec = Record()
        k = node.keys
        node.subscribe(k.slave("arm1", "operating_state"), OperatingState, rec.on_state)
        node.subscribe(k.slave("arm1", "measured_js"), JointState, rec.on_js)
        node.subscribe(k.slave("arm1", "servo_jp"), JointSetpoint, rec.on_sp)
        node.subscribe(k.safety("arm1", "state"), SafetyState, rec.on_safety)
        node.subscribe(k.events("*"), SafetyEvent, rec.on_event)
        m = Master(node)
        m.start()
        try:
            yield p, node, m, rec, console  # (console: the operator, the only one who may command)
        finally:
            m.stop.set()
            m.join(2)
            with rec.lock:  # the figure also when the run failed on something else (a loaded host)
                r = list(rec.rcm_mm)
                holds = sum(1 for k, _ in rec.events if k == "hold")
            if r:
                print(f"RCM from measured_js in trocar mode: max {max(r):.3f} mm, mean {np.mean(r):.3f} mm")
                print(f"over {len(r)} samples; {holds} hold events")
    for f in sorted((tmp_path / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-2000:]}")


def test_virtual_trocar_circle_and_eight_then_remove(
    site: tuple[Pipeline, Node, Master, Record, Node],
) -> None:
    pipe, node, master, rec, console = site
    key = node.keys.command("arm1")

    def send(name: str, *args: str) -> CommandReply:
        # as the operator console, confirming a motion-starting command (operator authority)
        r: CommandReply = operator_command(console, key, "arm1", name, *args)
        print(f"{name} {' '.join(args)} -> {'accepted' if r.accepted else 'REFUSED'}: {r.reason}")
        return r

    def now(attr: str) -> object:
        with rec.lock:
            return getattr(rec, attr)

    def held_since(t: float) -> bool:
        """A hold (or a stop) ended a slave-side motion since ``t`` (monotonic s)."""
        with rec.lock:
            return any(
                k in ("hold", "motion_stopped")
                for (k, _), te in zip(rec.events, rec.event_times, strict=True)
                if te >= t
            )

    def until(command: str, mode: str, timeout: float) -> bool:
        """Send ``command`` until the arm is in ``mode``: a watchdog hold (a scheduling stall of this
        busy host) stops a slave-side motion, and the operator commands it again."""
        for _ in range(10):
            assert pipe.wait(lambda: now("lease"), 30), "no lease"
            t = time.monotonic()
            send(command)
            if pipe.wait(lambda t=t: now("mode") == mode or held_since(t), timeout) and pipe.wait(
                lambda: now("mode") == mode, 0.3
            ):
                return True
        return False

    def ptp_aligned() -> bool:
        """Posture adjustment by PTP until finish_posture_adjust is accepted; False on a hold."""
        t = time.monotonic()
        assert send("begin_posture_adjust", "method=ptp").accepted
        while time.monotonic() < t + 20:
            if send("finish_posture_adjust").accepted:
                return True
            if held_since(t):
                return False
            time.sleep(0.2)
        return False

    for _ in range(10):  # a hold stops the PTP: abort back outside and adjust again
        assert pipe.wait(lambda: now("lease"), 30), "no lease"
        if ptp_aligned():
            break
        send("abort", "reason=held during the PTP")
    else:
        pytest.fail("posture adjustment never finished")
    assert until("insert", "trocar", 20), "never reached trocar mode"
    # deeper first, as the experiment's trace does: 1.5 s at 40 mm/s → ~110 mm
    assert send("set_motion_mode", "mode=jog").accepted
    assert send("jog", "frame=forceps", "axis=x", "direction=1").accepted
    time.sleep(1.5)
    assert send("stop").accepted
    time.sleep(0.5)
    assert send("set_motion_mode", "mode=master_slave").accepted
    time.sleep(0.2)
    # Like an operator, draw again if the slave stopped following during the drawing (a watchdog
    # hold on this starved host): the drawing is judged on one the slave followed throughout.
    for attempt in range(1, 6):
        for _ in range(10):  # a refused engage (a hold at the press): release, press again
            assert pipe.wait(lambda: now("lease"), 30), "no lease"
            master.clutch = True
            if pipe.wait(lambda: now("follow"), 3):
                break
            master.clutch = False
            time.sleep(0.5)
        else:
            pytest.fail("the slave never followed in trocar mode")
        t_draw = time.monotonic() + 0.3
        master.t0 = t_draw
        ns_from = time.time_ns() + 300_000_000
        time.sleep(0.3 + CIRCLE_S + EIGHT_S + 0.3)
        ns_to = time.time_ns() - 300_000_000
        master.clutch = False
        master.t0 = math.inf
        with rec.lock:
            lost = [t for t, f in rec.follow_log if t_draw <= t <= t_draw + CIRCLE_S + EIGHT_S and not f]
        if not lost:
            break
        print(f"attempt {attempt}: the slave stopped following (a hold); drawing again")
        assert pipe.wait(lambda: now("lease") and not now("follow"), 30)
        time.sleep(0.3)
    master.clutch = False
    assert pipe.wait(lambda: not now("follow"), 2)
    out_ok = until("remove", "non_trocar", 30)

    with rec.lock:
        hold_ms = longest_hold_ms(rec.setpoints, ns_from, ns_to)
        n_sp = sum(1 for t, _ in rec.setpoints if ns_from <= t <= ns_to)
        rcm = list(rec.rcm_mm)
        speed = list(rec.speed_causes)
        ik_fail = [t for k, t in rec.events if k == "ik_failure"]
        clamps = [t for k, t in rec.events if k == "trocar_clamped"]
        pivots = [t for k, t in rec.events if k == "remove_pivot"]
    print(
        f"followed setpoints {n_sp}; longest IK hold {hold_ms:.0f} ms; RCM max {max(rcm):.3f} mm, "
        f"mean {np.mean(rcm):.3f} mm over {len(rcm)} measured_js in trocar mode; "
        f"speed DEGRADED causes {speed[:3]}; ik_failure events {len(ik_fail)}; "
        f"trocar_clamped events {len(clamps)} {clamps[:2]}; remove pivot {pivots}; out {out_ok}"
    )
    assert not lost, "no drawing was followed throughout in 5 attempts"
    assert n_sp > 0.5 * 250 * (CIRCLE_S + EIGHT_S), "the slave did not follow the drawing"
    assert out_ok, "remove did not bring the forceps out"
    assert not ik_fail, ik_fail[:3]
    assert hold_ms <= 100.0
    assert not speed, speed[:3]
    # issue #20: < 1 mm at the full joint rate, over all of trocar mode (holds and re-engagements
    # included). It was 0.5–1.4 mm idle and 3–11 mm under load while the slave followed each
    # servo_jp as a step (tests/test_trocar_servo_rcm.py shows why); since, under load average
    # 23–35: 0.074, 1.587 (unexplained, docs/trocar.md) and 0.166 mm from start C.
    assert max(rcm) < 1.0
