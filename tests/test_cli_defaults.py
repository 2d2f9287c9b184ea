"""Every command line reaches the local site's router when no ``--connect`` is given.

The README's record line (``telesurg record --out run.mcap --seconds 60``) once failed as written
("bus mode 'client' needs at least one --connect endpoint") while ``cmd``, ``estop`` and
``console`` defaulted to the local router; now the default is one rule in
:func:`telesurg.shared.bus.bus_from_args`.
"""

from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from telesurg.services.record import read_summary
from telesurg.shared.bus import LOCAL_ROUTER, BusConfig, add_bus_args, bus_from_args


def _args(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    add_bus_args(ap)
    return ap.parse_args(list(argv))


def test_a_client_without_connect_goes_to_the_local_router() -> None:
    assert bus_from_args(_args()).connect == [LOCAL_ROUTER]
    assert bus_from_args(_args("--connect", "tcp/127.0.0.2:7000")).connect == ["tcp/127.0.0.2:7000"]
    # a file of the site's own, a peer or a router: no endpoint is invented
    assert bus_from_args(_args("--zenoh-config", "z.json5")).connect == []
    assert bus_from_args(_args("--mode", "peer")).connect == []
    assert bus_from_args(_args("--mode", "router")).connect == []
    # a config file's endpoints stay
    assert bus_from_args(_args(), BusConfig(connect=["tcp/127.0.0.3:1"])).connect == ["tcp/127.0.0.3:1"]


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


@pytest.mark.process
def test_record_as_the_readme_writes_it(tmp_path: Path) -> None:
    """``telesurg up`` on its default port, then the README's ``telesurg record`` line, shortened."""
    if not _port_free(7447):
        pytest.skip("127.0.0.1:7447 (the local site's default port) is taken on this machine")
    up = subprocess.Popen(
        [sys.executable, "-m", "telesurg.services.cli", "up", "--seconds", "40", "--log-dir", str(tmp_path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 30
        while _port_free(7447) and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(3.0)  # the services come up one by one after the router
        out = tmp_path / "run.mcap"
        rec = subprocess.run(
            [sys.executable, "-m", "telesurg.services.cli", "record", "--out", str(out), "--seconds", "3"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert rec.returncode == 0, rec.stderr[-2000:]
        with out.open("rb") as f:
            summary = read_summary(make_reader(f))
        # the site's streams, through its router: the slave's joints at 250 Hz, the watchdog's leases
        assert summary["slave/arm1/measured_js"]["messages"] > 100, sorted(summary)
        assert summary["safety/arm1/lease"]["messages"] > 20
    finally:
        up.terminate()
        up.wait(timeout=30)
