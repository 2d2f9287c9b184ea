"""``telesurg bench auth``: µs per message to sign and verify (HMAC-SHA256, the bus's choice) and,
for comparison, Ed25519 through ``cryptography`` — on the hot messages (``servo_jp``, the
watchdog's lease, the master pose).

The HMAC figures are what :class:`~telesurg.shared.bus.Node` adds per message: ``sign`` is
:meth:`~telesurg.shared.auth.Signer.attach` (the sender, once per publication), ``verify`` is
:func:`~telesurg.shared.auth.verify` (every subscriber, per message). Each figure is the best of
``--repeat`` short runs of ``--n`` calls (a busy machine inflates it less than a mean would).
``link_sign`` / ``link_verify`` are the same on a site of two hosts (shared/auth.py links): the
sender adds a second MAC under the link's key, the other host verifies that one. ``fresh`` is
what the freshness rules (:mod:`telesurg.shared.fresh`) add per received put, as the
bus runs them: the clock read, the signer's window on the key, the age and sequence checks and
the window update.

Example::

    telesurg bench auth --json docs/data/perf/auth.json
"""

from __future__ import annotations

import argparse
import functools
import json
import tempfile
import timeit
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from telesurg.services.keys import export
from telesurg.shared import auth
from telesurg.shared import messages as m
from telesurg.shared.fresh import Freshness, SenderWindow
from telesurg.shared.keys import Keys
from telesurg.shared.messages import now_ns
from telesurg.shared.streams import StreamStats
from telesurg.tools.bench.machine import machine, now

J6 = ("j1", "j2", "j3", "j4", "j5", "j6")
Q6 = (0.1234567, -0.7654321, 1.2345678, -0.0123456, 0.5432109, -1.5707963)


def samples() -> dict[str, tuple[str, str, m.Message]]:
    """name → (signer, key expression, message), as the services publish them."""
    k = Keys("local")
    t = 1_700_000_000_123_456_789
    return {
        "JointSetpoint (servo_jp)": (
            "mapping",
            k.slave("arm1", "servo_jp"),
            m.JointSetpoint(m.Header("mapping", 123_456, t), J6, Q6, follow=True, origin_ns=t),
        ),
        "SafetyLease (lease)": (
            "watchdog",
            k.safety("arm1", "lease"),
            m.SafetyLease(m.Header("watchdog", 123_456, t), "arm1", True, 250.0, ""),
        ),
        "CartesianPose (master measured_cp)": (
            "master_capture",
            k.master("m1", "measured_cp"),
            m.CartesianPose(
                m.Header("master_capture", 123_456, t),
                "master",
                (0.3123, -0.0456, 0.2789),
                (0.0, 0.0, 0.0, 1.0),
            ),
        ),
    }


def _best(fn: Any, n: int, repeat: int) -> float:
    return min(timeit.repeat(fn, number=n, repeat=repeat)) / n * 1e6


def fresh_check(signer: str, sid: bytes, stamp_ns: int) -> Any:
    """One received put's freshness check as :meth:`~telesurg.shared.bus.Node.subscribe` runs it
    (each call the next sequence number, so every call passes)."""
    import time

    fresh = Freshness(max_age_ms=600_000, start_ns=1)
    stats = StreamStats()
    seq = [0]

    def check() -> None:
        s = seq[0] = seq[0] + 1
        win = stats.senders.get(signer)
        if win is None:
            win = stats.senders[signer] = SenderWindow()
        if fresh.put_problem(signer, win, sid, s, stamp_ns, time.time_ns()):
            raise AssertionError("a fresh message was refused")
        fresh.took(win, sid, s, stamp_ns)

    return check


