"""The VIP site through the running services (issue #6, acceptance 2).

Router, watchdog, mapping (``mode = "vip"``), slave_control (MuJoCo, two VIP arms) and a scripted
master at the paper's console rate (25 Hz, one sample every 40 ms) driving both arms. The MuJoCo
wrists must follow the commanded path, and the 1 kHz interpolation must leave no velocity steps.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from helpers import operator_command
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import (
    CartesianPose,
    CommandReply,
    JointSetpoint,
    JointState,
    SafetyEvent,
)
from telesurg.shared.robots.vip import kinematics as vip
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process
DEPLOY = Path(__file__).resolve().parents[1] / "deploy" / "vip"
ARMS = {"arm1": vip.VIP_ARM1, "arm2": vip.VIP_ARM2}


class Log:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.wrist: dict[str, list[tuple[float, np.ndarray]]] = {a: [] for a in ARMS}
        # (receive time s, q, v, the slave's stamp s)
        self.js: dict[str, list[tuple[float, np.ndarray, np.ndarray, float]]] = {a: [] for a in ARMS}
        self.sp: dict[str, list[tuple[float, np.ndarray, bool]]] = {a: [] for a in ARMS}
        self.events: list[tuple[str, str, str]] = []


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Pipeline, Node, Log]]:
    logs = tmp_path_factory.mktemp("vip") / "logs"
    overrides = {  # deploy/vip: the console master m1 drives both arms
        "master_capture": ["scripted.clutch=[[1.0, 1e9]]", "scripted.clutch_repeat_s=0.0"],  # one engage
    }
    with (
        Pipeline(logs, mirror=False, impair=False, probe=False, overrides=overrides, config_dir=DEPLOY) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as node,
    ):
        log = Log()
        k = node.keys
        for arm in ARMS:

            def on_cp(m: CartesianPose, key: str, arm: str = arm) -> None:
                with log.lock:
                    log.wrist[arm].append((time.monotonic(), np.array(m.position)))

            def on_js(m: JointState, key: str, arm: str = arm) -> None:
                with log.lock:
                    q, v = np.array(m.position), np.array(m.velocity)
                    log.js[arm].append((time.monotonic(), q, v, m.header.stamp_ns / 1e9))

            def on_sp(m: JointSetpoint, key: str, arm: str = arm) -> None:
                with log.lock:
                    log.sp[arm].append((time.monotonic(), np.array(m.position), m.follow))

            node.subscribe(k.slave(arm, "measured_cp"), CartesianPose, on_cp)
            node.subscribe(k.slave(arm, "measured_js"), JointState, on_js)
            node.subscribe(k.slave(arm, "servo_jp"), JointSetpoint, on_sp)

        def on_event(m: SafetyEvent, key: str) -> None:
            with log.lock:
                log.events.append((m.arm, m.kind, m.text))

        node.subscribe(k.events(), SafetyEvent, on_event)
        yield p, node, log
    for f in sorted(logs.glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-2000:]}")


def followed(log: Log) -> bool:
    """Both arms have received a followed setpoint."""
    with log.lock:
        return all(any(f for _, _, f in log.sp[a]) for a in ARMS)


def test_both_wrists_follow_25hz_commands_smoothly(site: tuple[Pipeline, Node, Log]) -> None:
    _, _, log = site
    # engage at 1 s of the master's clock (later if this loaded host was slow to start it), then
    # 8 s = one full 20 mm wrist circle
    deadline = time.monotonic() + 30.0
    while not followed(log) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(8.0)
    with log.lock:
        sp = {a: list(v) for a, v in log.sp.items()}
        js = {a: list(v) for a, v in log.js.items()}
        wrist = {a: list(v) for a, v in log.wrist.items()}
        kinds = [k for _, k, _ in log.events]
    for arm, geom in ARMS.items():
        follow = [(t, q) for t, q, f in sp[arm] if f]
        assert len(follow) > 150, f"{arm}: only {len(follow)} followed setpoints"
        t0, t1 = follow[0][0], follow[-1][0]
        rate = (len(follow) - 1) / (t1 - t0)
        # the commanded wrist path (FK of every setpoint) and the MuJoCo wrist site
        path = np.array([vip.fk(q, geom).wrist for _, q in follow])
        meas = np.array([p for t, p in wrist[arm] if t0 + 0.2 <= t <= t1])
        d = np.min(np.linalg.norm(meas[:, None, :] - path[None, :, :], axis=2), axis=1) * 1e3
        travel = float(np.ptp(meas, axis=0).max()) * 1e3
        # velocity smoothness: joint-velocity change between 4 ms samples vs the velocity itself
        sel = [(vv, st) for t, _, vv, st in js[arm] if t0 + 0.5 <= t <= t1]
        v = np.array([vv for vv, _ in sel])
        # per 4 ms of the slave's clock: a sample published late (the loop was descheduled and
        # caught up) is compared over the time that really passed
        gaps = np.maximum(np.diff([st for _, st in sel]) / 0.004, 1.0)
        steps = np.abs(np.diff(v, axis=0)) / gaps[:, None]
        dv, dv_max = np.percentile(steps, 99, axis=0), steps.max(axis=0)
        vmax = np.abs(v).max(axis=0)
        print(
            f"{arm}: setpoints at {rate:.1f} Hz; wrist travel {travel:.1f} mm, distance from the "
            f"commanded path max {d.max():.3f} mm (mean {d.mean():.3f}); joint speed max "
            f"{np.round(vmax, 3)}, change per 4 ms p99 {np.round(dv, 4)}, max {np.round(dv_max, 4)}"
        )
        assert 20.0 <= rate <= 30.0  # the paper's console rate
        assert travel > 15.0  # the wrist really drew the 20 mm circle
        assert d.max() < 1.0, f"{arm}: wrist {d.max():.2f} mm off the commanded path"
        # a 25 Hz staircase would change the speed by ~its full value every 40 ms (every 10th
        # sample, so its p99 is that); interpolated, the speed changes only by what the path's
        # curvature asks for between 4 ms samples. A rare larger step is a scheduling stall of
        # this busy host (the slave replays the periods it slept through; it is printed above).
        moving = vmax > 0.05
        assert np.all(dv[moving] < 0.25 * vmax[moving]), f"{arm}: velocity steps {dv} vs {vmax}"
    assert "hold" not in kinds


def test_vip_commands_refused_while_following_and_reported(site: tuple[Pipeline, Node, Log]) -> None:
    _, node, log = site
    key = node.keys.mapping_command("arm1")

    def send(name: str, *args: str) -> CommandReply:
        r = operator_command(node, key, "arm1", name, *args)
        print(f"{name} {' '.join(args)} -> {'accepted' if r.accepted else 'REFUSED'}: {r.reason}")
        return r

    assert send("state").accepted
    r = send("reallocate_vip", "ev_mm=30")
    assert not r.accepted and "release the clutch" in r.reason  # following: a new VIP would move the elbow
    r = send("reallocate_vip", "ev_mm=80")
    assert not r.accepted
    with log.lock:
        vips = [t for a, k, t in log.events if k == "vip" and a == "arm1"]
    assert vips and "first engage" in vips[0]
