"""``telesurg bridge``: bridges between the site's bus and other middleware.

``telesurg bridge ros2``: one slave arm's CRTK topics over the rmw_zenoh wire format, for ROS 2
nodes (:mod:`telesurg.services.bridge.ros2`, docs/ros2.md). ``--arm A`` and ``--domain N`` are
short for ``--set arm="A"`` and ``--set domain=N``; every other flag is the service's.

Example::

    telesurg bridge ros2 --arm arm1 --domain 0
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence

KINDS = ("ros2",)
_SHORT: dict[str, tuple[str, Callable[[str], str]]] = {
    "--arm": ("arm", json.dumps),
    "--domain": ("domain", str),
}


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bridge KIND [options]``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(f"usage: telesurg bridge {{{','.join(KINDS)}}} [options]\n\n{__doc__}")
        return 0
    kind, rest = args[0], args[1:]
    if kind not in KINDS:
        print(f"telesurg bridge: unknown bridge {kind!r}; valid: {', '.join(KINDS)}", file=sys.stderr)
        return 2
    out: list[str] = []
    it = iter(rest)
    for a in it:
        flag, _, value = a.partition("=")
        if flag in _SHORT:
            if not value:
                value = next(it, "")
            if not value:
                print(f"telesurg bridge {kind}: {flag} needs a value", file=sys.stderr)
                return 2
            name, fmt = _SHORT[flag]
            out += ["--set", f"{name}={fmt(value)}"]
        else:
            out.append(a)
    from telesurg.services.bridge import ros2

    return ros2.main(out)
