"""mirror as a real process: bus traffic in, a complete .rrd out, garbage survived."""

from __future__ import annotations

import math
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import drawn_body_poses, entity_paths, scalar_counts, scalar_rows, series_names, text_logs
from telesurg.shared import robots
from telesurg.shared.bus import BusConfig, Node, open_session
from telesurg.shared.messages import JointState, SafetyEvent

ROOT = Path(__file__).resolve().parents[1]
JOINTS = ("j1", "j2", "j3", "j4", "j5", "j6")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _wait_alive(node: Node, service: str, timeout_s: float) -> bool:
    seen = threading.Event()
    node.watch_liveliness(node.keys.alive(service), lambda _svc, alive: seen.set() if alive else None)
    return seen.wait(timeout_s)


def _matching(publisher: Any) -> bool:
    """A subscriber (the mirror's) matches this publisher (zenoh's stub types this as bool)."""
    return bool(publisher.matching_status.matching)


@pytest.mark.process
def test_mirror_records_bus_traffic_to_rrd(tmp_path: Path) -> None:
    ep = f"tcp/127.0.0.1:{_free_port()}"
    out = tmp_path / "out.rrd"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    proc: subprocess.Popen[str] | None = None
    try:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "telesurg.services.cli",
                "mirror",
                "--connect",
                ep,
                "--set",
                f"save='{out}'",
            ],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        # The mirror draws master/slave/safety streams only from the services that own them.
        with (
            Node(BusConfig(connect=[ep]), "local", "slave_control") as node,
            Node(BusConfig(connect=[ep]), "local", "intruder") as intruder,
        ):
            assert _wait_alive(node, "mirror", 15.0), "mirror never joined the bus"
            js = node.outlet(node.keys.slave("arm1", "measured_js"), control=False)
            events = node.outlet(node.keys.events("slave_control"), control=False)
            fake = intruder.outlet(node.keys.slave("arm1", "measured_js"), control=False)
            raw = node.session.declare_publisher(node.keys.slave("arm1", "measured_js"))
            # The liveliness token precedes the subscribers by a few ms; wait until they match
            # (events/* is the mirror's last subscription: a stall may delay it behind the others).
            raw_events = node.session.declare_publisher(node.keys.events("slave_control"))
            deadline = time.monotonic() + 5.0
            while not (_matching(raw) and _matching(raw_events)) and time.monotonic() < deadline:
                time.sleep(0.02)
            raw_events.undeclare()  # type: ignore[no-untyped-call]
            time.sleep(0.2)

            sent = 0
            t0 = time.monotonic()
            for i in range(250):
                q = tuple(0.3 * math.sin(0.02 * i + k) for k in range(6))
                js.put(JointState(js.header(), JOINTS, q))
                sent += 1
                if i == 100:
                    raw.put(b"garbage")
                if i % 10 == 0:  # a look-alike from a service that does not own the stream
                    fake.put(JointState(fake.header(), JOINTS, (3.0,) * 6))
                if i % 60 == 0:
                    events.put(SafetyEvent(events.header(), "arm1", "test", "warning", f"event {i}"))
                time.sleep(max(0.0, t0 + (i + 1) / 250 - time.monotonic()))
            raw.undeclare()  # type: ignore[no-untyped-call]
            time.sleep(1.0)  # let the last samples (and the last event) reach the mirror

        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=15)
        assert proc.returncode == 0, stderr
        assert "rejected message" in stderr  # the garbage was seen and counted, not fatal
        assert "not an allowed source" in stderr  # so was the look-alike

        assert out.is_file()
        paths = entity_paths(out)
        assert "/slave/arm1/joints/measured" in paths
        # the robot's own bodies, not the stick figure
        assert "link1" in drawn_body_poses(out, robots.get("mh3f")), sorted(paths)
        assert "/slave/arm1/links" not in paths, sorted(paths)
        assert "/events" in paths
        n = scalar_counts(out).get("/slave/arm1/joints/measured", 0)
        assert 0.9 * sent <= n <= sent, (n, sent)
        # one row per sample holding every joint, and the genuine values only (not the 3.0s)
        rows = scalar_rows(out, "/slave/arm1/joints/measured")
        assert {len(r) for r in rows} == {6} and max(max(abs(v) for v in r) for r in rows) <= 0.3
        assert series_names(out, "/slave/arm1/joints/measured") == [f"{j} measured" for j in JOINTS]
        logged = [t for p, _lvl, t in text_logs(out) if p == "/events"]
        # the mirror's own report of the unsigned garbage (shared/auth.py) is an event too
        assert [t for t in logged if t.startswith("unauthenticated: rejected message on")]
        logged = [t for t in logged if not t.startswith("unauthenticated:")]
        assert logged == [f"[arm1] test: event {i}" for i in range(0, 250, 60)]
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5)
        router.close()  # type: ignore[no-untyped-call]


