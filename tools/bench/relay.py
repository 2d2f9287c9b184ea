"""The transport floor: a bare three-process zenoh relay (source → relay → sink) at a fixed rate.

Each process is plain zenoh-python with the control-stream QoS the services use (express,
``Priority.REAL_TIME``, ``CongestionControl.BLOCK``) and a callback subscriber, connected to the
same router as the services; the payload is a msgpack map padded to the size of a ``servo_jp``
message. No decoding, no validation, no logic: what is left is the price of the transport and of
a Python callback per hop. ``telesurg bench latency`` compares the real pipeline against it.

    python -m telesurg.tools.bench.relay source --connect tcp/127.0.0.1:7447 --rate 1000 --seconds 5
    python -m telesurg.tools.bench.relay relay  --connect …
    python -m telesurg.tools.bench.relay sink   --connect … --out sink.npy  # t_src t_relay t_sink
"""

from __future__ import annotations

import argparse
import threading
import time
from collections.abc import Sequence
from typing import Any

import msgpack
import numpy as np
from telesurg.services.common import install_stop_handlers
from telesurg.shared.bus import BusConfig, open_session
from telesurg.shared.timing import CycleTimer

KEY_A = "telesurg/bench/relay/a"
KEY_B = "telesurg/bench/relay/b"
PAYLOAD_BYTES = 230  # ≈ a 6-joint servo_jp message


def _publisher(session: Any, key: str) -> Any:
    import zenoh

    return session.declare_publisher(
        key, express=True, priority=zenoh.Priority.REAL_TIME, congestion_control=zenoh.CongestionControl.BLOCK
    )


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m telesurg.tools.bench.relay", description=__doc__)
    ap.add_argument("role", choices=("source", "relay", "sink"))
    ap.add_argument("--connect", required=True)
    ap.add_argument("--rate", type=float, default=1000.0, help="Hz (source; 0: unpaced)")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--out", help="sink: .npy of (t_source, t_relay, t_sink) ns rows")
    a = ap.parse_args(argv)
    stop = threading.Event()
    install_stop_handlers(stop)
    session = open_session(BusConfig(connect=[a.connect]))
    try:
        if a.role == "source":
            pub = _publisher(session, KEY_A)
            pad = b"x" * PAYLOAD_BYTES
            time.sleep(0.5)  # let the others subscribe
            end = time.monotonic() + a.seconds
            timer = CycleTimer(a.rate) if a.rate > 0 else None
            seq = 0
            while not stop.is_set() and time.monotonic() < end:
                pub.put(msgpack.packb({"seq": seq, "t0": time.time_ns(), "pad": pad}))
                seq += 1
                if timer is not None:
                    timer.wait()
                else:
                    time.sleep(0)
            print(f"sent {seq}", flush=True)
        elif a.role == "relay":
            pub = _publisher(session, KEY_B)

            def on_a(sample: Any) -> None:
                d = msgpack.unpackb(bytes(sample.payload))
                d["t1"] = time.time_ns()
                pub.put(msgpack.packb(d))

            sub = session.declare_subscriber(KEY_A, on_a)
            stop.wait()
            del sub
        else:
            rows: list[tuple[int, int, int]] = []

            def on_b(sample: Any) -> None:
                t2 = time.time_ns()
                d = msgpack.unpackb(bytes(sample.payload))
                rows.append((d["t0"], d["t1"], t2))

            sub = session.declare_subscriber(KEY_B, on_b)
            stop.wait()
            del sub
            if a.out:
                np.save(a.out, np.array(rows, dtype=np.int64).reshape(-1, 3))
            print(f"received {len(rows)}", flush=True)
    finally:
        session.close()  # type: ignore[no-untyped-call]
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
