"""A fourth robot with its own mapping and slave-side motion, from one folder (issue #40, acceptance 1).

``tests/robots/reach3/`` holds everything of the robot ``reach3``: its MJCF model, its kinematics
with a closed-form IK, its config dataclass, its Cartesian mapping strategy (mode ``reach``) and
its motion source (``go_home``); nothing outside the folder names it. One site (router, watchdog,
slave_control on MuJoCo, mapping, master_capture with its scripted 40 mm circle and the clutch
pressed from 9 s to 17 s, every 12 s, mirror) runs with ``--plugin tests/robots/reach3/reach3.py``:

* the robot's own mapping maps the master: every followed setpoint puts the tip exactly at the
  scaled master increment (closed form, no solver residual), and the MuJoCo arm follows;
* its motion: ``go_home`` on ``slave/arm1/command`` is refused while the arm follows the master,
  and once the clutch is released it brings the arm back to its home joints (``go_home_done``).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import operator_command, wait_first
from telesurg.services.launcher import CONTROL_SERVICES, Site, SiteSpec, free_port
from telesurg.shared import robots
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import (
    CartesianPose,
    JointSetpoint,
    JointState,
    OperatingState,
    SafetyEvent,
    SafetyState,
)

pytestmark = pytest.mark.process

PLUGIN = Path(__file__).resolve().parent / "robots" / "reach3" / "reach3.py"
SCALE = 0.5


@dataclass
class Log:
    lock: threading.Lock = field(default_factory=threading.Lock)
    master: dict[int, np.ndarray] = field(default_factory=dict)  # master stamp ns → position
    setpoints: list[tuple[float, np.ndarray, bool, int]] = field(default_factory=list)  # t, q, follow, origin
    js: list[tuple[float, np.ndarray]] = field(default_factory=list)
    safety_scales: list[float] = field(default_factory=list)
    events: list[tuple[float, str, str, str]] = field(default_factory=list)  # t, source, kind, text
    slave_follows: list[tuple[float, bool]] = field(default_factory=list)  # operating_state.follow
    replies: dict[str, Any] = field(default_factory=dict)  # what go_home answered, by moment
    codes: dict[str, int] = field(default_factory=dict)


def _wait(log: Log, site: Site, pred: Callable[[], float | None], timeout: float) -> float | None:
    return wait_first(log.lock, site, pred, timeout)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Log]:
    robots.load_plugin(str(PLUGIN))  # the test's own FK (the services load it from --plugin)
    out = tmp_path_factory.mktemp("reach3")
    common = ['model="reach3"', f"pairs={json.dumps(['m1:arm1'])}"]
    spec = SiteSpec(
        port=free_port(),
        config_dir=None,
        services=CONTROL_SERVICES,
        overrides={
            "watchdog": common,
            "slave_control": ['model="reach3"', "robot.home_speed_rad_s=0.8"],
            "mapping": [*common, 'mode="reach"', f"scale={SCALE}"],
            "master_capture": [
                "rate_hz=100.0",
                "scripted.clutch=[[9.0, 17.0]]",
                "scripted.clutch_repeat_s=12.0",
            ],
            "mirror": [f"save={json.dumps(str(out / 'reach3.rrd'))}"],
        },
        log_dir=out / "logs",
        plugins=(str(PLUGIN),),
    )
    log = Log()
    try:
        with Site(spec) as site, Node(BusConfig(connect=[spec.endpoint]), "local", "console") as node:
            k = node.keys

            def on_master(m: CartesianPose, key: str) -> None:
                with log.lock:
                    log.master[m.header.stamp_ns] = np.array(m.position)

            def on_sp(m: JointSetpoint, key: str) -> None:
                with log.lock:
                    log.setpoints.append((time.monotonic(), np.array(m.position), m.follow, m.origin_ns))

            def on_js(m: JointState, key: str) -> None:
                with log.lock:
                    log.js.append((time.monotonic(), np.array(m.position)))

            def on_safety(m: SafetyState, key: str) -> None:
                with log.lock:
                    log.safety_scales.append(round(m.scale, 6))

            def on_event(m: SafetyEvent, key: str) -> None:
                with log.lock:
                    log.events.append((time.monotonic(), m.header.source, m.kind, m.text))

            node.subscribe(k.master("m1", "measured_cp"), CartesianPose, on_master)
            node.subscribe(k.slave("arm1", "servo_jp"), JointSetpoint, on_sp)
            node.subscribe(k.slave("arm1", "measured_js"), JointState, on_js)
            node.subscribe(k.safety("arm1", "state"), SafetyState, on_safety)
            node.subscribe(k.events(), SafetyEvent, on_event)

            def on_state(m: OperatingState, key: str) -> None:
                with log.lock:
                    log.slave_follows.append((time.monotonic(), m.follow))

            node.subscribe(k.slave("arm1", "operating_state"), OperatingState, on_state)

            t_engage = _wait(log, site, lambda: next((t for t, _, f, _ in log.setpoints if f), None), 45.0)
            assert t_engage is not None, "the mapping never engaged"
            cmd = k.command("arm1")
            # A loaded host may make the watchdog hold (a stale stream) and end an engagement: the
            # clutch is pressed again every 12 s, so each step below has a few tries.
            for _ in range(3):  # go_home while the slave follows the master: refused
                following = _wait(
                    log, site, lambda: next((t for t, f in log.slave_follows[-1:] if f), None), 15.0
                )
                assert following is not None, "the slave never followed"
                time.sleep(1.0)  # away from home along the circle
                log.replies["following"] = r = operator_command(node, cmd, "arm1", "go_home")
                if not r.accepted:
                    break
            for _ in range(3):  # go_home with the clutch released: the arm goes home
                t0 = time.monotonic()

                def released(t0: float = t0) -> float | None:
                    return next(
                        (
                            t
                            for t, s, kind, text in log.events
                            if t > t0 and kind == "disengage" and "clutch" in text
                        ),
                        None,
                    )

                assert _wait(log, site, released, 20.0) is not None, "the clutch was never released"
                time.sleep(0.3)
                t_cmd = log.replies["t_cmd"] = time.monotonic()
                log.replies["released"] = operator_command(node, cmd, "arm1", "go_home")

                def done(t_cmd: float = t_cmd) -> float | None:
                    return next(
                        (t for t, _, kind, _ in log.events if t > t_cmd and kind == "go_home_done"), None
                    )

                if log.replies["released"].accepted and _wait(log, site, done, 3.0) is not None:
                    break
            else:
                raise AssertionError("go_home never ended")
            time.sleep(0.5)  # the servos settle
            with log.lock:
                log.replies["at_home"] = log.js[-1][1]
            log.codes = site.stop()
    finally:
        for f in sorted((out / "logs").glob("*.log")):
            print(f"--- {f.name}\n{f.read_text()[-3000:]}", file=sys.stderr)
    yield log


def test_the_robots_own_mapping_puts_the_tip_at_the_scaled_master_increments(run: Log) -> None:
    arm = robots.get("reach3").arm("arm1")
    follow = [(t, q, o) for t, q, f, o in run.setpoints if f]
    assert len(follow) > 100, f"only {len(follow)} followed setpoints"
    factors = sorted({SCALE * s for s in run.safety_scales} | {SCALE})
    # consecutive setpoints of one engagement (a hold and a new press in between start afresh)
    pairs = [
        ((a[0], a[1], a[3]), (b[0], b[1], b[3]))
        for a, b in pairwise(run.setpoints)
        if a[2] and b[2] and a[3] in run.master and b[3] in run.master
    ]
    assert len(pairs) > 0.8 * len(follow)
    err = []
    for (_, qa, oa), (_, qb, ob) in pairs:
        d_tip, d_m = arm.tip(qb) - arm.tip(qa), run.master[ob] - run.master[oa]
        if np.linalg.norm(d_tip) < 1e-12:
            continue  # a re-anchor (the watchdog's scale changed) or a repeated sample
        err.append(min(float(np.linalg.norm(d_tip - k * d_m)) for k in factors))
    assert len(err) > 0.8 * len(pairs)
    assert max(err) < 1e-6, f"{max(err) * 1e3:.4f} mm off the scaled increment"  # closed form: exact
    travel = max(float(np.linalg.norm(arm.tip(q) - arm.tip(follow[0][1]))) for _, q, _ in follow)
    assert travel > 0.01  # the tip went around the 20 mm circle


def test_go_home_waits_for_the_clutch_and_brings_the_arm_home(run: Log) -> None:
    following, released = run.replies["following"], run.replies["released"]
    assert not following.accepted and "release the clutch" in following.reason, following
    assert released.accepted, released.reason
    home = np.array(robots.get("reach3").arm("arm1").home)
    before = [q for t, q in run.js if t <= run.replies["t_cmd"]][-1]
    assert float(np.max(np.abs(before - home))) > 0.02  # the mapping had moved it away
    assert float(np.max(np.abs(run.replies["at_home"] - home))) < 0.005
    assert all(c == 0 for c in run.codes.values()), run.codes
