"""``telesurg keys``: the site keyring that authenticates every message (shared/auth.py).

One file per identity (``<identity>.key``, 32 random bytes in hex, mode 0600) in a directory of
mode 0700. ``telesurg up`` / ``demo`` make the default keyring if it is absent; every service and
command-line tool loads the same default (``$TELESURG_KEYS``, else
``$XDG_STATE_HOME/telesurg/<site>/keys``), or ``--keys DIR``. For two hosts (a console host and a
slave site), export the identities the other host needs and import them there.

Examples::

    telesurg keys init                                 # the default keyring of site "local"
    telesurg keys init /etc/telesurg/keys --site lab   # a keyring in a chosen place
    telesurg keys list                                 # identities (never the keys)
    telesurg keys add console2                         # one more identity
    telesurg keys export console watchdog --out pack   # copy these to the other host ...
    telesurg keys import pack                          # ... and add them to its keyring there
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from telesurg.shared.auth import IDENTITIES, Keyring, default_keys_dir, init_keyring, write_key
from telesurg.shared.errors import ConfigError


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg keys``."""
    p = argparse.ArgumentParser(
        prog="telesurg keys", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--site", default="local", help="site id: the default keyring's folder (default: local)")
    sub = p.add_subparsers(dest="cmd", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--site", dest="site_", help="site id: the default keyring's folder (default: local)")
    i = sub.add_parser(
        "init", parents=[common], help="make a keyring (the site's identities; existing keys are kept)"
    )
    i.add_argument("dir", nargs="?", help="keyring folder (default: the site's default keyring)")
    i.add_argument("--identity", action="append", default=[], help="identities to add (default: the site's)")
    ls = sub.add_parser("list", parents=[common], help="identities in a keyring (never the keys)")
    ls.add_argument("dir", nargs="?")
    a = sub.add_parser("add", parents=[common], help="add identities to a keyring")
    a.add_argument("identity", nargs="+")
    a.add_argument("--keys", metavar="DIR", help="keyring folder (default: the site's default)")
    e = sub.add_parser(
        "export", parents=[common], help="copy identities' keys into a new folder (for another host)"
    )
    e.add_argument("identity", nargs="+")
    e.add_argument("--out", required=True, type=Path, help="folder to write (made with mode 0700)")
    e.add_argument("--keys", metavar="DIR", help="keyring folder (default: the site's default)")
    m = sub.add_parser("import", parents=[common], help="add the keys of an exported folder to a keyring")
    m.add_argument("src", type=Path)
    m.add_argument("--keys", metavar="DIR", help="keyring folder (default: the site's default)")
    args = p.parse_args(argv)
    site = getattr(args, "site_", None) or args.site
    try:
        if args.cmd == "init":
            d = Path(args.dir) if args.dir else default_keys_dir(site)
            init_keyring(d, tuple(args.identity) or IDENTITIES)
            print(f"keyring {d}: {', '.join(Keyring.load(d).identities())}")
        elif args.cmd == "list":
            d = Path(args.dir) if args.dir else default_keys_dir(site)
            print("\n".join(Keyring.load(d).identities()))
        elif args.cmd == "add":
            d = Path(args.keys) if args.keys else default_keys_dir(site)
            Keyring.load(d)
            for ident in args.identity:
                print(f"{ident}: {'added' if write_key(d, ident) else 'already there'}")
        elif args.cmd == "export":
            ring = Keyring.load(Path(args.keys) if args.keys else default_keys_dir(site))
            init_keyring(args.out)
            for ident in args.identity:
                key = ring.key(ident)
                if key is None:
                    raise ConfigError(
                        f"no key for {ident!r} in {ring.path}; known: {', '.join(ring.identities())}"
                    )
                write_key(args.out, ident, key)
            print(f"exported {', '.join(args.identity)} to {args.out} (copy it securely, then delete it)")
        else:
            src = Keyring.load(args.src)
            d = Path(args.keys) if args.keys else default_keys_dir(site)
            init_keyring(d)
            for ident in src.identities():
                if not write_key(d, ident, src.keys[ident]):
                    have = Keyring.load(d).key(ident)
                    if have != src.keys[ident]:
                        raise ConfigError(f"{d} already has a different key for {ident!r}; remove it first")
            print(f"imported {', '.join(src.identities())} into {d}")
    except ConfigError as exc:
        print(f"telesurg keys: {exc}", file=sys.stderr)
        return 2
    return 0
