"""Process-level test: router + every service as separate OS processes on loopback.

Acceptance of the spine: the slave follows the scaled master within 2 mm, no sequence gaps, the
mirror's .rrd holds the slave joint series; SIGKILL of master_capture → the slave holds (< 1 mm);
a restarted master does not move the slave until the clutch engages again (no jump); SIGINT to
the launcher stops everything with exit code 0 and leaves no process behind.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from helpers import clutch_flags
from telesurg.services.launcher import SiteSpec, default_config_dir, free_port, service_argv, wait_port
from telesurg.services.launcher.report import (
    RELEASE_TRIM_S,
    TrackingError,
    engaged_segments,
    tracking_error,
)
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import CartesianPose, JointSetpoint, JointState, OperatingState, SafetyState
from telesurg.tools.bench.harness import OBSERVER_LOSS_MAX

pytestmark = pytest.mark.process

SCALE = 0.5  # the mapping default (deploy/local/site.toml keeps it)


def split_by_scale(
    segments: list[tuple[int, int]], factors: list[tuple[int, float]], scale: float
) -> list[tuple[int, int, float, bool]]:
    """Cut engaged segments where the safety scale factor changes.

    Returns (t0, t1, effective scale, starts an engagement) per part; ``factors`` are time-sorted
    (ns, factor) samples of the watchdog's state.
    """
    out = []
    for t0, t1 in segments:
        cuts = [t for t, _ in _changes(factors) if t0 < t < t1]
        bounds = [t0, *cuts, t1]
        for i, (a, b) in enumerate(itertools.pairwise(bounds)):
            out.append((a, b, scale * _factor_at(factors, a), i == 0))
    return out


def _changes(factors: list[tuple[int, float]]) -> list[tuple[int, float]]:
    out: list[tuple[int, float]] = []
    for t, f in factors:
        if not out or out[-1][1] != f:
            out.append((t, f))
    return out


def _factor_at(factors: list[tuple[int, float]], t: int) -> float:
    f = 1.0
    for tf, v in factors:
        if tf > t:
            break
        f = v
    return f


@dataclass
class Probe:
    """A test-side zenoh client recording what a user would look at."""

    node: Node
    lock: threading.Lock = field(default_factory=threading.Lock)
    master: list[tuple[int, float, float, float]] = field(default_factory=list)
    slave: list[tuple[int, float, float, float]] = field(default_factory=list)
    follow: list[tuple[int, bool]] = field(default_factory=list)
    factors: list[tuple[int, float]] = field(default_factory=list)  # watchdog motion-scale factor

    def __post_init__(self) -> None:
        k = self.node.keys
        self.node.subscribe(k.master("m1", "measured_cp"), CartesianPose, self._on(self.master))
        self.node.subscribe(k.slave("arm1", "measured_cp"), CartesianPose, self._on(self.slave))
        self.node.subscribe(k.slave("arm1", "servo_jp"), JointSetpoint, lambda m, k: None)
        self.node.subscribe(k.slave("arm1", "measured_js"), JointState, lambda m, k: None)
        self.node.subscribe(k.slave("arm1", "operating_state"), OperatingState, self._on_state)
        self.node.subscribe(k.safety("arm1", "state"), SafetyState, self._on_safety)

    def _on_safety(self, msg: SafetyState, key: str) -> None:
        with self.lock:
            self.factors.append((msg.header.stamp_ns, msg.scale))

    def _on(self, store: list[tuple[int, float, float, float]]):  # type: ignore[no-untyped-def]
        def cb(msg: CartesianPose, key: str) -> None:
            with self.lock:
                store.append((msg.header.stamp_ns, *msg.position))

        return cb

    def _on_state(self, msg: OperatingState, key: str) -> None:
        with self.lock:
            self.follow.append((msg.header.stamp_ns, msg.follow))

    def following(self) -> bool:
        with self.lock:
            return bool(self.follow) and self.follow[-1][1]

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        with self.lock:
            return np.array(self.master).reshape(-1, 4), np.array(self.slave).reshape(-1, 4)

    def observer_losses(self, stream: str) -> tuple[int, int, int]:
        """(received, lost, rejected) of ``stream`` at this probe."""
        s = self.node.streams.get(self.node.keys.slave("arm1", stream))
        return s.received, s.lost, s.rejected


def wait_for(pred, timeout: float, what: str) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def tip_at(slave: np.ndarray, t_ns: int) -> np.ndarray:
    """Slave tip position at time t (last sample at or before t)."""
    i = int(np.searchsorted(slave[:, 0], t_ns, side="right")) - 1
    return slave[max(i, 0), 1:]


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture
def site(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], SiteSpec, Path]]:
    port = free_port()
    logs = tmp_path / "logs"
    rrd = tmp_path / "session.rrd"
    argv = [sys.executable, "-m", "telesurg.services.cli", "up", "--port", str(port), "--log-dir", str(logs)]
    argv += ["--save", str(rrd)]
    # the control pipeline without the camera: with one, the mapping maps the master in the
    # endoscope's view frame (docs/console.md), and this test judges the fixed master → base frame
    argv += ["--services", "watchdog,slave_control,mapping,mirror,master_capture"]
    # the operator re-clutches every 4 s: a watchdog hold on this busy host ends one
    # engagement, not the test
    argv += clutch_flags()
    launcher_log = (tmp_path / "launcher.log").open("wb")
    proc = subprocess.Popen(argv, stderr=launcher_log)
    spec = SiteSpec(port=port, config_dir=default_config_dir(), log_dir=logs)
    try:
        assert wait_port("127.0.0.1", port, 20), "router did not come up"
        yield proc, spec, rrd
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        launcher_log.close()
        for f in sorted(logs.glob("*.log")):
            print(f"--- {f.name}\n{f.read_text()[-3000:]}")


def test_pipeline_follow_kill_restart_shutdown(
    site: tuple[subprocess.Popen[bytes], SiteSpec, Path],
) -> None:
    launcher, spec, rrd = site
    with Node(BusConfig(connect=[spec.endpoint]), "local", "test_probe") as node:
        probe = Probe(node)
        # (the launcher starts the services one at a time, each once the previous one is on the
        # bus: on a loaded 2-core host that alone can take tens of seconds)
        wait_for(probe.following, 60, "the slave to follow the master")
        t_follow = time.time_ns()

        # --- 2. the slave tip followed the scaled master motion within 2 mm after settling
        def judge() -> tuple[np.ndarray, int, list[tuple[int, int, float, bool]], TrackingError]:
            master, slave = probe.arrays()
            t_end = int(min(master[-1, 0], slave[-1, 0]))
            with probe.lock:
                factors = sorted(probe.factors)
                follow = sorted(probe.follow)
            # Judged while the slave followed: each engagement (the operator re-clutches; a hold
            # ends one) re-anchors the mapping. The watchdog may also lower the motion scale
            # (DEGRADED, e.g. latency over budget on a busy host); the mapping re-anchors there
            # too, so each part is checked with its own scale. The slave's follow flag outlives a
            # clutch release by up to its setpoint timeout while the master moves on: the last
            # RELEASE_TRIM_S of each engagement are not judged.
            segs = engaged_segments(follow, RELEASE_TRIM_S)
            engaged = [(max(a, t_follow), min(b, t_end)) for a, b in segs if b > t_follow]
            parts = split_by_scale([(a, b) for a, b in engaged if b > a], factors, SCALE)
            return slave, t_end, parts, tracking_error(master, slave, parts, SCALE, np.eye(3), settle_s=0.5)

        # ≥ 5 s of scripted motion; on a busy host whose stalls make the watchdog hold now and
        # then (the operator re-clutches every 4 s), up to 30 s until 2 s of following are judged
        while True:
            time.sleep(1.0)
            slave, t_end, parts, err = judge()
            waited = (time.time_ns() - t_follow) / 1e9
            if (waited >= 6.0 and err.samples > 500) or waited > 30.0:
                break
        sel = (slave[:, 0] > t_follow + 0.5e9) & (slave[:, 0] < t_end)
        travel_mm = np.ptp(slave[sel, 1:], axis=0).max() * 1e3
        scales = sorted({round(p[2], 3) for p in parts})
        print(
            f"tracking error mean {err.mean_mm:.3f} mm, max {err.max_mm:.3f} mm over {err.samples} "
            f"samples in {waited:.0f} s, travel {travel_mm:.1f} mm, scales {scales}"
        )
        assert err.samples > 500, f"only {err.samples} slave samples while following"  # ≥ 2 s at 250 Hz
        # 40 mm master radius × 0.5 → a 40 mm circle (20 mm at a degraded scale)
        assert travel_mm > (30.0 if scales == [SCALE] else 15.0), "the slave did not draw the circle"
        assert err.max_mm < 2.0
        # the probe is an observer the router may drop for on a busy host (as the demo's report
        # node): a few samples lost of thousands, none rejected; the slave's own tracking is above
        for stream in ("servo_jp", "measured_js"):
            received, lost, rejected = probe.observer_losses(stream)
            print(f"probe {stream}: {received} received, {lost} lost, {rejected} rejected")
            assert rejected == 0 and received > 500 and lost <= OBSERVER_LOSS_MAX * received, (
                stream,
                received,
                lost,
            )
        assert node.streams.get(node.keys.slave("arm1", "measured_js")).received > 1000

        # --- 3. SIGKILL master capture: the slave holds
        pids = json.loads((spec.log_dir / "pids.json").read_text())  # type: ignore[operator]
        t_kill = time.time_ns()
        os.kill(pids["master_capture"], signal.SIGKILL)
        wait_for(lambda: not probe.following(), 2, "the slave to hold after the kill")
        time.sleep(1.5)
        _, slave = probe.arrays()
        p_kill = tip_at(slave, t_kill)
        after = slave[slave[:, 0] >= t_kill, 1:]
        moved_mm = np.linalg.norm(after - p_kill, axis=1).max() * 1e3
        print(f"tip motion after SIGKILL: {moved_mm:.3f} mm")
        assert moved_mm < 1.0

        # --- restart master capture: no motion until the clutch engages again, then no jump
        t_restart = time.time_ns()
        master_log = (spec.log_dir / "master_capture.restart.log").open("wb")  # type: ignore[operator]
        restarted = subprocess.Popen(
            service_argv(spec, "master_capture"), stdout=master_log, stderr=subprocess.STDOUT
        )
        try:
            wait_for(probe.following, 15, "re-engage after the master restart")
            with probe.lock:
                t_engage = next(t for t, f in reversed(probe.follow) if not f)  # last hold sample
            time.sleep(1.0)
            _, slave = probe.arrays()
            p_restart = tip_at(slave, t_restart)
            before = slave[(slave[:, 0] >= t_restart) & (slave[:, 0] <= t_engage), 1:]
            drift_mm = np.linalg.norm(before - p_restart, axis=1).max() * 1e3
            win = slave[(slave[:, 0] >= t_engage - 0.2e9) & (slave[:, 0] <= t_engage + 0.2e9), 1:]
            step_mm = np.linalg.norm(np.diff(win, axis=0), axis=1).max() * 1e3
            print(
                f"motion before re-engage {drift_mm:.3f} mm; largest 4 ms step at re-engage {step_mm:.3f} mm"
            )
            assert before.shape[0] > 50, "no slave samples between restart and re-engage"
            assert drift_mm < 0.5
            assert step_mm < 1.0
        finally:
            restarted.send_signal(signal.SIGINT)
            assert restarted.wait(10) == 0
            master_log.close()

    # --- 4. SIGINT to the launcher stops every process, exit code 0, no orphans
    launcher.send_signal(signal.SIGINT)
    assert launcher.wait(30) == 0
    alive = [name for name, pid in pids.items() if pid_alive(pid)]
    assert not alive, f"processes left behind: {alive}"

    # --- the mirror's recording holds the slave joint series
    from helpers import scalar_counts

    assert rrd.exists()
    counts = scalar_counts(rrd)
    assert counts.get("/slave/arm1/joints/measured", 0) > 1000, sorted(counts)[:20]
