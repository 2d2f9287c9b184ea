"""Every other door into the bus binds to loopback unless configured otherwise (issue #39): the
rerun web viewer and its gRPC port (the mirror's), and the ROS 2 bridge (a client of the site's
router: it listens on nothing). The web console's and ``telesurg view``'s listeners are checked in
their own tests (tests/test_web_door_browser.py, tests/test_camera_view_record.py)."""

from __future__ import annotations

import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import psutil
import pytest
from conftest import wait_until
from telesurg.services.launcher import free_port
from telesurg.shared.bus import BusConfig, Node


def listening(pid: int) -> set[tuple[str, int]]:
    """(address, port) of every TCP/UDP socket ``pid`` and its children listen on."""
    procs = [psutil.Process(pid), *psutil.Process(pid).children(recursive=True)]
    out: set[tuple[str, int]] = set()
    for p in procs:
        for c in p.net_connections(kind="inet"):
            if c.status == psutil.CONN_LISTEN or (c.type == 2 and not c.raddr):  # 2: SOCK_DGRAM
                out.add((c.laddr.ip, c.laddr.port))
    return out


def test_the_rerun_web_viewer_and_its_grpc_port_listen_on_loopback_only(tmp_path: Path) -> None:
    from telesurg.services.mirror.view import RerunView

    web, grpc = free_port(), free_port()
    view = RerunView("bindtest", serve=True, web_port=web, grpc_port=grpc)
    try:
        ports = listening(psutil.Process().pid)
        print("rerun listens on:", sorted(ports))
        mine = {(ip, port) for ip, port in ports if port in (web, grpc)}
        assert mine == {("127.0.0.1", web), ("127.0.0.1", grpc)}, mine
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as r:
            assert r.status == 200 and b"<html" in r.read(4096).lower()  # the viewer is served
        assert f"localhost:{web}" in view.url
    finally:
        view.close()
    assert not any(port == web for _, port in listening(psutil.Process().pid)), "the viewer outlived close()"


@pytest.mark.process
def test_the_ros2_bridge_listens_on_nothing(endpoint: str, tmp_path: Path) -> None:
    """The bridge is a zenoh client of the site's router: ROS 2 nodes reach the arm only through
    that router (whoever may connect to it: docs/security.md §12); the bridge opens no port."""
    argv = [sys.executable, "-m", "telesurg.services.cli", "bridge", "ros2", "--arm", "arm1"]
    argv += ["--connect", endpoint]
    with (tmp_path / "bridge.log").open("w") as log:
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
    try:
        with Node(BusConfig(connect=[endpoint]), "local", "bindtest") as node:
            seen: list[bool] = []
            node.watch_liveliness(node.keys.alive("ros2_bridge"), lambda service, alive: seen.append(alive))
            assert wait_until(lambda: any(seen) or proc.poll() is not None, 60.0), "the bridge never came up"
        assert proc.poll() is None, (tmp_path / "bridge.log").read_text()[-2000:]
        time.sleep(0.5)
        ports = listening(proc.pid)
        assert ports == set(), f"the ROS 2 bridge listens on {sorted(ports)}"
    finally:
        proc.terminate()
        proc.wait(15)
