"""The watchdog service object on a real (in-process) zenoh router: e-stop, echo latency, and
inputs that never wait for the loop."""

from __future__ import annotations

import threading
import time

from conftest import wait_until
from telesurg.services.watchdog import Watchdog, WatchdogConfig, _probe_loop
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
        echo = threading.Thread(target=_probe_loop, args=(wd, cfg, stop), daemon=True)
        echo.start()
        loop = threading.Thread(target=wd.serve, args=(stop,), daemon=True)
        loop.start()
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
            # (the lease is put before the loop's urgent tick records the verdict)
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
            loop.join(2.0)


def test_the_clock_source_probes_the_masters_clock(endpoint: str) -> None:
    """With ``latency_source = "clock"`` the watchdog probes master_capture's clock over the bus
    (signed clock probes): on one host the offset it finds is ~0 and the round trip is short."""
    bus = BusConfig(connect=[endpoint])
    cfg = WatchdogConfig(site="t", echo_hz=50.0, bus=bus)
    cfg.validate()
    stop = threading.Event()
    with Node(bus, "t", "watchdog") as node, Node(bus, "t", "master_capture"):
        wd = Watchdog(cfg, node)
        probes = threading.Thread(target=_probe_loop, args=(wd, cfg, stop), daemon=True)
        probes.start()
        try:
            assert wait_until(lambda: wd.clock.samples >= 10, 5.0)
            delay = wd.clock.delay_ns()
            assert delay is not None and 0 < delay < 20e6
            assert abs(wd.clock_offset_ns) < 2e6  # one clock: only the path's asymmetry is left
            assert node.fresh.offsets["master_capture"] == wd.clock_offset_ns
            # nobody answers for a service that is not there: no sample, nothing changes
            assert node.clock_probe("nobody", timeout=0.2) is None
        finally:
            stop.set()
            probes.join(2.0)


def test_an_estop_never_waits_for_the_loop(endpoint: str) -> None:
    """While the loop is in a tick (its lease put held up by the transport, say), an e-stop is
    taken and the zenoh thread that delivered it goes on delivering: the loop revokes the lease
    as soon as it can. (A callback that ticked itself waited for the loop here, and the thread
    it blocked was one the loop's put could need: the watchdog did not stop once, 2026-12-04.)"""
    bus = BusConfig(connect=[endpoint])
    cfg = WatchdogConfig(site="t", bus=bus)
    cfg.validate()
    leases: list[SafetyLease] = []
    stop = threading.Event()
    with Node(bus, "t", "watchdog") as node, Node(bus, "t", "master_capture") as master:
        wd = Watchdog(cfg, node)
        master.subscribe(master.keys.safety("arm1", "lease"), SafetyLease, lambda m, k: leases.append(m))
        out = master.outlet(master.keys.estop)
        time.sleep(0.2)
        loop = threading.Thread(target=wd.serve, args=(stop,), daemon=True)
        with wd.tick_lock:  # the loop is stuck in a tick
            loop.start()
            out.put(EStop(out.header(), "*", "estop", "test"))
            out.put(EStop(out.header(), "arm1", "reset", "test"))  # refused: not the console's
            # both delivered and handled on zenoh's thread, though no tick can run
            assert wait_until(lambda: wd.authority.refused == 1, 2.0), "the e-stop callback is blocked"
            assert wd.arms[0].safety.estop and wd.urgent.is_set()
            assert not any(m.reason.startswith("ESTOP") for m in leases)
        try:  # the loop is free again: the urgent tick revokes the lease at once
            assert wait_until(lambda: any(m.reason.startswith("ESTOP") for m in leases), 2.0)
            assert wd.arms[0].verdict.state == "ESTOP"
        finally:
            stop.set()
            loop.join(2.0)


def test_the_masters_lost_poses_count_as_a_share_of_its_samples(endpoint: str) -> None:
    """Over the datagram link a WAN loses a few master poses, each superseded by the next: 4 % lost
    changes nothing, 20 % is DEGRADED (``max_master_loss_pct``, 10 %); a lost ``servo_jp`` still
    counts per second (``max_loss_per_s``)."""
    from telesurg.shared.messages import CartesianPose

    bus = BusConfig(connect=[endpoint])
    cfg = WatchdogConfig(site="t", bus=bus)
    cfg.validate()
    with Node(bus, "t", "watchdog") as node, Node(bus, "t", "master_capture") as master:
        wd = Watchdog(cfg, node)
        arm = wd.arms[0]
        out = master.outlet(arm.master_pose)
        stats = node.streams.get(arm.master_pose)
        time.sleep(0.3)
        sent = 0

        def burst(n: int, skip_every: int) -> None:
            nonlocal sent
            for i in range(n):
                h = out.header()  # a number taken and never sent: a lost sample
                if i % skip_every != skip_every - 1:
                    out.put(CartesianPose(h, "master", (0.0, 0.0, 0.0)))
                    sent += 1
                time.sleep(0.001)
            assert wait_until(lambda: node.poll() >= 0 and stats.received >= sent, 5.0), (stats, sent)

        assert wd.degraded_causes(arm, 100.0) == []
        burst(250, 25)  # 4 %
        assert wd.degraded_causes(arm, 100.5) == []
        assert wd.degraded_causes(arm, 102.0) == []  # (a new window: the burst above left it)
        burst(250, 5)  # 20 %
        causes = wd.degraded_causes(arm, 102.5)
        assert causes == ["20 % of the master's poses lost or reordered in the last second"], causes
