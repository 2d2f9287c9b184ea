"""Every ``telesurg …`` command line in README.md and docs/ is one the real CLI accepts.

The fenced code blocks of README.md and ``docs/**/*.md`` are read; every command in them that
starts ``telesurg``, ``.venv/bin/telesurg`` or ``python -m telesurg.services…`` (after ``&&``,
``;`` or ``|`` too, continuation lines joined, comments dropped) is handed to the subcommand's
own ``main`` with its ``argparse`` stopped right after parsing: an unknown command, subcommand
or flag, a missing argument or a bad choice fails the test with the file and line. ``[--flag]``
is an optional part: both forms are checked. A repository path given to ``--config``,
``--config-dir``, ``--plugin`` or ``--attach`` must exist.

One line is also run as written: ``telesurg record --out run.mcap --seconds 5`` against a local
site started by ``telesurg up`` on the default port 127.0.0.1:7447 — inside a private network
namespace (``unshare --net``, as root) so that other sites on this machine do not matter, or on
the host's loopback when its port 7447 is free.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from telesurg.services.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^(\s*)(```+|~~~+)(.*)$")
SEPARATORS = {"&&", "||", ";", "|", "&"}
PATH_FLAGS = {"--config", "--config-dir", "--plugin", "--attach"}
REPO_DIRS = ("deploy/", "tests/", "docs/", "services/", "shared/", "tools/", "firmware/")


@dataclass(frozen=True)
class DocCommand:
    """One documented command: where it is, and its arguments after ``telesurg``."""

    where: str  # file:line
    command: str  # the subcommand (``record``), or a module for ``python -m``
    args: tuple[str, ...]
    text: str

    def __str__(self) -> str:
        return f"{self.where}: {self.text}"


def _blocks(path: Path) -> Iterator[list[tuple[int, str]]]:
    """The fenced code blocks of a file: (line number, line) of each line inside one. In a block
    that shows a shell session (``$ command`` lines), only those lines, without the ``$ ``."""
    fence, block = "", []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        m = FENCE.match(line)
        if m and not fence:
            fence, block = m.group(2), []
            continue
        if m and fence and m.group(2).startswith(fence[0]) and not m.group(3).strip():
            fence = ""
            if any(t.lstrip().startswith("$ ") for _, t in block):
                block = [(k, t.lstrip()[2:]) for k, t in block if t.lstrip().startswith("$ ")]
            yield block
            continue
        if fence:
            block.append((n, line))


def _lines(block: list[tuple[int, str]]) -> Iterator[tuple[int, str]]:
    """A block's lines with ``\\`` continuations joined (numbered by their first line)."""
    pending, start = "", 0
    for n, line in block:
        if not pending:
            start = n
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        yield start, pending + line
        pending = ""
    if pending:
        yield start, pending


def _segments(tokens: list[str]) -> Iterator[list[str]]:
    seg: list[str] = []
    for t in tokens:
        if t in SEPARATORS:
            if seg:
                yield seg
            seg = []
        else:
            seg.append(t)
    if seg:
        yield seg


def documented_commands() -> list[DocCommand]:
    """Every telesurg command line of the docs' code blocks."""
    out: list[DocCommand] = []
    assign = re.compile(r"([A-Z_][A-Z0-9_]*)=(.*)", re.S)
    for path in DOCS:
        rel = path.relative_to(ROOT)
        for block in _blocks(path):
            env: dict[str, list[str]] = {}  # VAR="…" lines of the block: $VAR expands to its words
            for n, line in _lines(block):
                try:
                    tokens = shlex.split(line, comments=True)
                except ValueError:  # not shell (e.g. a Python or JSON line that names telesurg)
                    continue
                for seg in _segments(tokens):
                    while seg and (m := assign.fullmatch(seg[0])):
                        if len(seg) == 1:
                            env[m.group(1)] = m.group(2).split()
                        seg = seg[1:]
                    seg = [w for t in seg for w in (env.get(t[1:], [t]) if t.startswith("$") else [t])]
                    if not seg:
                        continue
                    head = seg[0]
                    if (head == "telesurg" or head.endswith("/telesurg")) and len(seg) > 1:
                        out.append(DocCommand(f"{rel}:{n}", seg[1], tuple(seg[2:]), " ".join(seg)))
                    elif Path(head).name.startswith("python") and seg[1:2] == ["-m"] and _ours(seg[2:3]):
                        out.append(DocCommand(f"{rel}:{n}", seg[2], tuple(seg[3:]), " ".join(seg)))
    return out


def _ours(module: list[str]) -> bool:
    return bool(module) and module[0].startswith("telesurg.")


def _variants(args: tuple[str, ...]) -> list[tuple[str, ...]]:
    """``[--reset]`` is optional: the line without it and with it."""
    variants: list[tuple[str, ...]] = [()]
    for a in args:
        if a.startswith("[") and a.endswith("]") and len(a) > 2:
            inner = a[1:-1].split()
            variants = [v for base in variants for v in (base, (*base, *inner))]
        else:
            variants = [(*v, a) for v in variants]
    return variants


class _Parsed(Exception):
    """Raised by the patched ``parse_args``: the command line parsed, nothing ran."""


