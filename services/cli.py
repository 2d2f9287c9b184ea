"""``telesurg``: one CLI, one subcommand per service plus the launcher.

Examples::

    telesurg demo                       # whole simulated session + rerun web viewer
    telesurg demo --headless --seconds 20 --save out.rrd --report out.json
    telesurg up                         # router + every service, Ctrl-C stops them
    telesurg up --config-dir deploy/plas   # another site: deploy/plas/site.toml
    telesurg site init mysites          # the packaged site files and deploy scripts, to edit
    telesurg slave-control --help       # one service on its own
"""

from __future__ import annotations

import importlib
import importlib.util
import re
import sys
from collections.abc import Sequence

from telesurg.services import COMMANDS as _COMMANDS
from telesurg.services import SERVICES

#: subcommand → (module with a ``main(argv) -> int``, help), from the service table
#: (:mod:`telesurg.services`): every site process, then the other commands.
COMMANDS: dict[str, tuple[str, str]] = {
    **{s.cli: (s.module, s.help) for s in SERVICES},
    **{c.name: (c.module, c.help) for c in _COMMANDS},
}
#: Commands that start a site (or a bench's) and watch it: run from the command line, each runs in
#: a session, so a scheduler autogroup, of its own (:mod:`telesurg.shared.session`), not in the
#: busy jobs' of its shell.
OWN_SESSION = tuple(c.name for c in _COMMANDS if c.own_session)
#: command → the optional dependency group it needs (``pip install 'telesurg[lab]'``)
EXTRAS = {c.name: c.extra for c in _COMMANDS if c.extra}


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


def usage() -> str:
    """Help text listing the subcommands."""
    lines = ["usage: telesurg COMMAND [options]   (telesurg COMMAND --help for options)", ""]
    lines += [f"  {name:<15} {desc}" for name, (_, desc) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Dispatch to the subcommand's ``main``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage())
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