def test_mirror_shows_the_teleop_state_of_each_pair(tmp_path: Path) -> None:
    from telesurg.services.mirror import Mirror
    from telesurg.services.mirror.view import RerunView
    from telesurg.shared.messages import Header, TeleopState

    out = tmp_path / "teleop.rrd"
    view = RerunView("test", save=str(out))
    mirror = Mirror(view, "telesurg/local", trail_s=1.0, trail_hz=10.0)
    key = "telesurg/local/mapping/arm1/teleop_state"
    t0 = 1_700_000_000_000_000_000
    states = [("DISABLED", "DISABLED", "no master buttons yet"), ("IDLE", "DISABLED", "ready to engage")]
    states += [("ENABLED", "IDLE", "engaged m1 → arm1 at scale 0.5")] * 3  # re-sent at 10 Hz: one line
    states += [("HOLDING", "ENABLED", "slave holding: lease expired")]
    items = [
        (
            key,
            t0 + i,
            TeleopState(Header("mapping", i, t0 + i), "m1", "arm1", s, p, r, t0, 0.5, 1.0, "cartesian"),
        )
        for i, (s, p, r) in enumerate(states)
    ]
    mirror.feed(items)  # type: ignore[arg-type]
    view.close()
    lines = [(lvl, t) for p, lvl, t in text_logs(out) if p == "/mapping/arm1/teleop"]
    assert [t.split(" (")[0] for _, t in lines] == ["DISABLED", "IDLE", "ENABLED", "HOLDING"], lines
    assert lines[-1][0] == "WARN" and "slave holding: lease expired" in lines[-1][1], lines
    assert "was ENABLED" in lines[-1][1] and "scale 0.5 × safety 1" in lines[-1][1], lines
    # the engaged step signal: its changes (0, 1, 0); a repeat within 1/STEP_HZ is not sent again
    assert scalar_rows(out, "/mapping/arm1/engaged") == [[0.0], [1.0], [0.0]]


