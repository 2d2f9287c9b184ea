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
    telesurg cmd remove --yes      # confirm a motion-starting command without asking

Operator authority (docs/security.md#10-operator-authority): commands are sent as the operator
console identity (``--as``, default ``console``); a stranger may only ask ``state`` / ``programs``
and stop. A motion-starting command (PTP, jog, insert / remove, playback, mode changes, VIP) is
answered ``confirm required`` with a summary and a token: ``telesurg cmd`` shows it and asks
(on a terminal), or confirms at once with ``--yes``; without either it is not carried out.

Exit codes: 0 accepted, 1 refused (or not confirmed), 2 no reply / bad arguments / connection error.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from telesurg.shared.authority import CONFIRM_ARG
from telesurg.shared.bus import Node, add_bus_args, bus_from_args
from telesurg.shared.errors import ConfigError, MessageError
from telesurg.shared.keys import check_id
from telesurg.shared.messages import Command, CommandReply, Sequencer


def _ask(question: str) -> bool:
    """Ask the operator on a terminal; False without one (then ``--yes`` is needed)."""
    if not sys.stdin.isatty():
        return False
    try:
        return input(f"{question}\nconfirm? [y/N] ").strip().lower() in ("y", "yes")
    except EOFError:
        return False


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
    ap.add_argument(
        "--mapping", action="store_true", help="send to the mapping (scale, VIP) instead of the slave"
    )
    ap.add_argument("--yes", action="store_true", help="confirm a motion-starting command without asking")
    ap.add_argument(
        "--as", dest="identity", default="console", help="sender identity, header src (default: console)"
    )
    add_bus_args(ap)
    a = ap.parse_args(argv)
    try:
        check_id("arm", a.arm)
        check_id("service", a.identity)
        bus = bus_from_args(a)
        with Node(bus, a.site, a.identity) as node:  # the identity signs (and is the header src)
            key = node.keys.mapping_command(a.arm) if a.mapping else node.keys.command(a.arm)
            seq = Sequencer(a.identity)
            # from_body validates like the receiver will (name pattern, key=value arguments)
            cmd = Command.from_body(seq.next(), {"arm": a.arm, "name": a.name, "args": list(a.args)})
            try:
                reply = node.request(key, cmd, CommandReply, a.timeout)
                if reply.confirm:
                    if not (a.yes or _ask(reply.reason)):
                        print(f"not confirmed: {reply.reason}")
                        return 1
                    args = [*a.args, f"{CONFIRM_ARG}={reply.confirm}"]
                    cmd = Command.from_body(seq.next(), {"arm": a.arm, "name": a.name, "args": args})
                    reply = node.request(key, cmd, CommandReply, a.timeout)
            except MessageError as exc:  # refused by the authority (or the router's ACL): the reason
                print(f"refused: {exc}")
                return 1
    except (ConfigError, ConnectionError, MessageError, TimeoutError) as exc:
        print(f"telesurg cmd: {exc}", file=sys.stderr)
        return 2
    print(f"{'accepted' if reply.accepted else 'refused'}: {reply.reason}")
    return 0 if reply.accepted else 1
