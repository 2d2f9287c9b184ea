"""``telesurg bench``: measurements that print a table and write JSON.

Subcommands::

    telesurg bench faults [--json FILE] [--only kill:mapping,cut:0.6,...]
    telesurg bench attack [--json FILE] [--quick] [--only CASE,...]
    telesurg bench fuzz --count N [--json FILE]
    telesurg bench latency --rate 1000 --seconds 10 [--json FILE]
    telesurg bench soak --rate 1000 --seconds 60 [--json FILE]
    telesurg bench arms --arms 1,2,4 --rate 1000 --seconds 20 [--json FILE]
    telesurg bench ik [--n 1000] [--json FILE]
    telesurg bench sim [--seconds 5] [--json FILE]
    telesurg bench decode [--n 20000] [--json FILE]
    telesurg bench flood [--site locked|open] [--no-caps] [--json FILE]
    telesurg bench viewer [--seconds 100] [--json FILE]
    telesurg bench ingest --kind poses|primitives|series|trail [--rate 10] [--json FILE]
    telesurg bench memory [--seconds 300] [--set SERVICE.KEY=VALUE] [--json FILE] [--plot FILE]
    telesurg bench wakeup [--seconds 10] [--blocks 2] [--slice-us 100] [--load cpu:2] [--json FILE]
    telesurg bench links [--pairs 4] [--seconds 20] [--rate 1000] [--json FILE]
    telesurg bench haptics [--services] [--quick] [--json FILE] [--plot FILE]
    telesurg bench gym [--steps 2000] [--runs 3] [--json FILE]
"""

from __future__ import annotations

import importlib
import os
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from telesurg.shared.auth import IDENTITIES, KEYS_ENV, init_keyring

BENCHES = {
    "faults": ("telesurg.tools.bench.faults", "inject faults one at a time; detection, motion, recovery"),
    "attack": (
        "telesurg.tools.bench.attack",
        "forged messages / commands against a site: accepted, motion",
    ),
    "fuzz": ("telesurg.tools.bench.fuzz", "malformed messages on every key while the pipeline runs"),
    "latency": ("telesurg.tools.bench.perf", "one-way latency: bare zenoh relay vs the real pipeline"),
    "soak": ("telesurg.tools.bench.perf", "long run: losses per stream, deadline misses, CPU and RSS"),
    "arms": (
        "telesurg.tools.bench.arms",
        "a robot of N arms at the control rate: CPU per service, misses, HOLDs, latency vs the relay",
    ),
    "ik": ("telesurg.tools.bench.perf", "analytic IK / mapping vs a generic numerical IK"),
    "sim": ("telesurg.tools.bench.perf", "MuJoCo steps/s unpaced per robot model"),
    "video": (
        "telesurg.tools.bench.video",
        "endoscope video: fps, render/encode/transport/decode, age; control path camera on/off",
    ),
    "decode": ("telesurg.tools.bench.decode", "µs per strict decode / encode of the hot messages"),
    "flood": ("telesurg.tools.bench.flood", "1 MB messages on a control and a master key: RSS, HOLDs"),
    "memory": ("telesurg.tools.bench.memory", "RSS of each service over a quiet run: growth MB/s"),
    "auth": ("telesurg.tools.bench.auth", "µs per sign / verify (HMAC, Ed25519) of the hot messages"),
    "viewer": (
        "telesurg.tools.bench.viewer",
        "the rerun web viewer in Chromium during the demo: lag behind live, frames/s, HOLDs",
    ),
    "ingest": (
        "telesurg.tools.bench.ingest",
        "messages of one kind a second the rerun web viewer takes in (software WebGL)",
    ),
    "wakeup": (
        "telesurg.tools.bench.wakeup",
        "how late a control process's thread wakes up: the kernel's scheduler slice vs a shorter one",
    ),
    "links": (
        "telesurg.tools.bench.links",
        "the bare relay over a TCP loopback link vs a Unix socket: CPU and latency",
    ),
    "haptics": (
        "telesurg.tools.bench.haptics",
        "bilateral force feedback (none/naive/TDPA/wave) vs round trip, jitter, loss (in-process; "
        "--services: through a real site)",
    ),
    "gym": ("telesurg.gym.bench", "ms per step of each Gymnasium environment, no rendering"),
    "transport": (
        "telesurg.tools.bench.transport",
        "zenoh links for a 1 kHz stream under packet loss (root)",
    ),
}


def main(argv: Sequence[str] | None = None) -> int:
    """Dispatch to a bench."""
    args = list(sys.argv[2:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help") or args[0] not in BENCHES:
        lines = ["usage: telesurg bench NAME [options]", ""]
        lines += [f"  {n:<8} {d}" for n, (_, d) in BENCHES.items()]
        print("\n".join(lines), file=sys.stdout if not args or args[0] in ("-h", "--help") else sys.stderr)
        return 0 if not args or args[0] in ("-h", "--help") else 2
    module = importlib.import_module(BENCHES[args[0]][0])
    # every bench runs on a keyring of its own, never the site's real one: its strangers and
    # tools (intruder, fuzz, local_client, bench_probe) add their keys to this one only
    # (restored after: a bench called in-process must not leave the caller on a deleted keyring)
    before = os.environ.get(KEYS_ENV)
    with tempfile.TemporaryDirectory(prefix="telesurg-bench-keys-") as tmp:
        os.environ[KEYS_ENV] = str(init_keyring(Path(tmp) / "keys", IDENTITIES))
        try:
            if BENCHES[args[0]][0] == "telesurg.tools.bench.perf":
                code: int = module.main(args[1:], args[0])
            else:
                code = module.main(args[1:])
        finally:
            if before is None:
                os.environ.pop(KEYS_ENV, None)
            else:
                os.environ[KEYS_ENV] = before
    return code
