"""``telesurg bench decode``: µs per strict decode (and encode) of the messages on the hot paths.

Every process decodes every message it takes (:func:`telesurg.shared.messages.decode_as` in
``Node.subscribe``), so the decoder's cost is paid per sample per subscriber: the mapping per
master pose, the slave per ``servo_jp``, the watchdog per lease it checks, the mirror and the
recorder per everything. The payloads are what the services publish (six joints, float64 arrays,
a typical source id); each figure is the best of ``--repeat`` runs of ``--n`` calls, so a busy
machine inflates it less than a mean would.

Example::

    telesurg bench decode --json docs/data/perf/decode.json
"""

from __future__ import annotations

import argparse
import functools
import timeit
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from telesurg.shared import jsonio
from telesurg.shared import messages as m
from telesurg.tools.bench.machine import machine, now

J6 = ("j1", "j2", "j3", "j4", "j5", "j6")
Q6 = (0.1234567, -0.7654321, 1.2345678, -0.0123456, 0.5432109, -1.5707963)


def samples() -> dict[str, m.Message]:
    """One message per benchmarked type, as the services fill them (the hot ones first)."""
    h = m.Header("slave_control", 123_456, 1_700_000_000_123_456_789)
    return {
        "JointSetpoint (servo_jp)": m.JointSetpoint(
            h, J6, Q6, follow=True, origin_ns=1_700_000_000_000_000_000
        ),
        "CartesianPose (measured_cp)": m.CartesianPose(
            h, "base", (0.3123, -0.0456, 0.2789), (0.0, 0.7071067811865476, 0.0, 0.7071067811865476)
        ),
        "SafetyLease": m.SafetyLease(h, "forceps", True, 150.0, ""),
        "JointState (measured_js)": m.JointState(h, J6, Q6, Q6, Q6),
        "MasterButtons": m.MasterButtons(h, clutch=True, operator_present=True),
        "OperatingState": m.OperatingState(
            h, "ENABLED", "trocar", True, True, "", 3, 0.25, 0, 0, (0.4, 0.0, 0.1)
        ),
        "SafetyState": m.SafetyState(h, "forceps", "OK", (), 1.0, 1.2, 2.3, 3.4, 200),
        "Heartbeat": m.Heartbeat(h, "slave_control", 12.5, 0),
    }


def run(n: int, repeat: int) -> dict[str, Any]:
    """µs per decode / encode of each sample; checks each payload decodes back to its message."""
    rows: dict[str, Any] = {}
    for name, msg in samples().items():
        payload = msg.encode()
        if m.decode(payload) != msg:
            raise SystemExit(f"{name}: decode(encode(msg)) != msg")
        dec = min(timeit.repeat(functools.partial(m.decode, payload), number=n, repeat=repeat)) / n * 1e6
        enc = min(timeit.repeat(msg.encode, number=n, repeat=repeat)) / n * 1e6
        rows[name] = {
            "type": msg.TYPE,
            "bytes": len(payload),
            "decode_us": round(dec, 2),
            "encode_us": round(enc, 2),
        }
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    """Print the table; write the JSON if asked."""
    ap = argparse.ArgumentParser(prog="telesurg bench decode", description=__doc__)
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--n", type=int, default=20_000, help="calls per run (default 20000)")
    ap.add_argument("--repeat", type=int, default=7, help="runs; the best is reported (default 7)")
    ap.add_argument("--label", default="", help="a note stored in the JSON (e.g. the codec measured)")
    a = ap.parse_args(argv)
    if a.n < 1 or a.repeat < 1:
        ap.error("--n and --repeat must be >= 1")
    rows = run(a.n, a.repeat)
    print(f"{'message':<30} {'bytes':>5} {'decode µs':>10} {'encode µs':>10}")
    for name, r in rows.items():
        print(f"{name:<30} {r['bytes']:>5} {r['decode_us']:>10.2f} {r['encode_us']:>10.2f}")
    res = {
        "label": a.label,
        "n": a.n,
        "repeat": a.repeat,
        "messages": rows,
        "date": now(),
        "machine": machine(),
    }
    if a.json:
        a.json.write_text(jsonio.dumps(res, indent=2) + "\n")
    return 0
