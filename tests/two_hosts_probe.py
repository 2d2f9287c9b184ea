"""The two-host tests' probe, run inside the slave's namespace (``tests/test_two_hosts.py``):
it prints what the slave site shows, one JSON line per record, until SIGINT/SIGTERM. A script of
its own so it starts fast on a loaded host (no pytest, no test helpers to import)::

    python tests/two_hosts_probe.py ENDPOINT [CREDENTIALS_DIR] [--haptics] [--master-times]
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

SITE = "lab"


def _bus(endpoint: str, certs: Path | None, ident: str, ca: Path | None = None) -> Any:
    from telesurg.shared.bus import BusConfig

    cfg = BusConfig(connect=[endpoint])
    if certs is not None:
        cfg.tls_root_ca = str(ca or certs / "ca.pem")
        if ident:
            cfg.tls_cert, cfg.tls_key = str(certs / f"{ident}.pem"), str(certs / f"{ident}.key")
            cfg.mtls = True
    return cfg


_EMIT_LOCK = threading.Lock()


def _emit(**rec: Any) -> None:
    """One JSON line on stdout; zenoh callbacks run on several threads: one write each, locked."""
    line = json.dumps({"t": time.monotonic_ns(), **rec}) + "\n"
    with _EMIT_LOCK:
        sys.stdout.write(line)
        sys.stdout.flush()


def probe_main(endpoint: str, creds: str = "", *flags: str) -> int:
    """Print what the slave site shows, one JSON line per record, until SIGINT/SIGTERM; ``creds``:
    the locked-down site's local credentials (the operator identity on its local listener).
    ``--haptics``: also every contact force (``cf``) and master pose with its energy (``mp``).
    ``--master-times``: also, once a second, the master poses' ages on arrival and the gaps between
    them (``ms``), and the mapping's commanded tip (``sp``, 100 Hz)."""
    from telesurg.shared.bus import Node
    from telesurg.shared.clock import wall_ns
    from telesurg.shared.messages import (
        CartesianPose,
        CartesianWrench,
        MasterButtons,
        OperatingState,
        SafetyEvent,
        SafetyState,
    )

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    last_tip = [0]
    last_master = [0]  # receive time of the newest master pose: when the link went silent
    clutch: list[bool] = []
    haptics = "--haptics" in flags
    master_times = "--master-times" in flags  # the master poses' ages and gaps (tests/test_wan_process.py)
    ages: list[float] = []  # ms, since the last summary
    gaps: list[float] = []
    last_rx = [0]
    bus = _bus(endpoint, None, "")
    if creds:
        from telesurg.services.launcher.lockdown import LocalPki

        pki = LocalPki(Path(creds))
        bus.tls_root_ca, bus.tls_cert, bus.tls_key = (
            str(pki.ca),
            str(pki.cert("operator")),
            str(pki.key("operator")),
        )
        bus.mtls = True
    with Node(bus, SITE, "probe") as node:
        k, sub = node.keys, node.subscribe

        def on_tip(m: CartesianPose, key: str) -> None:
            now = time.monotonic_ns()
            if now - last_tip[0] >= 10_000_000:  # 100 Hz is plenty
                last_tip[0] = now
                _emit(k="tip", p=list(m.position), ts=m.header.stamp_ns)

        def on_op(m: OperatingState, key: str) -> None:
            _emit(
                k="op",
                follow=m.follow,
                lease=m.lease_ok,
                state=m.state,
                reason=m.reason,
                m_last=last_master[0],
            )

        def on_master(m: CartesianPose, key: str) -> None:
            last_master[0] = time.monotonic_ns()
            if master_times:  # its age on arrival (the namespaces share one wall clock), its gap
                age = (wall_ns() - m.header.stamp_ns) / 1e6
                with _EMIT_LOCK:
                    ages.append(round(age, 2))
                    if last_rx[0]:
                        gaps.append(round((last_master[0] - last_rx[0]) / 1e6, 2))
                    last_rx[0] = last_master[0]
            if haptics:
                _emit(k="mp", p=list(m.position), e=m.energy_in_j)

        def on_cf(m: CartesianWrench, key: str) -> None:
            _emit(k="cf", f=list(m.force))

        def on_safety(m: SafetyState, key: str) -> None:
            _emit(k="safety", state=m.state, causes=list(m.causes), scale=m.scale, p50=m.latency_p50_ms)

        last_buttons = [0]

        def on_buttons(m: MasterButtons, key: str) -> None:
            now = time.monotonic_ns()
            if master_times and now - last_buttons[0] > 500_000_000:
                clutch.clear()  # after a silence (a cut link) the first reading is news again
            last_buttons[0] = now
            if m.header.seq % 25 == 0:
                _emit(k="btn", seq=m.header.seq, v=m.clutch)
            if not clutch or clutch[-1] != m.clutch:
                clutch.append(m.clutch)
                _emit(k="clutch", v=m.clutch)

        def on_event(m: SafetyEvent, key: str) -> None:
            _emit(k="event", src=m.header.source, kind=m.kind, text=m.text)

        last_sp = [0]

        def on_setpoint(m: CartesianPose, key: str) -> None:
            now = time.monotonic_ns()
            if now - last_sp[0] >= 10_000_000:
                last_sp[0] = now
                _emit(k="sp", p=list(m.position), ts=m.header.stamp_ns)

        sub(k.slave("arm1", "measured_cp"), CartesianPose, on_tip, sources=["slave_control"])
        if master_times:
            sub(k.slave("arm1", "setpoint_cp"), CartesianPose, on_setpoint, sources=["mapping"])
        sub(k.slave("arm1", "operating_state"), OperatingState, on_op, sources=["slave_control"])
        sub(k.master("m1", "measured_cp"), CartesianPose, on_master, sources=["master_capture"])
        sub(k.safety("arm1", "state"), SafetyState, on_safety, sources=["watchdog"])
        sub(k.master("m1", "buttons"), MasterButtons, on_buttons, sources=["master_capture"])
        sub(k.events(), SafetyEvent, on_event)
        if haptics:
            sub(k.slave("arm1", "measured_cf"), CartesianWrench, on_cf, sources=["slave_control"])
        time.sleep(0.3)
        _emit(k="ready")
        while not stop.wait(1.0):
            if master_times:  # one summary a second (a line per pose would cost the host more)
                with _EMIT_LOCK:
                    batch, ages[:] = list(ages), []
                    gap_batch, gaps[:] = list(gaps), []
                _emit(k="ms", age=batch, gap=gap_batch)
    return 0


if __name__ == "__main__":
    sys.exit(probe_main(*sys.argv[1:]))
