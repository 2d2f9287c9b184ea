"""The PLAS site end to end (issue #5, acceptance 3).

The encoder-board emulator on a real pseudo-terminal → ``master_capture --device serial`` → the
all-joints mapping (Table-6 factors) → the MuJoCo PLAS slave, both arms. Each slave joint must
follow its mapped master joint; unplugging the board (SIGKILL of the emulator) must hold the slave;
a new board resumes only after a new engage (clutch press).

The master_capture port is a symlink to the emulator's pty, like ``/dev/serial/by-id/…`` on a
real machine: a restarted emulator gets a new pty and the link is moved to it.
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import JointSetpoint, JointState, OperatingState, SafetyEvent, SafetyState
from telesurg.shared.robots.plas import kinematics as plas
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process
DEPLOY = Path(__file__).resolve().parents[1] / "deploy" / "plas"
ARMS = ("arm1", "arm2")


class Board:
    """The emulator process and the symlink master_capture opens."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "telesurg.tools.emulate",
                "emulate",
                "--pty",
                "--rate",
                "200",
                "--counts-per-rev",
                "1600",
                "--clutch-repeat",  # the operator re-clutches every 3 s: a hold on this busy
                "3",  # host ends one stretch of following, not the test
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None
        pty = self.proc.stdout.readline().strip()
        assert pty.startswith("/dev/"), pty
        tmp = self.link.with_suffix(".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(pty)
        os.replace(tmp, self.link)  # atomic, like udev moving a by-id link

    def kill(self) -> None:
        if self.proc is None:
            return
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


class Log:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.master: list[tuple[float, np.ndarray, int]] = []  # (t, q, stamp_ns)
        self.js: dict[str, list[tuple[float, np.ndarray]]] = {a: [] for a in ARMS}
        self.sp: dict[str, list[tuple[float, np.ndarray, bool, int]]] = {a: [] for a in ARMS}  # origin_ns
        self.state: dict[str, list[tuple[float, bool, bool]]] = {a: [] for a in ARMS}
        self.scale: dict[str, list[tuple[float, float]]] = {a: [] for a in ARMS}  # the watchdog's
        self.events: list[tuple[float, str, str, str]] = []  # (sent, on the monotonic clock)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Board, Log]]:
    tmp = tmp_path_factory.mktemp("plas")
    board = Board(tmp / "ttyPLAS")
    overrides = {"master_capture": [f'serial.port="{board.link}"']}
    log = Log()
    try:
        with (
            Pipeline(
                tmp / "logs", mirror=False, impair=False, probe=False, overrides=overrides, config_dir=DEPLOY
            ) as p,
            Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as node,
        ):
            k = node.keys

            def on_master(m: JointState, key: str) -> None:
                with log.lock:
                    log.master.append((time.monotonic(), np.array(m.position), m.header.stamp_ns))

            node.subscribe(k.master("m1", "measured_js"), JointState, on_master)
            for arm in ARMS:

                def on_js(m: JointState, key: str, arm: str = arm) -> None:
                    with log.lock:
                        log.js[arm].append((time.monotonic(), np.array(m.position)))

                def on_sp(m: JointSetpoint, key: str, arm: str = arm) -> None:
                    with log.lock:
                        log.sp[arm].append((time.monotonic(), np.array(m.position), m.follow, m.origin_ns))

                def on_state(m: OperatingState, key: str, arm: str = arm) -> None:
                    with log.lock:
                        log.state[arm].append((time.monotonic(), m.follow, m.lease_ok))

                def on_safety(m: SafetyState, key: str, arm: str = arm) -> None:
                    with log.lock:
                        log.scale[arm].append((time.monotonic(), m.scale))

                node.subscribe(k.slave(arm, "measured_js"), JointState, on_js)
                node.subscribe(k.slave(arm, "servo_jp"), JointSetpoint, on_sp)
                node.subscribe(k.slave(arm, "operating_state"), OperatingState, on_state)
                node.subscribe(k.safety(arm, "state"), SafetyState, on_safety)

            def on_event(m: SafetyEvent, key: str) -> None:
                with log.lock:
                    # when it was sent, on this clock: an event (DATA_HIGH, batched) may arrive
                    # after a real-time state its sender published later
                    sent = time.monotonic() - max(0.0, (time.time_ns() - m.header.stamp_ns) / 1e9)
                    log.events.append((sent, m.arm, m.kind, m.text))

            node.subscribe(k.events(), SafetyEvent, on_event)
            board.start()  # after the site is up: the clutch is released for 1 s, then pressed
            yield board, log
    finally:
        board.kill()
    for f in sorted((tmp / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-2500:]}")


LAG_S = 0.4  # s: how late on the commanded path a measured configuration may be (see above)


def _follow_stretches(states: list[tuple[float, bool, bool]]) -> list[tuple[float, float]]:
    """(start, end) of every uninterrupted stretch of following."""
    out, start = [], None
    for t, f, _ in states:
        if f and start is None:
            start = t
        elif not f and start is not None:
            out.append((start, t))
            start = None
    if start is not None:
        out.append((start, states[-1][0]))
    return out


def wait(pred, timeout: float) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)
    return False


def following(log: Log, arm: str) -> bool:
    with log.lock:
        return bool(log.state[arm]) and log.state[arm][-1][1]


