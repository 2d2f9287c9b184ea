"""``telesurg bench fuzz``: malformed messages on every key while the pipeline runs.

Publishes ``--count`` payloads (random bytes, mutated valid messages, boundary values — see
:mod:`telesurg.tools.bench.fuzzgen`) round-robin on every key the services subscribe to, while
the scripted master drives the slave. Reports: crashes (service processes that died: must be 0),
messages each service rejected (from their heartbeats) against the number a local strict decoder
says it must reject, slave holds during the run, and whether the slave ever got outside its joint
limits or jumped (must be never).

Every fuzz payload is rejected before the freshness rules look at it (by the authenticator, the
decoder or the source rules), so a service's count is its heartbeat's ``rejected`` less
``replayed``: what a receiver behind its streams refuses as too old is its own traffic. A service
that lost messages meanwhile (its heartbeat's ``lost``: it fell behind its buffers, as the mirror
at idle priority can on a busy host) may have lost payloads unexamined: its count may then be
lower, never higher, and the table says so.

Example::

    telesurg bench fuzz --count 100000 --json out/fuzz.json
"""

from __future__ import annotations

import argparse
import os
import random
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.services.mirror import SUBSCRIBED
from telesurg.services.router import RouterConfig
from telesurg.shared import jsonio
from telesurg.shared.auth import PUT, Signer
from telesurg.shared.bus import Node
from telesurg.shared.errors import MessageError
from telesurg.shared.messages import (
    CartesianPose,
    EStop,
    JointSetpoint,
    JointState,
    MasterButtons,
    Message,
    OperatingState,
    SafetyLease,
    SafetyState,
    TeleopState,
    decode,
    decode_as,
)
from telesurg.shared.robots.mh3f.kinematics import MH3F
from telesurg.tools.bench.fuzzgen import FUZZ_KINDS, always_invalid, fuzz_cases, valid_template
from telesurg.tools.bench.harness import Pipeline
from telesurg.tools.bench.machine import machine, now

#: key (under telesurg/<site>/) → (message type on it, services that subscribe with their sources)
TARGETS: dict[str, tuple[type[Message], dict[str, str]]] = {
    "master/m1/measured_cp": (CartesianPose, {"mapping": "master_capture", "watchdog": "master_capture"}),
    "master/m1/buttons": (MasterButtons, {"mapping": "master_capture", "watchdog": "master_capture"}),
    "slave/arm1/servo_jp": (JointSetpoint, {"slave_control": "mapping", "watchdog": "mapping"}),
    "slave/arm1/setpoint_cp": (CartesianPose, {}),  # drawn by the mirror only
    "slave/arm1/measured_js": (JointState, {"mapping": "slave_control", "watchdog": "slave_control"}),
    "slave/arm1/operating_state": (OperatingState, {"mapping": "slave_control", "watchdog": "slave_control"}),
    "safety/arm1/lease": (SafetyLease, {"slave_control": "watchdog"}),
    "safety/arm1/state": (SafetyState, {"mapping": "watchdog"}),
    "mapping/arm1/teleop_state": (TeleopState, {}),  # drawn by the mirror (and shown by consoles)
    # the e-stop key gets only payloads that can never decode (a valid e-stop would stop the arm)
    "estop": (EStop, {"slave_control": "", "watchdog": ""}),
}
SERVICES = ("mapping", "watchdog", "slave_control", "mirror")
MIRROR_TRUSTED = frozenset({"master_capture", "mapping", "slave_control", "watchdog"})
MIRROR_SUBSCRIBED = SUBSCRIBED  # the keys the mirror draws (telesurg.services.mirror.SUBSCRIBED)


#: The identity the fuzzer signs every payload with (shared/auth.py): its payloads pass the
#: authenticator and meet the strict decoder and the source rules; a decodable one whose header
#: ``src`` is not this signer is rejected by the authenticator (signer ≠ src).
FUZZ_SIGNER = "fuzz"


def fuzz_signer(node: Node) -> Signer:
    """The fuzzer's signer, its key from ``node``'s keyring (added there if absent)."""
    return Signer(FUZZ_SIGNER, node.keyring.ensure(FUZZ_SIGNER))


