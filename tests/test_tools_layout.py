"""Tools beside the runtime: ``tools/`` (benchmarks, experiments, device emulators) depends on the
runtime (``shared/``, ``services/``), never the other way round, and the runtime runs without the
tools' heavy dependencies (the ``lab`` extra: matplotlib, psutil, mink, …).

* Every ``import`` under shared/ and services/ (module level, lazy, ``TYPE_CHECKING``, relative)
  is read with :mod:`ast`: none names ``telesurg.tools`` or the tests. The runtime reaches a tool
  only by name, through the CLI's command table (``services/cli.py``): no other runtime file
  even spells ``telesurg.tools``.
* Every import under tools/ names the standard library, a third-party package, the runtime or
  ``telesurg.tools`` itself, never the tests.
* In a fresh interpreter where the lab extra's packages cannot be imported (a ``sys.meta_path``
  blocker), every runtime module imports, and ``telesurg bench`` / ``telesurg experiment`` say in
  one line what to install.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import textwrap
import tomllib
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ("shared", "services")
#: top-level names the test tree can be imported as (``tests``, or one of its files on sys.path)
TEST_NAMES = frozenset({"tests"} | {p.stem for p in (ROOT / "tests").glob("*.py")})
#: the one runtime file that names the tools: the CLI's command table
COMMAND_TABLE = ROOT / "services" / "cli.py"


def modules(*folders: str) -> dict[str, Path]:
    """``telesurg.<folder>.…`` → file, for every module under ``folders``."""
    out: dict[str, Path] = {}
    for folder in folders:
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(("telesurg", *(parts[:-1] if parts[-1] == "__init__" else parts)))] = path
    return out


def imports(module: str, path: Path) -> Iterator[tuple[str, int]]:
    """(imported module, line) for every import statement of ``module``, relative ones resolved
    against its package (``from ..x import y`` → ``<parent>.x.y``)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield from ((a.name, node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            yield from ((f"{base}.{a.name}", node.lineno) for a in node.names)


def within(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def test_imports_are_resolved(tmp_path: Path) -> None:
    """The reader sees absolute, relative, lazy and TYPE_CHECKING imports (no vacuous walk)."""
    src = tmp_path / "__init__.py"
    src.write_text(
        "from typing import TYPE_CHECKING\nimport telesurg.shared.bus\nfrom ... import tools\n"
        "from ...tools.bench import harness\nif TYPE_CHECKING:\n    import helpers\n"
        "def f() -> None:\n    from telesurg.tools.emulate import emulator\n"
    )
    got = [name for name, _ in imports("telesurg.services.x", src)]
    assert got == [
        "typing.TYPE_CHECKING",
        "telesurg.shared.bus",
        "telesurg.tools",
        "telesurg.tools.bench.harness",
        "helpers",
        "telesurg.tools.emulate.emulator",
    ]
    assert {"telesurg.shared.bus", "telesurg.services.launcher", "telesurg.tools.bench.harness"} <= set(
        modules("shared", "services", "tools")
    )


def test_the_runtime_never_imports_tools_or_tests() -> None:
    bad = [
        f"{path.relative_to(ROOT)}:{line} imports {name}"
        for module, path in modules(*RUNTIME).items()
        for name, line in imports(module, path)
        if within(name, "telesurg.tools")
        or within(name, "telesurg.gym")  # (the environments build on the runtime, not under it)
        or name.split(".")[0] in TEST_NAMES | {"tools", "gymnasium"}
    ]
    assert not bad, "\n".join(bad)


def test_the_runtime_names_tools_only_in_the_command_table() -> None:
    """No ``importlib`` detour: outside the command table no runtime file spells a tool's module."""
    bad = [
        str(path.relative_to(ROOT))
        for path in modules(*RUNTIME).values()
        if path != COMMAND_TABLE and "telesurg.tools" in path.read_text()
    ]
    assert not bad, bad
    from telesurg.services.cli import COMMANDS

    tools = {name for name, (module, _) in COMMANDS.items() if within(module, "telesurg.tools")}
    assert {"bench", "experiment", "device", "impair"} <= tools


def test_tools_import_only_downward() -> None:
    bad = [
        f"{path.relative_to(ROOT)}:{line} imports {name}"
        for module, path in modules("tools").items()
        for name, line in imports(module, path)
        if name.split(".")[0] in TEST_NAMES
        or (within(name, "telesurg") and not any(within(name, f"telesurg.{f}") for f in (*RUNTIME, "tools")))
    ]
    assert not bad, "\n".join(bad)


def lab_packages() -> list[str]:
    """The import names of the ``lab`` extra's packages (pyproject.toml)."""
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    return [req.split("==")[0].split("[")[0].strip().replace("-", "_") for req in extras["lab"]]


def test_the_runtime_imports_without_the_lab_extra(tmp_path: Path) -> None:
    """Every runtime module imports with the lab extra's packages unimportable, and the tools
    that need them say what to install (exit 2, one line)."""
    blocked = [*lab_packages(), "gymnasium"]  # (and the learn extra's environments)
    assert {"matplotlib", "psutil"} <= set(blocked)
    runtime = [m for m, p in modules(*RUNTIME).items() if p.name != "__main__.py"]
    code = textwrap.dedent(
        f"""
        import contextlib, importlib, io, json, sys
        BLOCKED = {blocked!r}
        class Blocker:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED:
                    raise ModuleNotFoundError(f"No module named {{name!r}} (blocked)", name=name)
                return None
        sys.meta_path.insert(0, Blocker())
        failed = {{}}
        for m in {runtime!r}:
            try:
                importlib.import_module(m)
            except Exception as exc:
                failed[m] = f"{{type(exc).__name__}}: {{exc}}"
        from telesurg.services.cli import main
        err, codes = io.StringIO(), {{}}
        for cmd in (["bench", "faults"], ["experiment", "jang-vip", "--out", "x"]):
            with contextlib.redirect_stderr(err):
                codes[cmd[0]] = main(cmd)
        leaked = sorted(n for n in sys.modules if n.split(".")[0] in BLOCKED or "telesurg.tools" in n)
        out = {{"failed": failed, "codes": codes, "stderr": err.getvalue(), "leaked": leaked}}
        print(json.dumps(out))
        """
    )
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=240
    )
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["failed"] == {}, out["failed"]
    assert out["codes"] == {"bench": 2, "experiment": 2}
    lines = out["stderr"].strip().splitlines()
    assert len(lines) == 2, lines
    for line, cmd in zip(lines, ("bench", "experiment"), strict=True):
        assert (
            line.startswith(f"telesurg {cmd} needs the 'lab' extra (")
            and "pip install 'telesurg[lab]'" in line
        )
        assert all(p in line for p in ("matplotlib", "psutil")), line
    assert out["leaked"] == [] and list(tmp_path.iterdir()) == []