def run(n: int, repeat: int) -> dict[str, Any]:
    """µs per sign / verify of each sample, HMAC and Ed25519; checks that each verifies."""
    rows: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        d = auth.init_keyring(Path(tmp) / "keys", ("mapping", "watchdog", "master_capture", "console"))
        ring = auth.Keyring.load(d)
        # the same identities on a site of two hosts: the console host (master_capture) and the site
        site = auth.init_keyring(Path(tmp) / "site", ("mapping", "watchdog", "master_capture", "console"))
        export(
            site, ["master_capture", "console"], "console", "slave-site", Path(tmp) / "console", quiet=True
        )
        site_ring, console_ring = auth.Keyring.load(site), auth.Keyring.load(Path(tmp) / "console")
        for name, (signer_id, key, msg) in samples().items():
            payload = msg.encode()
            signer = auth.Signer(signer_id, ring.keys[signer_id])
            att = signer.attach(auth.PUT, key, payload)
            auth.verify(ring, auth.PUT, key, payload, att)  # raises if it does not verify
            # the sender's host and the other host
            here, there = (
                (console_ring, site_ring) if signer_id == "master_capture" else (site_ring, console_ring)
            )
            linked = auth.Signer(signer_id, here.keys[signer_id], links=here.send_keys())
            latt = linked.attach(auth.PUT, key, payload)
            auth.verify(there, auth.PUT, key, payload, latt)
            sk = Ed25519PrivateKey.generate()
            pk = sk.public_key()
            data = key.encode() + payload
            sig = sk.sign(data)
            pk.verify(sig, data)
            rows[name] = {
                "type": msg.TYPE,
                "payload_bytes": len(payload),
                "attachment_bytes": len(att),
                "hmac_sign_us": round(
                    _best(functools.partial(signer.attach, auth.PUT, key, payload), n, repeat), 2
                ),
                "hmac_verify_us": round(
                    _best(functools.partial(auth.verify, ring, auth.PUT, key, payload, att), n, repeat), 2
                ),
                "ed25519_sign_us": round(_best(functools.partial(sk.sign, data), max(1, n // 10), repeat), 2),
                "ed25519_verify_us": round(
                    _best(functools.partial(pk.verify, sig, data), max(1, n // 10), repeat), 2
                ),
                "link_sign_us": round(
                    _best(functools.partial(linked.attach, auth.PUT, key, payload), n, repeat), 2
                ),
                "link_verify_us": round(
                    _best(functools.partial(auth.verify, there, auth.PUT, key, payload, latt), n, repeat), 2
                ),
                "decode_us": round(_best(functools.partial(m.decode, payload), n, repeat), 2),
                "fresh_us": round(_best(fresh_check(signer_id, signer.sid, now_ns()), n, repeat), 2),
            }
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    """Print the table; write the JSON if asked."""
    ap = argparse.ArgumentParser(prog="telesurg bench auth", description=__doc__)
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--n", type=int, default=2000, help="calls per run (default 2000; Ed25519: n/10)")
    # many short runs: on a shared machine the best of them escapes the other jobs' preemption
    ap.add_argument("--repeat", type=int, default=200, help="runs; the best is reported (default 200)")
    a = ap.parse_args(argv)
    if a.n < 1 or a.repeat < 1:
        ap.error("--n and --repeat must be >= 1")
    rows = run(a.n, a.repeat)
    cols = (
        "hmac_sign_us",
        "hmac_verify_us",
        "link_sign_us",
        "link_verify_us",
        "ed25519_sign_us",
        "ed25519_verify_us",
        "decode_us",
        "fresh_us",
    )
    print(f"{'message':<36} {'bytes':>5} " + " ".join(f"{c[:-3]:>15}" for c in cols) + "   (µs)")
    for name, r in rows.items():
        print(f"{name:<36} {r['payload_bytes']:>5} " + " ".join(f"{r[c]:>15.2f}" for c in cols))
    res = {
        "n": a.n,
        "repeat": a.repeat,
        "messages": rows,
        "date": now(),
        "machine": machine(),  # with the 1-minute load average: a shared machine's load
    }
    if a.json:
        a.json.write_text(json.dumps(res, indent=2) + "\n")
    return 0
