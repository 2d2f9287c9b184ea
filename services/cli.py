"""``telesurg``: one CLI, one subcommand per service plus the launcher.

Examples::

    telesurg demo                       # whole simulated session + rerun web viewer
    telesurg demo --headless --seconds 20 --save out.rrd --report out.json
    telesurg up                         # router + every service, Ctrl-C stops them
    telesurg up --config-dir deploy/plas   # another site: deploy/plas/site.toml
    telesurg site init mysites          # the packaged site files and deploy scripts, to edit
    telesurg slave-control --help       # one service on its own
    telesurg --version                  # the installed package's version
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

#: subcommand → module with a ``main(argv) -> int``
COMMANDS = {
    "router": ("telesurg.services.router", "zenoh router for a site (Python process, no zenohd)"),
    "master-capture": ("telesurg.services.master_capture", "publish a master device's pose and buttons"),
    "mapping": ("telesurg.services.mapping", "master pose → slave joint setpoints (clutch, scale, IK)"),
    "slave-control": ("telesurg.services.slave_control", "run the slave arm (MuJoCo) under a lease"),
    "watchdog": ("telesurg.services.watchdog", "grant slave leases while every service is healthy"),
    "mirror": ("telesurg.services.mirror", "stream everything to rerun (web viewer or .rrd)"),
    "up": ("telesurg.services.launcher", "start router + all services locally; Ctrl-C stops all"),
    "demo": ("telesurg.services.launcher.demo", "the whole simulated teleop session (scripted circle)"),
    "site": ("telesurg.services.launcher.site", "write the packaged site files to DIR (init), check one"),
    "estop": ("telesurg.services.estop", "e-stop (or --reset) one arm or every arm of a site"),
    "cmd": ("telesurg.services.command", "send an operator command (trocar mode, jog, …) to a slave arm"),
    "bench": ("telesurg.services.bench", "fault-injection and fuzz benchmarks (tables + JSON)"),
    "impair": ("telesurg.services.bench.impair", "userspace TCP link impairer (cut / delay) for fault tests"),
    "device": (
        "telesurg.services.device",
        "serial device tools: emulate an encoder board on a pty, monitor one",
    ),
    "console": (
        "telesurg.services.console",
        "operator console (terminal UI): state, clutch, commands, e-stop",
    ),
    "certs": ("telesurg.services.certs", "make a CA and per-identity certificates for mutual TLS"),
    "keys": ("telesurg.services.keys", "the site keyring that authenticates every message (init, list, …)"),
    "record": ("telesurg.services.record", "record every message of a site into an MCAP file"),
    "replay": (
        "telesurg.services.record.replay",
        "replay a recording's master streams into a live site, compare",
    ),
    "export": (
        "telesurg.services.record.export",
        "a recording in Foxglove / ROS 2 schemas (MCAP) or as a rerun .rrd",
    ),
    "docs": ("telesurg.services.docs", "regenerate (or --check) the docs pages built from the code"),
    "experiment": ("telesurg.services.experiment", "reproduce a paper's evaluation (figures + metrics.json)"),
    "camera": (
        "telesurg.services.camera",
        "the endoscope view: MuJoCo render or a real camera → JPEG frames",
    ),
    "view": ("telesurg.services.camera.view", "show a site's live camera picture in a small web page"),
    "bridge": ("telesurg.services.bridge", "bridge ros2: an arm's CRTK topics for ROS 2 (rmw_zenoh)"),
}
#: Commands that start a site (or a bench's) and watch it: run from the command line, each runs in
#: a session, so a scheduler autogroup, of its own (:mod:`telesurg.shared.session`), not in the
#: busy jobs' of its shell.
OWN_SESSION = ("up", "demo", "bench")


def version() -> str:
    """The installed package's version (its metadata), e.g. ``0.1.0``."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as package_version

    try:
        return package_version("telesurg")
    except PackageNotFoundError:  # a bare checkout on sys.path, never installed
        return "unknown (not installed)"


def usage() -> str:
    """Help text listing the subcommands."""
    lines = ["usage: telesurg COMMAND [options]   (telesurg COMMAND --help for options)"]
    lines += ["       telesurg --version", ""]
    lines += [f"  {name:<15} {desc}" for name, (_, desc) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Dispatch to the subcommand's ``main``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return 0
    if args[0] in ("-V", "--version"):
        print(f"telesurg {version()}")
        return 0
    cmd, rest = args[0], args[1:]
    if cmd not in COMMANDS:
        print(f"telesurg: unknown command {cmd!r}\n\n{usage()}", file=sys.stderr)
        return 2
    if cmd in OWN_SESSION and argv is None:  # from the command line (a caller's main(argv) runs here)
        from telesurg.shared.session import run_in_own_session

        if (rc := run_in_own_session(args)) is not None:
            return rc
    module = importlib.import_module(COMMANDS[cmd][0])
    code: int = module.main(rest)
    return code


if __name__ == "__main__":
    sys.exit(main())
