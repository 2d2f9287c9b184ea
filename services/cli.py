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
import importlib.util
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass

from telesurg.shared.service_table import SERVICES


@dataclass(frozen=True)
class Command:
    """A ``telesurg`` command that is not a site process: ``module`` has ``main(argv) -> int``."""

    name: str
    module: str
    help: str
    own_session: bool = False  # from the command line it runs in a session (autogroup) of its own
    extra: str = ""  # the optional dependencies it needs: ``pip install 'telesurg[<extra>]'``


_S = "telesurg.services"
_T = "telesurg.tools"
OTHER_COMMANDS: tuple[Command, ...] = (
    Command(
        "up", f"{_S}.launcher", "start router + all services locally; Ctrl-C stops all", own_session=True
    ),
    Command("demo", f"{_S}.launcher.demo", "the whole simulated teleop session (scripted circle)", True),
    Command("site", f"{_S}.launcher.site", "write the packaged site files to DIR (init), check one"),
    Command("estop", f"{_S}.estop", "e-stop (or --reset) one arm or every arm of a site"),
    Command("cmd", f"{_S}.command", "send an operator command (trocar mode, jog, …) to a slave arm"),
    Command("certs", f"{_S}.certs", "make a CA and per-identity certificates for mutual TLS"),
    Command("keys", f"{_S}.keys", "the site keyring that authenticates every message (init, list, …)"),
    Command("record", f"{_S}.record", "record every message of a site into an MCAP file"),
    Command("replay", f"{_S}.record.replay", "replay a recording's master streams into a live site, compare"),
    Command(
        "export", f"{_S}.record.export", "a recording in Foxglove / ROS 2 schemas (MCAP) or as a rerun .rrd"
    ),
    Command("view", f"{_S}.camera.view", "show a site's live camera picture in a small web page"),
    Command("bridge", f"{_S}.bridge", "bridge ros2: an arm's CRTK topics for ROS 2 (rmw_zenoh)"),
    Command("docs", f"{_S}.docs", "regenerate (or --check) the docs pages built from the code"),
    # tools beside the runtime (tools/): the runtime never imports them
    Command("bench", f"{_T}.bench", "fault-injection and fuzz benchmarks (tables + JSON)", True, "lab"),
    Command(
        "experiment",
        f"{_T}.experiment",
        "reproduce a paper's evaluation (figures + metrics.json)",
        extra="lab",
    ),
    Command(
        "study", f"{_T}.study", "a user study: tasks × conditions, synthetic operator, report", True, "lab"
    ),
    Command("impair", f"{_T}.bench.impair", "userspace TCP link impairer (cut / delay) for fault tests"),
    Command("device", f"{_T}.emulate", "serial device tools: emulate an encoder board on a pty, monitor one"),
)


#: subcommand → (module with a ``main(argv) -> int``, help), from the service table
#: (:mod:`telesurg.shared.service_table`), then the other commands.
COMMANDS: dict[str, tuple[str, str]] = {
    **{s.cli: (s.module, s.help) for s in SERVICES},
    **{c.name: (c.module, c.help) for c in OTHER_COMMANDS},
}
#: Commands that start a site (or a bench's) and watch it: run from the command line, each runs in
#: a session, so a scheduler autogroup, of its own (:mod:`telesurg.shared.session`), not in the
#: busy jobs' of its shell.
OWN_SESSION = tuple(c.name for c in OTHER_COMMANDS if c.own_session)
#: command → the optional dependency group it needs (``pip install 'telesurg[lab]'``)
EXTRAS = {c.name: c.extra for c in OTHER_COMMANDS if c.extra}


def missing_extra(extra: str) -> list[str]:
    """The distributions of the installed package's optional group ``extra`` that are not
    installed (none for an unknown group, or when telesurg's metadata is not installed)."""
    from importlib import metadata

    try:
        requires = metadata.requires("telesurg") or []
    except metadata.PackageNotFoundError:
        return []
    missing = []
    for req in requires:
        name, _, marker = req.partition(";")
        if marker.replace("'", '"').split() != ["extra", "==", f'"{extra}"']:
            continue
        dist = re.split(r"[\s\[<>=!~]", name.strip(), maxsplit=1)[0]
        try:
            found = importlib.util.find_spec(dist.replace("-", "_")) is not None
        except ImportError:
            found = False
        if not found:
            missing.append(dist)
    return missing


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
    if (extra := EXTRAS.get(cmd)) and (missing := missing_extra(extra)):
        print(
            f"telesurg {cmd} needs the {extra!r} extra ({', '.join(missing)} not installed): "
            f"pip install 'telesurg[{extra}]' (in a checkout: pip install -e '.[{extra}]')",
            file=sys.stderr,
        )
        return 2
    module = importlib.import_module(COMMANDS[cmd][0])
    code: int = module.main(rest)
    return code


if __name__ == "__main__":
    sys.exit(main())