def test_slave_joints_follow_the_mapped_master_joints(site: tuple[Board, Log]) -> None:
    _, log = site
    assert wait(lambda: all(following(log, a) for a in ARMS), 15), "the slave never followed"
    time.sleep(5.0)
    with log.lock:
        master = list(log.master)
        sp = {a: list(v) for a, v in log.sp.items()}
        js = {a: list(v) for a, v in log.js.items()}
        states = {a: list(v) for a, v in log.state.items()}
        scales = {a: list(v) for a, v in log.scale.items()}
    for arm in ARMS:
        # every uninterrupted stretch of following (re-clutching every 3 s, or a watchdog hold on
        # this busy host, ends one)
        stretches = _follow_stretches(states[arm])
        assert stretches, f"{arm} never followed"

        def setpoints(t0: float, t_end: float) -> list[tuple[float, np.ndarray, int]]:
            return [(t, q, o) for t, q, f, o in sp[arm] if f and t0 - 0.1 <= t <= t_end]  # noqa: B023

        # 1) the slave tracks its setpoints: every measured configuration is one commanded within
        #    the last LAG_S (judged on the path, so this busy host's scheduling delays don't count:
        #    a CI machine under load stalls a process for 150-250 ms now and then, and the slave
        #    then lags its path by that much while on it; off the path it would be far from every
        #    setpoint of the window)
        errs, qs_all = [], []
        for t0, t_end in stretches:
            follow_sp = setpoints(t0, t_end)
            if not follow_sp:
                continue
            ts = np.array([t for t, _, _ in follow_sp])
            qs = np.array([q for _, q, _ in follow_sp])
            qs_all.append(qs)
            for t, q in js[arm]:
                if not t0 + 0.3 <= t <= t_end - 0.05:
                    continue
                recent = qs[(ts >= t - LAG_S) & (ts <= t)]
                if len(recent):
                    errs.append(np.abs(recent - q).max(axis=1).min())
        err, err99 = float(np.max(errs)), float(np.percentile(errs, 99))
        # 2) the setpoints are the Table-6 mapping of the master's motion: replay the master
        #    samples seen during the longest stretch through the same mapping, from its first
        #    setpoint (each engage starts the integration anew)
        follow_sp = setpoints(*max(stretches, key=lambda s: s[1] - s[0]))
        qs = np.array([q for _, q, _ in follow_sp])
        o_first, o_last = follow_sp[0][2], follow_sp[-1][2]  # master stamps behind the setpoints
        #    at the watchdog's scale of the moment (DEGRADED, e.g. late samples on a loaded host,
        #    scales the master's increments down, as the mapping does)
        seen = [(t, q) for t, q, st in master if o_first <= st <= o_last]
        st_scale = scales[arm]

        def scale_at(t: float, st_scale: list[tuple[float, float]] = st_scale) -> float:
            return next((s for ts, s in reversed(st_scale) if ts <= t), 1.0)

        q = qs[0].copy()
        cfg = plas.MappingConfig(d1_speed=0.010)
        reduced = 0
        for (_, a), (t, b) in itertools.pairwise(seen):
            s = scale_at(t)
            reduced += s < 1.0
            q = plas.map_step(q, a, (b - a) * s, dt=0.005 * s, config=cfg).q
        moved = np.ptp(np.concatenate(qs_all), axis=0)
        print(
            f"{arm}: followed {len(stretches)} stretches, the longest "
            f"{follow_sp[-1][0] - follow_sp[0][0]:.1f} s; "
            f"slave joints moved {np.round(moved, 3)}; distance from the commanded path p99 {err99:.4f}, "
            f"max {err:.4f} over {len(errs)} samples; "
            f"mapping replay vs last setpoint {np.round(q - qs[-1], 4)} "
            f"({reduced} of {len(seen) - 1} master steps at a reduced scale)"
        )
        assert np.all(moved[1:4] > 0.02)  # θ2, θ3, θ4 really moved
        # rad (the slides move less than 0.01 m): 99 % of the samples within the engage tolerance
        # (idle: max 0.006-0.009); a CI stall can push a few samples off the path while the slave
        # catches up (seen: up to 0.038), so single samples are bounded at 0.05
        assert len(errs) > 150 and err99 < 0.02 and err < 0.05
        assert np.allclose(q[1:], qs[-1][1:], atol=0.02)  # the Table-6 mapping of the master motion


def test_unplugged_board_holds_and_a_new_board_needs_a_new_engage(site: tuple[Board, Log]) -> None:
    board, log = site
    assert wait(lambda: all(following(log, a) for a in ARMS), 15)
    t_kill = time.monotonic()
    board.kill()  # unplug
    assert wait(lambda: not any(following(log, a) for a in ARMS), 2.0), "the slave kept following"
    with log.lock:
        t_hold = min(t for a in ARMS for t, f, _ in log.state[a] if t >= t_kill and not f)
    print(f"board unplugged: the slave stopped following after {(t_hold - t_kill) * 1e3:.0f} ms")
    time.sleep(1.0)
    with log.lock:
        q_still = {a: log.js[a][-1][1] for a in ARMS}
    t_new = time.monotonic()
    board.start()  # a new board on a new pty behind the same link
    assert wait(lambda: all(following(log, a) for a in ARMS), 15), "never resumed after the new board"

    def engaged() -> bool:
        with log.lock:
            return any(k == "engage" and t >= t_new for t, _, k, _ in log.events)

    assert wait(engaged, 5), "resumed without an engage event"
    with log.lock:
        engages = [t for t, a, k, _ in log.events if k == "engage" and t >= t_new]
        first_follow = min(t for a in ARMS for t, f, _ in log.state[a] if t >= t_new and f)
        still = [
            float(np.max(np.abs(q - q_still[a])))
            for a in ARMS
            for t, q in log.js[a]
            if t_new <= t < min(engages)
        ]
    print(
        f"new board: engage {(min(engages) - t_new):.2f} s after it started (its clutch is pressed at 1 s), "
        f"first follow {(first_follow - t_new):.2f} s; "
        f"slave motion before the engage {max(still) * 1e3:.3f} mrad"
    )
    assert engages and first_follow >= min(engages)  # resumed only through a new engage
    assert max(still) < 1e-3  # and nothing moved before it
