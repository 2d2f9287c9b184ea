"""A viewer that opens late starts near live: the mirror's gRPC server keeps only ``history_mb``.

rerun's gRPC server replays what it buffered to every viewer that connects (by default up to
1 GiB: the whole session, from its start); a web viewer that ingests at about the rate data
arrives then stays as far behind live as the session was old when it opened. The real mirror
(``telesurg mirror --serve --save``, its default ``history_mb``) is fed MH3F joint states over zenoh as
slave_control publishes them; then a late viewer connects — rerun's own CLI
(``rerun <url> --save late.rrd``), a real client of the same server — and what it received is
read back: the newest samples and the robot's static geometry, not the session's start. The
mirror's own .rrd still holds every sample (the limit cuts what a late viewer is replayed, not
the recording).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import entity_paths, scalar_counts

pytestmark = pytest.mark.process

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 500.0
SECONDS = 10.0  # s: the history_mb default holds ~3 s of this stream


def _source_times(rrd: Path, entity: str) -> np.ndarray:
    """Every ``source_time`` stamp (ns) of ``entity``'s Scalars rows in an .rrd, sorted."""
    from rerun.chunk import RrdReader

    out: list[np.ndarray] = []
    for c in RrdReader(str(rrd)).stream():
        if c.entity_path != entity:
            continue
        batch = c.to_record_batch()
        if "source_time" in batch.schema.names and any(n.startswith("Scalars:") for n in batch.schema.names):
            out.append(np.asarray(batch.column("source_time").cast("int64").to_numpy(), np.int64))
    return np.sort(np.concatenate(out)) if out else np.empty(0, np.int64)


def _stop(p: subprocess.Popen[bytes]) -> int:
    """SIGINT, then SIGTERM, then SIGKILL: the exit code of whichever ended it."""
    for sig, wait_s in ((signal.SIGINT, 30.0), (signal.SIGTERM, 15.0), (signal.SIGKILL, 10.0)):
        p.send_signal(sig)
        try:
            return p.wait(timeout=wait_s)  # (rerun's CLI once took over 60 s on a loaded host)
        except subprocess.TimeoutExpired:
            continue
    return p.wait(timeout=10)


@pytest.mark.timeout(300)
def test_a_late_viewer_gets_the_recent_data_and_the_geometry_not_the_whole_session(tmp_path: Path) -> None:
    from telesurg.services.launcher import free_port, wait_port
    from telesurg.shared import robots
    from telesurg.shared.bus import BusConfig, Node, open_session
    from telesurg.shared.messages import JointState

    rerun_cli = Path(sys.executable).with_name("rerun")
    if not rerun_cli.exists():
        pytest.skip(f"needs rerun's CLI beside the interpreter: {rerun_cli}")
    profile = robots.get("mh3f").arm("arm1")
    ep = f"tcp/127.0.0.1:{free_port()}"
    web, grpc = free_port(), free_port()
    saved, late = tmp_path / "mirror.rrd", tmp_path / "late.rrd"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    argv = [sys.executable, "-m", "telesurg.services.cli", "mirror", "--connect", ep, "--serve"]
    argv += ["--save", str(saved), "--set", f"web_port={web}", "--set", f"grpc_port={grpc}"]
    argv += ["--set", "plot_hz=0"]  # every sample, to count them; history_mb: the default
    log = (tmp_path / "mirror.out").open("wb")
    mirror = subprocess.Popen(argv, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    client: subprocess.Popen[bytes] | None = None
    client_log = None
    stamps: list[int] = []
    try:
        assert wait_port("127.0.0.1", grpc, 60.0), (tmp_path / "mirror.out").read_text()[-2000:]
        with Node(BusConfig(connect=[ep]), "local", "slave_control") as node:
            js = node.outlet(node.keys.slave("arm1", "measured_js"), control=False)
            home = np.asarray(profile.home, np.float64)
            seen = threading.Event()
            node.watch_liveliness(node.keys.alive("mirror"), lambda _s, alive: seen.set() if alive else None)
            assert seen.wait(30.0), "the mirror never joined the bus"
            time.sleep(1.0)  # its subscribers match a moment after its liveliness token
            t0 = time.monotonic()
            n = int(RATE_HZ * SECONDS)
            for i in range(n):  # the slave's measured joints, j1 swinging
                q = home.copy()
                q[0] += 0.4 * np.sin(2.0 * i / RATE_HZ)
                msg = JointState(js.header(), profile.joint_names, tuple(q))
                js.put(msg)
                stamps.append(msg.header.stamp_ns)
                time.sleep(max(0.0, t0 + (i + 1) / RATE_HZ - time.monotonic()))
        time.sleep(1.5)  # the mirror's last series block and rerun's flush tick
        # a viewer that opens now, after the session: rerun's CLI saving what the server replays
        client_log = (tmp_path / "late.out").open("wb")
        url = f"rerun+http://127.0.0.1:{grpc}/proxy"
        client = subprocess.Popen(
            [str(rerun_cli), url, "--save", str(late), "--port", str(free_port())],
            stdout=client_log,
            stderr=subprocess.STDOUT,
        )
        time.sleep(5.0)
        t_stop = time.monotonic()
        rc = _stop(client)
        # (what the late viewer received is judged below, from its file, however it ended)
        print(f"rerun CLI exited {rc} {time.monotonic() - t_stop:.1f} s after SIGINT")
        client_log.close()
        assert _stop(mirror) == 0, (tmp_path / "mirror.out").read_text()[-3000:]
    finally:
        for p in (client, mirror):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        log.close()
        if client_log is not None:
            client_log.close()
        router.close()  # type: ignore[no-untyped-call]

    j1 = "/slave/arm1/joints/measured"
    # the recording keeps the whole session
    assert scalar_counts(saved)[j1] >= 0.9 * len(stamps), scalar_counts(saved)
    # (rerun's CLI, stopped by a signal, writes no footer: pyproject's filterwarnings lets its
    # reader's warning pass)
    got = _source_times(late, j1)
    late_paths = entity_paths(late)
    assert got.size, (
        f"the late viewer got no joint samples: {sorted(late_paths)}",
        (tmp_path / "late.out").read_text()[-2000:],
    )
    first, last = stamps[0], stamps[-1]
    print(
        f"late viewer: {got.size} of {len(stamps)} samples of j1, from {(got[0] - first) / 1e9:.2f} s "
        f"to {(got[-1] - first) / 1e9:.2f} s of the {(last - first) / 1e9:.2f} s session"
    )
    # the newest samples (a serving mirror sends joint series in blocks of 1/LIVE_SERIES_HZ = 1 s;
    # the last block goes out with the next sample or at shutdown), not the session's start
    assert got[-1] >= last - 1.2e9
    assert got[0] > first + 0.5 * (last - first), "the late viewer was replayed the session's first half"
    # the robot's own geometry (static) is kept for a new viewer (at 0.05 MB it was not)
    assert "/slave/geometry/mh3f" in late_paths, sorted(late_paths)
