"""``telesurg keys``: the site keyring that authenticates every message (shared/auth.py).

One file per identity (``<identity>.key``, 32 random bytes in hex, mode 0600) in a directory of
mode 0700. ``telesurg up`` / ``demo`` make the default keyring if it is absent; every service and
command-line tool loads the same default (``$TELESURG_KEYS``, else
``$XDG_STATE_HOME/telesurg/<site>/keys``), or ``--keys DIR``. For two hosts (a console host and a
slave site), ``export --to HOST`` moves the identities the other host runs into a folder for it,
with a link: a pair of keys between the two hosts, so each verifies what the other sends without
being able to sign as any identity of the other (shared/auth.py).

Examples::

    telesurg keys init                                 # the default keyring of site "local"
    telesurg keys init /etc/telesurg/keys --site lab   # a keyring in a chosen place
    telesurg keys list                                 # identities (never the keys)
    telesurg keys add console2                         # one more identity
    telesurg keys export master_capture console --to console --out pack  # for the console host ...
    telesurg keys import pack                          # ... and add them to its keyring there
"""

from __future__ import annotations

import argparse
import secrets
import sys
from collections.abc import Sequence
from pathlib import Path

from telesurg.shared.auth import (
    IDENTITIES,
    KEY_BYTES,
    KEY_SUFFIX,
    LINK_SUFFIX,
    Keyring,
    Link,
    check_id_name,
    default_keys_dir,
    init_keyring,
    write_key,
    write_private,
)
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
        "export",
        parents=[common],
        help="move identities to another host: their keys and a link to this host, into a new folder",
    )
    e.add_argument("identity", nargs="+")
    e.add_argument("--to", default="console", help="the other host's name (default: console)")
    e.add_argument(
        "--from",
        dest="from_",
        default="slave-site",
        help="this host's name, as the other host will know it (default: slave-site)",
    )
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
            ring = Keyring.load(d)
            print("\n".join(ring.identities()))
            for host, link in sorted(ring.links.items()):
                claims = "every identity not listed above" if "*" in link.claims else ", ".join(link.claims)
                print(f"link to host {host}: signs as {claims}")
        elif args.cmd == "add":
            d = Path(args.keys) if args.keys else default_keys_dir(site)
            Keyring.load(d)
            for ident in args.identity:
                print(f"{ident}: {'added' if write_key(d, ident) else 'already there'}")
        elif args.cmd == "export":
            export(
                Path(args.keys) if args.keys else default_keys_dir(site),
                args.identity,
                args.to,
                args.from_,
                args.out,
            )
        else:
            src = Keyring.load(args.src)
            d = Path(args.keys) if args.keys else default_keys_dir(site)
            init_keyring(d)
            for ident in src.identities():
                if not write_key(d, ident, src.keys[ident]):
                    have = Keyring.load(d).key(ident)
                    if have != src.keys[ident]:
                        raise ConfigError(f"{d} already has a different key for {ident!r}; remove it first")
            for host, link in src.links.items():
                if (
                    not write_private(d, f"{host}{LINK_SUFFIX}", link.to_json())
                    and Keyring.load(d).links[host] != link
                ):
                    raise ConfigError(f"{d} already has a different link to host {host!r}; remove it first")
            links = "".join(f", link to {h}" for h in sorted(src.links))
            print(f"imported {', '.join(src.identities())}{links} into {d}")
    except ConfigError as exc:
        print(f"telesurg keys: {exc}", file=sys.stderr)
        return 2
    return 0


def export(
    keyring: Path, identities: list[str], to: str, this_host: str, out: Path, quiet: bool = False
) -> None:
    """Move ``identities`` from ``keyring`` to a new folder ``out`` for host ``to``, with a link.

    ``out`` gets the identities' keys and ``<this_host>.link`` (this host signs as every identity
    the other does not run); ``keyring`` gets ``<to>.link`` (the other host signs as exactly
    ``identities``) and loses those identities' keys: from now on they run on the other host."""
    check_id_name("host", to)
    check_id_name("host", this_host)
    ring = Keyring.load(keyring)
    for ident in identities:
        if ident not in ring.keys:
            raise ConfigError(f"no key for {ident!r} in {ring.path}; known: {', '.join(ring.identities())}")
    if to in ring.links:
        raise ConfigError(
            f"{ring.path} already has a link to host {to!r} ({', '.join(ring.links[to].claims)}); "
            f"remove {to}{LINK_SUFFIX} to make a new one"
        )
    if out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out} exists and is not empty: export into a new folder")
    to_them, to_us = secrets.token_bytes(KEY_BYTES), secrets.token_bytes(KEY_BYTES)
    init_keyring(out)
    for ident in identities:
        write_key(out, ident, ring.keys[ident])
    write_private(out, f"{this_host}{LINK_SUFFIX}", Link(this_host, ("*",), to_us, to_them).to_json())
    write_private(ring.path, f"{to}{LINK_SUFFIX}", Link(to, tuple(identities), to_them, to_us).to_json())
    for ident in identities:
        (ring.path / f"{ident}{KEY_SUFFIX}").unlink()
    if quiet:
        return
    print(
        f"moved {', '.join(identities)} to {out} for host {to!r} (copy it there securely, then delete it); "
        f"{ring.path} verifies them through the link {to}{LINK_SUFFIX}"
    )
