"""``telesurg site``: the site files shipped with the package.

``telesurg site init DIR`` writes the packaged site folders (``local``, ``plas``, ``vip``,
``serial``, ``slave-site`` with its ``acl.json5``, ``console``: one ``site.toml`` each) and the
deploy scripts (``local.sh``, ``slave-site.sh``, ``console.sh``) into DIR, to edit and run:
``telesurg up --config-dir DIR/plas``. An existing file is left alone unless ``--force``.
``telesurg site check FILE`` builds every service's config from a site file and reports the first
error (file, table, key), as ``telesurg up`` does before it starts anything.

Examples::

    telesurg site init mysites && telesurg up --config-dir mysites/local
    telesurg site check mysites/plas/site.toml
"""

from __future__ import annotations

import argparse
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

from telesurg.services.launcher import CONFIG_CLASSES, check_site, deploy_dir
from telesurg.shared.config import read_site
from telesurg.shared.errors import ConfigError

#: what ``init`` copies: the site folders' files and the scripts (not the package's __init__.py)
PATTERNS = ("*/site.toml", "*/*.json5", "*.sh")


def packaged_files() -> list[Path]:
    """The packaged site files and scripts, relative to the ``telesurg.deploy`` folder."""
    root = deploy_dir()
    return sorted({p.relative_to(root) for pat in PATTERNS for p in root.glob(pat) if p.is_file()})


def init(dest: Path, force: bool = False) -> list[Path]:
    """Copy the packaged site folders and scripts into ``dest``; the files written."""
    root = deploy_dir()
    written = []
    for rel in packaged_files():
        out = dest / rel
        if out.exists() and not force:
            continue
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(root / rel, out)  # keeps the scripts' execute bits
        written.append(out)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg site``."""
    parser = argparse.ArgumentParser(
        prog="telesurg site", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="cmd", required=True)
    p_init = sub.add_parser("init", help="write the packaged site folders and deploy scripts into DIR")
    p_init.add_argument("dir", type=Path, metavar="DIR")
    p_init.add_argument("--force", action="store_true", help="overwrite files that exist")
    p_check = sub.add_parser("check", help="build every service's config from a site file")
    p_check.add_argument("file", type=Path, metavar="FILE")
    args = parser.parse_args(argv)
    if args.cmd == "init":
        try:
            written = init(args.dir, args.force)
        except (ConfigError, OSError) as exc:
            print(f"telesurg site init: {exc}", file=sys.stderr)
            return 1
        kept = len(packaged_files()) - len(written)
        for p in written:
            print(p)
        if kept:
            print(f"telesurg site init: kept {kept} file(s) that exist (--force overwrites)", file=sys.stderr)
        return 0
    try:
        site = read_site(args.file)
        check_site(args.file, list(CONFIG_CLASSES), {})
    except ConfigError as exc:
        print(f"telesurg site check: {exc}", file=sys.stderr)
        return 2
    print(f"{args.file}: ok ({', '.join(sorted(site.tables)) or 'no service tables'})")
    return 0
