"""``telesurg estop``: send an e-stop (or its reset) to one arm or every arm of a site.

The watchdog and slave_control both latch the e-stop: the arm holds (watchdog state ESTOP, slave
``FAULT``) until ``telesurg estop --reset``; after the reset the operator must engage again.
The command waits until the watchdog's state confirms it and exits 0, or 1 if no confirmation
came within ``--timeout``. It sends as the operator console identity (``--as``, default
``console``): anyone may e-stop, only the operator console may reset (docs/security.md).

Example::

    telesurg estop --connect tcp/127.0.0.1:7447 --reason "instrument collision"
    telesurg estop --connect tcp/127.0.0.1:7447 --reset
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
from collections.abc import Sequence

from telesurg.shared.bus import Node, add_bus_args, bus_from_args
from telesurg.shared.errors import ConfigError
from telesurg.shared.keys import check_id
from telesurg.shared.messages import EStop, SafetyState, Sequencer


def main(argv: Sequence[str] | None = None) -> int:
    """Publish one EStop and wait for the watchdog to confirm."""
    ap = argparse.ArgumentParser(
        prog="telesurg estop", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--site", default="local", help="site id (default: local)")
    ap.add_argument("--arm", default="*", help="slave arm id, or * for every arm (default)")
    ap.add_argument("--reset", action="store_true", help="reset a latched e-stop instead")
    ap.add_argument("--reason", default="", help="shown in the events")
    ap.add_argument("--timeout", type=float, default=2.0, help="s to wait for confirmation (default 2)")
    ap.add_argument(
        "--as", dest="identity", default="console", help="sender identity, header src (default: console)"
    )
    add_bus_args(ap)
    args = ap.parse_args(argv)
    try:
        if args.arm != "*":
            check_id("arm", args.arm)
        check_id("service", args.identity)
        bus = bus_from_args(args)
        action = "reset" if args.reset else "estop"
        with Node(bus, args.site, args.identity) as node:  # the identity signs (and is the header src)
            done = threading.Event()
            seen: dict[str, str] = {}

            def on_state(msg: SafetyState, key: str) -> None:
                if args.arm in ("*", msg.arm):
                    seen[msg.arm] = msg.state
                    if (msg.state == "ESTOP") == (action == "estop"):
                        done.set()

            arm_key = "*" if args.arm == "*" else args.arm
            node.subscribe(f"{node.keys.prefix}/safety/{arm_key}/state", SafetyState, on_state)
            out = node.outlet(node.keys.estop)
            seq = Sequencer(args.identity)
            reason = args.reason or f"telesurg estop (pid {os.getpid()})"
            # Re-send until confirmed: the first put may race the subscriber discovery.
            for _ in range(max(1, int(args.timeout / 0.2))):
                out.put(EStop(seq.next(), args.arm, action, reason))
                if done.wait(0.2):
                    break
    except (ConfigError, ConnectionError) as exc:
        print(f"telesurg estop: {exc}", file=sys.stderr)
        return 2
    states = ", ".join(f"{a}: {s}" for a, s in sorted(seen.items())) or "no watchdog state received"
    print(f"{action} {'confirmed' if done.is_set() else 'NOT confirmed'} ({states})")
    return 0 if done.is_set() else 1
