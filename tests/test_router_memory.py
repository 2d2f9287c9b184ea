"""The router maps no zenoh shared memory (issue #17, acceptance 2).

zenoh 1.x enables its shared-memory transport by default (16 MiB pools for messages over 3 KiB).
In ``telesurg bench flood`` (the locked-down pipeline, 10 s of 1 MB puts) the router ended with a
16 MB ``*.zenoh`` shared-memory segment mapped and resident that it did not have before the flood
— most of its +21-23 MB after the flood (docs/security.md). The site's router now runs with shared
memory off (``router.shared_memory = false``). Here the real router process takes 2 s of 1 MB
puts from each of three client sessions one after another: with the default config it maps no
shared-memory segment at all; with ``shared_memory=true`` (the situation before) it does (here
the 12 KB segment zenoh maps first; in the bench's flood the 16 MB pool) — so the check can fail.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from telesurg.services.launcher import free_port

pytestmark = pytest.mark.process


def _shm_mapped_mb(pid: int) -> tuple[float, float]:
    """(mapped, resident) MB of the zenoh shared-memory segments ``pid`` maps (``*.zenoh`` files)."""
    size = rss = 0
    shm = False
    for line in Path(f"/proc/{pid}/smaps").read_text().splitlines():
        parts = line.split()
        if parts and "-" in parts[0] and len(parts) >= 5:
            shm = len(parts) > 5 and parts[5].endswith(".zenoh")
        elif shm and parts and parts[0] == "Size:":
            size += int(parts[1])
        elif shm and parts and parts[0] == "Rss:":
            rss += int(parts[1])
    return size / 1024, rss / 1024


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def _floods(extra: list[str]) -> tuple[tuple[float, float], float, float]:
    """((SHM MB mapped, resident), RSS before, RSS after) of a router after 3 client sessions of
    1 MB puts on a control key (dropped by the router's size cap, as in the flood bench)."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    argv = [sys.executable, "-m", "telesurg.services.cli", "router", "--listen", ep, *extra]
    router = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([ep]))
        deadline = time.monotonic() + 60
        while True:  # the router process is up once a session opens
            try:
                zenoh.open(conf).close()  # type: ignore[no-untyped-call]
                break
            except zenoh.ZError:
                assert time.monotonic() < deadline, "the router did not come up within 60 s"
                time.sleep(0.5)
        before = _rss_mb(router.pid)
        payload = os.urandom(1 << 20)
        for _ in range(3):
            with zenoh.open(conf) as s:
                pub = s.declare_publisher("telesurg/local/slave/arm1/servo_jp")
                end = time.monotonic() + 2.0  # as fast as it can for 2 s (the bench floods for 10)
                while time.monotonic() < end:
                    pub.put(payload)
                time.sleep(0.5)
        time.sleep(1.0)
        return _shm_mapped_mb(router.pid), before, _rss_mb(router.pid)
    finally:
        router.send_signal(signal.SIGINT)
        try:
            router.wait(10)
        except subprocess.TimeoutExpired:
            router.kill()
            router.wait()


def test_the_router_maps_no_clients_shared_memory() -> None:
    (mapped, resident), before, after = _floods([])
    print(f"shared memory off: SHM mapped {mapped:.3f} MB ({resident:.3f} MB resident)")
    print(f"  router RSS {before:.1f} → {after:.1f} MB")
    assert mapped == 0.0
    (mapped_on, resident_on), before_on, after_on = _floods(["--set", "shared_memory=true"])
    print(f"shared memory on: SHM mapped {mapped_on:.3f} MB ({resident_on:.3f} MB resident)")
    print(f"  router RSS {before_on:.1f} → {after_on:.1f} MB")
    assert mapped_on > 0.0, "with shared memory on the router mapped no segment: the check proves nothing"
