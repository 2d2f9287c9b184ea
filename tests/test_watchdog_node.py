"""The watchdog service object on a real (in-process) zenoh router: e-stop and echo latency."""

from __future__ import annotations

import threading
import time

from conftest import wait_until
from telesurg.services.watchdog import Watchdog, WatchdogConfig, _echo_loop
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import EStop, SafetyLease


def test_echo_latency_source_and_estop(endpoint: str) -> None:
    bus = BusConfig(connect=[endpoint])
    cfg = WatchdogConfig(site="t", latency_source="echo", echo_hz=50.0, bus=bus)
    cfg.validate()
    leases: list[SafetyLease] = []
    stop = threading.Event()
    with (
        Node(bus, "t", "watchdog") as node,
        Node(bus, "t", "master_capture") as master,
        Node(bus, "t", "console") as console,
    ):
        wd = Watchdog(cfg, node)
        master.subscribe(master.keys.safety("arm1", "lease"), SafetyLease, lambda m, k: leases.append(m))
        echo = threading.Thread(target=_echo_loop, args=(wd, cfg, stop), daemon=True)
        echo.start()
        try:
            # RTT/2 to master_capture's echo queryable becomes the arm's latency figure
            assert wait_until(lambda: wd.arms[0].safety.latency(time.monotonic())[3] >= 10, 5.0)
            p50, _, p99, n = wd.arms[0].safety.latency(time.monotonic())
            print(f"echo latency over {n} probes: p50 {p50:.2f} ms, p99 {p99:.2f} ms")
            assert 0.0 < p50 < 50.0
            # an e-stop from any service latches ESTOP at once and denies the lease
            out = master.outlet(master.keys.estop)
            time.sleep(0.2)
            out.put(EStop(out.header(), "*", "estop", "test"))
            assert wait_until(lambda: bool(leases) and leases[-1].reason.startswith("ESTOP"), 2.0)
            # (the lease is put before the e-stop callback's tick records the verdict)
            assert not leases[-1].allow
            assert wait_until(lambda: wd.arms[0].verdict.state == "ESTOP", 2.0)
            wd.tick()
            assert wd.arms[0].verdict.state == "ESTOP"  # latched
            # a reset only from the operator console (shared/authority.py): master_capture's is refused
            out.put(EStop(out.header(), "arm1", "reset", "test"))
            assert wait_until(lambda: wd.authority.refused == 1, 2.0)
            assert wd.arms[0].safety.estop
            reset = console.outlet(console.keys.estop)
            time.sleep(0.2)
            reset.put(EStop(reset.header(), "arm1", "reset", "test"))
            assert wait_until(lambda: wd.arms[0].safety.estop == "", 2.0)
            wd.tick()
            assert wd.arms[0].verdict.state == "HOLD"  # the other causes remain (no streams here)
        finally:
            stop.set()
            echo.join(2.0)