def parse_only(module_name: str, args: tuple[str, ...]) -> str | None:
    """Hand ``args`` to the module's ``main`` and stop once argparse accepted them.

    Returns None if they parse (or ``--help`` printed), else argparse's error text."""
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(self: argparse.ArgumentParser, *a: Any, **k: Any) -> Any:
        ns = original(self, *a, **k)
        raise _Parsed(ns)

    module = importlib.import_module(module_name)
    err = io.StringIO()
    argparse.ArgumentParser.parse_args = parse_then_stop  # type: ignore[method-assign]
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            module.main(list(args))
    except _Parsed:
        return None
    except SystemExit as e:
        return None if e.code in (0, None) else (err.getvalue().strip() or f"exit {e.code}")
    finally:
        argparse.ArgumentParser.parse_args = original  # type: ignore[method-assign]
    return "main() returned without parsing its arguments with argparse"


COMMANDS_IN_DOCS = documented_commands()


def test_the_docs_have_command_lines() -> None:
    """The extraction finds the README's own lines (a broken extractor would check nothing)."""
    texts = {c.text for c in COMMANDS_IN_DOCS}
    assert len(COMMANDS_IN_DOCS) > 50, len(COMMANDS_IN_DOCS)
    assert ".venv/bin/telesurg record --out run.mcap --seconds 60" in texts
    assert ".venv/bin/telesurg estop [--reset]" in texts


def test_a_wrong_command_line_is_caught() -> None:
    assert parse_only("telesurg.services.record", ("--out", "x.mcap", "--seconds", "5")) is None
    assert "unrecognized arguments: --frobnicate" in (
        parse_only("telesurg.services.record", ("--out", "x.mcap", "--frobnicate")) or ""
    )
    assert "required" in (parse_only("telesurg.services.record", ("--seconds", "5")) or "")
    assert parse_only("telesurg.services.record.export", ("a.mcap", "--to", "foxglove", "b.mcap")) is None
    assert "invalid choice" in (
        parse_only("telesurg.services.record.export", ("a", "--to", "ros1", "b")) or ""
    )


@pytest.mark.parametrize("cmd", COMMANDS_IN_DOCS, ids=lambda c: c.where)
def test_every_documented_command_parses(cmd: DocCommand) -> None:
    if cmd.command.startswith("telesurg."):
        module = cmd.command
        assert importlib.util.find_spec(module) is not None, f"{cmd}: no module {module}"
        if cmd.args in ((), ("...",)):
            return
    else:
        assert cmd.command in COMMANDS, f"{cmd}: no command {cmd.command!r} (telesurg --help lists them)"
        module = COMMANDS[cmd.command][0]
    if "..." in cmd.args:
        pytest.skip(f"{cmd}: an elided command line")
    for args in _variants(cmd.args):
        problem = parse_only(module, args)
        assert problem is None, f"{cmd}\n  telesurg {cmd.command} {' '.join(args)}: {problem}"
    for flag, value in zip(cmd.args, cmd.args[1:], strict=False):
        if flag in PATH_FLAGS and value.startswith(REPO_DIRS):
            assert (ROOT / value).exists(), f"{cmd}: {value} does not exist"


# --------------------------------------------------------------------------- run as written


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


RECORD_LINE = "telesurg record --out run.mcap --seconds 5"
SCRIPT = f"""
set -e
ip link set lo up 2>/dev/null || true
cd "$WORK"
"$BIN/telesurg" up --seconds 45 --log-dir logs > up.log 2>&1 &
UP=$!
for i in $(seq 150); do
  (echo > /dev/tcp/127.0.0.1/7447) 2>/dev/null && break
  sleep 0.2
done
sleep 4
set +e
{RECORD_LINE} > record.log 2>&1
echo "record exit $?"
kill -INT $UP
wait $UP
"""


@pytest.mark.timeout(240)
@pytest.mark.process
def test_the_record_line_works_as_written(tmp_path: Path) -> None:
    """``telesurg record --out run.mcap --seconds 5`` (no ``--connect``) records the local site."""
    from mcap.reader import make_reader
    from telesurg.services.record import read_summary

    assert any(c.text.endswith("telesurg record --out run.mcap --seconds 60") for c in COMMANDS_IN_DOCS)
    bin_dir = Path(sys.executable).parent
    env = dict(os.environ, WORK=str(tmp_path), BIN=str(bin_dir), PATH=f"{bin_dir}:{os.environ['PATH']}")
    if os.geteuid() == 0 and shutil.which("unshare") and shutil.which("ip"):
        argv = ["unshare", "--net", "bash", "-c", SCRIPT]  # a loopback of its own: 7447 is free
    elif _port_free(7447):
        argv = ["bash", "-c", SCRIPT]
    else:
        pytest.skip("127.0.0.1:7447 is taken and no private network namespace (needs root + unshare)")
    r = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=200)
    record_log = (tmp_path / "record.log").read_text() if (tmp_path / "record.log").exists() else ""
    assert "record exit 0" in r.stdout, f"{r.stdout}\n{r.stderr}\n{record_log[-3000:]}"
    with (tmp_path / "run.mcap").open("rb") as f:
        summary = read_summary(make_reader(f))
    js = summary["slave/arm1/measured_js"]
    print(f"{RECORD_LINE}: {js['messages']} measured_js at {js['rate_hz']} Hz, {len(summary)} keys")
    # five seconds of the site's streams through its router: the slave's joints, the leases
    assert js["messages"] > 250, sorted(summary)
    assert summary["safety/arm1/lease"]["messages"] > 50