#: Payload + attachment bytes above which the site router drops a message on a control key where
#: it enters (its size cap, services/router): such a payload reaches no service.
ROUTER_CAP = RouterConfig().max_message_bytes


def expected_rejections(key: str, payload: bytes) -> dict[str, int]:
    """Which services must reject ``payload`` on ``key`` (1), signed by :data:`FUZZ_SIGNER` —
    by the same strict decoder, source rules and signer = ``src`` rule."""
    cls, subs = TARGETS[key]
    out = {}
    try:
        msg = decode_as(payload, cls)
        src = msg.header.source
    except MessageError:
        msg, src = None, ""
    for svc, allowed in subs.items():
        out[svc] = int(msg is None or src != FUZZ_SIGNER or (bool(allowed) and src != allowed))
    if not any(fnmatchcase(key, pattern) for pattern in MIRROR_SUBSCRIBED):
        out["mirror"] = 0  # the mirror does not subscribe to this key (leases, e-stop)
        return out
    try:
        anymsg = decode(payload)
        role = key.split("/")[0]
        out["mirror"] = int(
            anymsg.header.source != FUZZ_SIGNER
            or (
                anymsg.header.source not in MIRROR_TRUSTED
                and role in ("master", "slave", "safety", "mapping")
            )
        )
    except MessageError:
        out["mirror"] = 1  # the mirror decodes any message type on the keys it draws
    return out


Tally = dict[str, tuple[int, int, int]]


def rejections(before: Tally, after: Tally) -> tuple[dict[str, int], dict[str, int]]:
    """Per service, the fuzz payloads it rejected between two :meth:`Pipeline.tallies` (rejected
    less replayed: no fuzz payload reaches the freshness rules) and the messages it lost."""
    rej, lost = {}, {}
    for s in SERVICES:
        r0, p0, l0 = before.get(s, (0, 0, 0))
        r1, p1, l1 = after.get(s, (0, 0, 0))
        rej[s], lost[s] = (r1 - r0) - (p1 - p0), l1 - l0
    return rej, lost


