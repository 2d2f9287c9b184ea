"""``telesurg cmd``: send one operator command to a slave arm and print the reply.

Commands are served by slave_control on ``slave/<arm>/command`` (see ``docs/trocar.md``); each
is accepted, or refused with the reason, and a refused command changes nothing.

Examples::

    telesurg cmd state
    telesurg cmd begin_posture_adjust method=ptp
    telesurg cmd finish_posture_adjust
    telesurg cmd insert            # jog along the forceps axis; trocar mode from 50 mm deep
    telesurg cmd jog frame=base axis=y direction=1
    telesurg cmd stop
    telesurg cmd remove

Exit codes: 0 accepted, 1 refused, 2 no reply / bad arguments / connection error.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from telesurg.shared.bus import Node, add_bus_args, bus_from_args
from telesurg.shared.errors import ConfigError, MessageError
from telesurg.shared.keys import check_id
from telesurg.shared.messages import Command, CommandReply


def main(argv: Sequence[str] | None = None) -> int:
    """Send the command, print ``accepted: …`` or ``refused: …``."""
    ap = argparse.ArgumentParser(
        prog="telesurg cmd", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("name", help="command name, e.g. state, insert, jog")
    ap.add_argument("args", nargs="*", metavar="KEY=VALUE", help="command arguments")
    ap.add_argument("--arm", default="arm1", help="slave arm id (default: arm1)")
    ap.add_argument("--site", default="local", help="site id (default: local)")
    ap.add_argument("--timeout", type=float, default=3.0, help="s to wait for the reply (default 3)")
    add_bus_args(ap)
    a = ap.parse_args(argv)
    try:
        check_id("arm", a.arm)
        bus = bus_from_args(a)
        with Node(bus, a.site, f"console_cli_{os.getpid()}") as node:
            key = node.keys.command(a.arm)
            out = node.outlet(key, control=False)
            # from_body validates like the receiver will (name pattern, key=value arguments)
            cmd = Command.from_body(out.header(), {"arm": a.arm, "name": a.name, "args": list(a.args)})
            reply = node.request(key, cmd, CommandReply, a.timeout)
    except (ConfigError, ConnectionError, MessageError, TimeoutError) as exc:
        print(f"telesurg cmd: {exc}", file=sys.stderr)
        return 2
    print(f"{'accepted' if reply.accepted else 'refused'}: {reply.reason}")
    return 0 if reply.accepted else 1
