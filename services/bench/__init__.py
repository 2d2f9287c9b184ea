"""``telesurg bench``: measurements that print a table and write JSON.

Subcommands::

    telesurg bench faults [--json FILE] [--only kill:mapping,cut:0.6,...]
    telesurg bench fuzz --count N [--json FILE]
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

BENCHES = {
    "faults": ("services.bench.faults", "inject faults one at a time; detection, motion, recovery"),
    "fuzz": ("services.bench.fuzz", "malformed messages on every key while the pipeline runs"),
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
    code: int = module.main(args[1:])
    return code