def counts_match(rej: dict[str, int], lost: dict[str, int], expected: dict[str, int]) -> bool:
    """Each service rejected exactly what it must, or, if it lost messages (fell behind its
    buffers), no more than that."""
    return all(rej[s] == expected[s] or (lost[s] > 0 and rej[s] <= expected[s]) for s in SERVICES)


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bench fuzz``."""
    ap = argparse.ArgumentParser(
        prog="telesurg bench fuzz", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--count", type=int, default=10_000, help="payloads to publish (default 10000)")
    ap.add_argument("--rate", type=float, default=500.0, help="payloads per second (default 500)")
    ap.add_argument("--seed", type=int, default=1, help="generator seed (default 1)")
    ap.add_argument("--json", type=Path, help="write the result as JSON here")
    ap.add_argument("--log-dir", type=Path, help="service logs (default: a temporary directory)")
    args = ap.parse_args(argv)
    if args.count < 1 or args.rate <= 0:
        print("telesurg bench fuzz: --count and --rate must be positive", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="telesurg-fuzz-") as tmp:
        log_dir = args.log_dir or Path(tmp) / "logs"
        result = run(args.count, args.rate, args.seed, log_dir)
    result["command"] = "telesurg bench fuzz " + " ".join(argv if argv is not None else sys.argv[3:])
    print_table(result)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(jsonio.dumps(result, indent=2))
    return 0 if result["ok"] else 1


def run(count: int, rate: float, seed: int, log_dir: Path) -> dict[str, Any]:
    """Fuzz a running pipeline; the measured result."""
    rng = random.Random(seed)
    keys = list(TARGETS)
    gens = {}
    for k in keys:
        cls = TARGETS[k][0]
        kinds = [x for x in FUZZ_KINDS if always_invalid(x)] if k == "estop" else None
        tmpl = [valid_template(cls, source="fuzz")]
        gens[k] = fuzz_cases(random.Random(rng.random()), tmpl, count, **({"kinds": kinds} if kinds else {}))
    expected: Counter[str] = Counter()
    kinds_sent: Counter[str] = Counter()
    with Pipeline(log_dir) as pipe:
        p = pipe.p
        if not pipe.wait_following(30):
            raise RuntimeError("the slave never followed before fuzzing")
        # the counts before: once every service has caught up. A mirror still working through
        # its start-up backlog (it runs at idle priority) rejects the oldest of it as stale,
        # and those rejections must not be counted as the fuzzer's.
        pipe.settled_heartbeats()
        before = pipe.tallies()
        with p.lock:
            holds0 = p.op[-1][5] if p.op else 0
        import zenoh

        prefix = pipe.node.keys.prefix
        signer = fuzz_signer(pipe.node)
        # BLOCK, not zenoh's default DROP: every payload must arrive for the counts to match.
        pubs = {
            k: pipe.node.session.declare_publisher(
                f"{prefix}/{k}", congestion_control=zenoh.CongestionControl.BLOCK
            )
            for k in keys
        }
        t_start = time.monotonic()
        at_router = 0
        for i in range(count):
            key = keys[i % len(keys)]
            case = next(gens[key])
            if key == "estop" and expected_rejections(key, case.payload)["watchdog"] == 0:
                continue  # never send a decodable e-stop
            attachment = signer.attach(PUT, f"{prefix}/{key}", case.payload)
            pubs[key].put(case.payload, attachment=attachment)
            kinds_sent[case.kind] += 1
            if len(case.payload) + len(attachment) > ROUTER_CAP:
                at_router += 1  # the router's size cap drops it before any service sees it
            else:
                expected.update(expected_rejections(key, case.payload))
            lag = t_start + (i + 1) / rate - time.monotonic()
            if lag > 0:
                time.sleep(lag)
        duration = time.monotonic() - t_start
        pipe.settled_heartbeats()
        rej, lost = rejections(before, pipe.tallies())
        following_after = pipe.wait_following(12.0)
        dead = pipe.site.dead()
        with p.lock:
            holds = (p.op[-1][5] if p.op else 0) - holds0
            slave_rejected = p.op[-1][7] if p.op else 0
        with p.lock:
            joints = np.array(p.joints, dtype=float)
        for pub in pubs.values():
            pub.undeclare()  # type: ignore[no-untyped-call]
        codes = pipe.close()
    lo, hi = np.array(MH3F.lower), np.array(MH3F.upper)
    outside = int(((joints < lo) | (joints > hi)).any(axis=1).sum()) if joints.size else 0
    sent = sum(kinds_sent.values())
    result: dict[str, Any] = {
        "date": now(),
        "machine": machine(),
        "cpus": os.cpu_count(),
        "sent": sent,
        "seconds": round(duration, 1),
        "rate_per_s": round(sent / duration, 0),
        "kinds": dict(sorted(kinds_sent.items())),
        "crashes": len(dead) + sum(1 for c in codes.values() if c != 0),
        "dead": dead,
        "exit_codes": codes,
        "rejected": rej,
        "expected_rejected": {s: expected.get(s, 0) for s in SERVICES},
        "lost": lost,
        "dropped_at_router": at_router,
        "slave_holds_during_fuzz": holds,
        "slave_rejected_setpoints_total": slave_rejected,
        "joint_samples_outside_limits": outside,
        "joint_samples_checked": int(joints.shape[0]) if joints.size else 0,
        "following_after": following_after,
    }
    result["counts_match"] = counts_match(rej, lost, result["expected_rejected"])
    result["ok"] = bool(
        result["crashes"] == 0 and outside == 0 and result["counts_match"] and following_after
    )
    return result


def print_table(r: dict[str, Any]) -> None:
    """A rich table of the result."""
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"telesurg bench fuzz: {r['sent']} payloads in {r['seconds']} s")
    t.add_column("figure")
    t.add_column("value", justify="right")
    t.add_row("crashed services", str(r["crashes"]))
    for s, n in r["rejected"].items():
        behind = f"; fell behind, {r['lost'][s]} lost" if r["lost"][s] else ""
        t.add_row(f"rejected by {s}", f"{n} (expected {r['expected_rejected'][s]}{behind})")
    t.add_row("slave holds during the run", str(r["slave_holds_during_fuzz"]))
    t.add_row(
        "joint samples outside limits", f"{r['joint_samples_outside_limits']} of {r['joint_samples_checked']}"
    )
    t.add_row("following after the run", "yes" if r["following_after"] else "NO")
    t.add_row("verdict", "ok" if r["ok"] else "FAILED")
    Console().print(t)