def test_the_mirror_file_has_no_footer_and_rerun_can_add_one(tmp_path: Path) -> None:
    """rerun keeps a footer's chunk manifest in memory for the whole session, so the mirror's
    .rrd is written without one by default (``rrd_footer``); the file still opens, and rerun's
    CLI adds the footer afterwards, as docs/console.md says."""
    import warnings

    from rerun.chunk import RrdReader
    from telesurg.services.mirror.view import RerunView

    def chunks(path: Path) -> tuple[int, list[str]]:
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            n = sum(1 for _ in RrdReader(str(path)).stream())
        return n, [str(w.message) for w in seen if "footer" in str(w.message)]

    for footer in (False, True):
        out = tmp_path / f"footer{int(footer)}.rrd"
        view = RerunView("test", save=str(out), rrd_footer=footer)
        t0 = 1_700_000_000_000_000_000
        for i in range(50):  # 50 blocks of one sample: 50 chunks
            view.series("/slave/arm1/joints/measured", [t0 + i * 10**6], [t0 + i * 10**6], [0.01 * i])
        view.close()
        n, said = chunks(out)
        assert n > 0 and bool(said) is not footer, (footer, n, said)
    fixed = tmp_path / "optimized.rrd"
    rerun_cli = Path(sys.executable).with_name("rerun")
    cmd = [str(rerun_cli), "rrd", "optimize", str(tmp_path / "footer0.rrd"), "-o", str(fixed)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    n, said = chunks(fixed)
    assert n > 0 and not said, said
    assert scalar_counts(fixed)["/slave/arm1/joints/measured"] == 50


def _lean_live_session(out: Path, offview_hz: float) -> None:
    """3 s of an MH3F measured at 250 Hz, its master pose and clutch at 50 Hz, fed to a Mirror
    the way its loop does (a batch, then draw()), as a serving lean mirror would get them."""
    from telesurg.services.mirror import Mirror
    from telesurg.services.mirror.view import RerunView
    from telesurg.shared.messages import CartesianPose, Header, JointState, MasterButtons

    p = robots.get("mh3f").arms("arm1")[0]
    view = RerunView("test", save=str(out))
    mirror = Mirror(
        view, "telesurg/local", trail_s=1.0, trail_hz=10.0, series_hz=4.0, draw_hz=5.0,
        layout="lean", offview_hz=offview_hz,
    )  # fmt: skip
    t0 = 1_700_000_000_000_000_000
    for i in range(750):
        stamp = t0 + i * 4_000_000
        q = tuple(float(v) + 0.1 * np.sin(i / 100) for v in p.home)
        js = JointState(Header("slave_control", i, stamp), p.joint_names, q)
        items: list[tuple[str, int, object]] = [("telesurg/local/slave/arm1/measured_js", stamp, js)]
        if i % 5 == 0:
            h = Header("master_capture", i, stamp)
            pose = CartesianPose(h, "master", (0.01 * np.sin(i / 50), 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
            items.append(("telesurg/local/master/m1/measured_cp", stamp, pose))
            buttons = MasterButtons(h, (i // 100) % 2 == 1, True)
            items.append(("telesurg/local/master/m1/buttons", stamp, buttons))
        mirror.feed(items)  # type: ignore[arg-type]
        mirror.draw()
    view.close()


def test_a_live_lean_mirror_sends_what_its_layout_does_not_show_in_1_s_blocks(tmp_path: Path) -> None:
    """The lean layout shows the slave 3D view, the joint plots and the text log; while serving,
    the rest (master trail, clutch, …) goes out in 1 s blocks — every sample, fewer chunks for the
    web viewer to take in — and the joints still every 1/series_hz."""
    from rerun.chunk import RrdReader

    counts: dict[float, dict[str, int]] = {}  # scalar blocks (one chunk each) or logged rows
    rows: dict[float, dict[str, list[list[float]]]] = {}
    for hz in (0.0, 1.0):
        out = tmp_path / f"offview-{hz}.rrd"
        _lean_live_session(out, hz)
        n: dict[str, int] = {}
        for c in RrdReader(str(out)).stream():
            # trails and poses are logged row by row (batched into chunks by rerun): count their rows
            n[c.entity_path] = n.get(c.entity_path, 0) + (
                c.num_rows if c.entity_path.endswith(("/tip", "/mh3f")) else 1
            )
        counts[hz] = n
        rows[hz] = {e: scalar_rows(out, e) for e in ("/master/m1/clutch", "/slave/arm1/joints/measured")}
    clutch, joints, master, robot = (
        "/master/m1/clutch",
        "/slave/arm1/joints/measured",
        "/master/m1/tip",
        "/slave/geometry/mh3f",
    )
    # 3 s at 1 Hz (and the last block at close) against 3 s at 4 Hz
    assert counts[1.0][clutch] <= 5 < counts[0.0][clutch], counts
    # the master's trail drawn at 1 Hz, the robot (shown) at the 5 Hz scene rate
    assert counts[1.0][master] <= 5 < counts[0.0][master], counts
    assert counts[1.0][robot] == counts[0.0][robot] >= 10, counts
    assert counts[1.0][joints] == counts[0.0][joints] >= 10, counts
    # the same samples either way: nothing the viewer is sent later is lost
    assert rows[1.0] == rows[0.0]
    assert [r[0] for r in rows[1.0][clutch]].count(1.0) > 0


def test_a_live_mirror_redraws_the_trails_at_their_own_rate(tmp_path: Path) -> None:
    """``trail_draw_hz``: the whole tip trail is one message per redraw; a serving mirror redraws
    it once a second while the robot's bodies follow at the scene rate."""
    from rerun.chunk import RrdReader
    from telesurg.services.mirror import Mirror
    from telesurg.services.mirror.view import RerunView
    from telesurg.shared.messages import CartesianPose, Header, JointState

    p = robots.get("mh3f").arms("arm1")[0]
    rows: dict[float, dict[str, int]] = {}
    for hz in (0.0, 1.0):
        out = tmp_path / f"trail-{hz}.rrd"
        view = RerunView("test", save=str(out))
        mirror = Mirror(view, "telesurg/local", trail_s=1.0, trail_hz=10.0, draw_hz=5.0, trail_draw_hz=hz)
        t0 = 1_700_000_000_000_000_000
        for i in range(750):  # 3 s at 250 Hz
            stamp = t0 + i * 4_000_000
            h = Header("slave_control", i, stamp)
            q = tuple(float(v) + 0.1 * np.sin(i / 100) for v in p.home)
            tip = CartesianPose(h, "world", (0.3 + 0.01 * np.sin(i / 50), 0.0, 0.3), (0.0, 0.0, 0.0, 1.0))
            mirror.feed(
                [
                    ("telesurg/local/slave/arm1/measured_js", stamp, JointState(h, p.joint_names, q)),
                    ("telesurg/local/slave/arm1/measured_cp", stamp, tip),
                ]  # type: ignore[list-item]
            )
            mirror.draw()
        view.close()
        n: dict[str, int] = {}
        for c in RrdReader(str(out)).stream():
            n[c.entity_path] = n.get(c.entity_path, 0) + c.num_rows
        rows[hz] = n
    tip, robot = "/slave/arm1/tip", "/slave/geometry/mh3f"
    assert rows[1.0][tip] <= 5 and rows[0.0][tip] >= 14, rows  # 3 s at 1 Hz (+ the last at close) / 5 Hz
    assert rows[1.0][robot] == rows[0.0][robot] >= 14, rows  # the bodies at the scene rate either way


def test_a_serving_mirror_hands_each_scene_over_at_once_and_a_file_gets_batches(tmp_path: Path) -> None:
    """``send_at_once`` (a mirror serving the web viewer): each drawn scene is its own message, sent
    as drawn; without it (a file) rerun's batcher gathers the rows of its tick into one chunk."""
    from rerun.chunk import RrdReader
    from telesurg.services.mirror import Mirror
    from telesurg.services.mirror.view import RerunView
    from telesurg.shared.messages import Header, JointState

    p = robots.get("mh3f").arms("arm1")[0]
    chunks: dict[bool, tuple[int, int]] = {}
    for at_once in (False, True):
        out = tmp_path / f"at-once-{at_once}.rrd"
        view = RerunView("test", save=str(out), flush_s=5.0)  # no tick within the test
        mirror = Mirror(
            view, "telesurg/local", trail_s=1.0, trail_hz=10.0, draw_hz=30.0, send_at_once=at_once
        )
        t0 = 1_700_000_000_000_000_000
        for i in range(250):  # 1 s at 250 Hz: 30 scenes
            stamp = t0 + i * 4_000_000
            q = tuple(float(v) + 0.1 * np.sin(i / 20) for v in p.home)
            js = JointState(Header("slave_control", i, stamp), p.joint_names, q)
            mirror.feed([("telesurg/local/slave/arm1/measured_js", stamp, js)])  # type: ignore[list-item]
            mirror.draw()
        view.close()
        robot = [c for c in RrdReader(str(out)).stream() if c.entity_path == "/slave/geometry/mh3f"]
        temporal = [c for c in robot if not c.is_static]
        chunks[at_once] = (len(temporal), sum(c.num_rows for c in temporal))
    (batched, rows), (handed, rows_at_once) = chunks[False], chunks[True]
    assert rows == rows_at_once >= 25, chunks  # the same scenes either way
    assert handed == rows_at_once and batched <= 2, chunks
