"""The import rules of the package layout (docs/architecture.md, "Layout"), checked on the source.

Every ``import`` statement under ``shared/`` and ``services/`` is read with :mod:`ast` — at module
level, inside functions and under ``if TYPE_CHECKING:`` alike — and checked against the rooms:

* ``shared/`` (``telesurg.shared``), the runtime library: imports only ``shared``.
* ``services/common.py``, the service chassis (and ``services/__init__.py``): imports only ``shared``.
* a **service** — every package under ``services/`` that is not a tool, the launcher included
  (it starts services as ``python -m telesurg.services.cli <command>`` processes, never imports
  them): imports ``shared``, ``services/common.py`` and its own package, nothing else under
  ``services/``.
* a **tool** — ``services/cli.py`` and ``services/record/replay.py``, ``export.py``: may import
  any service (tools drive and compose services); only tools import tools. (The benchmarks,
  experiments and emulators live beside the runtime in ``tools/``: tests/test_tools_layout.py.)
* nothing under ``shared/`` or ``services/`` imports the tests.
* no import cycle between modules. A lazy import (inside a function) counts — it only hides the
  loop until the function runs; an ``if TYPE_CHECKING:`` import does not (it never runs).
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("shared", "services")
SHARED = "telesurg.shared"
SERVICES = "telesurg.services"
COMMON = "telesurg.services.common"
MAPPING = "telesurg.services.mapping"
#: modules and packages that drive or compose services (a package name covers its submodules)
TOOLS = (
    "telesurg.services.cli",
    "telesurg.services.record.replay",
    "telesurg.services.record.export",
)
#: top-level names the test tree can be imported as (``tests``, or a file of it on ``sys.path``)
TEST_NAMES = frozenset({"tests"} | {p.stem for p in (ROOT / "tests").glob("*.py")})

# Violations that remain, each named with what removes it (none today; the tests below fail on an
# entry that no longer occurs): (importer, imported) for a rule, the sorted modules of a cycle.
ALLOWED_RULE_VIOLATIONS: frozenset[tuple[str, str]] = frozenset()
ALLOWED_CYCLES: frozenset[tuple[str, ...]] = frozenset()


@dataclass(frozen=True)
class Import:
    """One imported module: the importer, the most specific module named, and the line."""

    importer: str
    imported: str
    line: int
    runtime: bool = True  # False under ``if TYPE_CHECKING:``

    def __str__(self) -> str:
        return f"{self.importer} imports {self.imported} (line {self.line})"


def source_modules() -> dict[str, Path]:
    """Installed module name (``telesurg.…``) → file, for every module under the folders."""
    out: dict[str, Path] = {}
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(("telesurg", *parts))] = path
    return out


MODULES = source_modules()


def _resolve(name: str) -> str:
    """The longest prefix of ``name`` that is one of our modules (``name`` itself if none)."""
    probe = name
    while probe and probe not in MODULES:
        probe = probe.rpartition(".")[0]
    return probe or name


def _type_checking_only(tree: ast.AST) -> set[ast.AST]:
    """The import nodes inside ``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``) blocks."""
    out: set[ast.AST] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If):
            test = node.test
            name = test.id if isinstance(test, ast.Name) else getattr(test, "attr", "")
            if name == "TYPE_CHECKING":
                out |= {n for stmt in node.body for n in ast.walk(stmt)}
    return out


def imports_of(module: str, path: Path) -> Iterator[Import]:
    """Every module ``module`` imports: ``import a.b`` → a.b; ``from a import b`` → a.b if that
    is a module, else a; relative imports resolved against the package."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    typing_only = _type_checking_only(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield Import(module, _resolve(alias.name), node.lineno, node not in typing_only)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            for alias in node.names:
                name = _resolve(f"{base}.{alias.name}")
                yield Import(module, name if name in MODULES else base, node.lineno, node not in typing_only)


ALL_IMPORTS = [imp for mod, path in MODULES.items() for imp in imports_of(mod, path)]


def within(module: str, package: str) -> bool:
    """``module`` is ``package`` or inside it."""
    return module == package or module.startswith(package + ".")


def is_tool(module: str) -> bool:
    """``module`` is a tool (or inside one)."""
    return any(within(module, t) for t in TOOLS)


def service_of(module: str) -> str:
    """The service package (``telesurg.services.<name>``) ``module`` belongs to."""
    return ".".join(module.split(".")[:3])


def rule_broken(imp: Import) -> str | None:
    """Why ``imp`` breaks a layout rule, or None if it keeps them."""
    a, b = imp.importer, imp.imported
    if b.split(".")[0] in TEST_NAMES:
        return "production code imports the tests"
    if not within(b, "telesurg"):
        return None  # stdlib or a third-party library
    if within(a, SHARED):
        return None if within(b, SHARED) else "shared imports only shared"
    if within(b, SHARED):
        return None
    if is_tool(a):
        return None
    if is_tool(b):
        return "only tools import tools"
    if a in (COMMON, SERVICES):
        return "services/common.py and services/__init__.py import only shared"
    if b in (COMMON, SERVICES) or within(b, service_of(a)):
        return None
    return "a service imports only shared, services/common.py and its own package"


def test_the_source_tree_is_read() -> None:
    """The checks below see the real tree (guards against a wrong ROOT or a vacuous walk)."""
    assert {"telesurg.shared.messages", "telesurg.services.mapping", "telesurg.services.cli"} <= set(MODULES)
    assert Import("telesurg.services.mapping", "telesurg.shared.messages", 0).imported in {
        i.imported for i in ALL_IMPORTS if i.importer == "telesurg.services.mapping"
    }
    assert any(is_tool(m) for m in MODULES) and any(within(m, SHARED) for m in MODULES)
    for tool in TOOLS:
        assert tool in MODULES, f"{tool} listed as a tool but not in the tree"


def test_imports_are_read_as_python_runs_them(tmp_path: Path) -> None:
    """Module-level, lazy, relative and ``TYPE_CHECKING`` imports, each resolved to our module."""
    (tmp_path / "__init__.py").write_text(
        "from typing import TYPE_CHECKING\n"
        "import telesurg.shared.bus\n"
        "from telesurg.shared.robots.mh3f import kinematics, HERE\n"
        "from . import engage\n"
        "from .position import PositionMapping\n"
        "if TYPE_CHECKING:\n"
        "    from telesurg.services.slave_control import SlaveControlConfig\n"
        "def f() -> None:\n"
        "    from telesurg.services.mirror.view import RerunView\n"
    )
    got = [(i.imported, i.runtime) for i in imports_of(MAPPING, tmp_path / "__init__.py")]
    assert got == [
        ("typing", True),
        ("telesurg.shared.bus", True),
        ("telesurg.shared.robots.mh3f.kinematics", True),
        ("telesurg.shared.robots.mh3f", True),
        (f"{MAPPING}.engage", True),
        (f"{MAPPING}.position", True),
        ("telesurg.services.slave_control", False),
        ("telesurg.services.mirror.view", True),
    ]


def test_the_rules_catch_what_they_forbid() -> None:
    """Each rule rejects a made-up import of the kind it forbids, and allows the kinds it allows."""
    bad = [
        ("telesurg.shared.bus", "telesurg.services.common"),
        ("telesurg.services.watchdog", "telesurg.services.mapping"),
        ("telesurg.services.mapping.position", "telesurg.services.slave_control.control"),
        ("telesurg.services.launcher", "telesurg.services.mirror.view"),
        ("telesurg.services.common", "telesurg.services.mapping"),
        ("telesurg.services", "telesurg.services.watchdog"),
        ("telesurg.services.slave_control", "telesurg.services.bench.harness"),
        ("telesurg.services.record", "telesurg.services.record.replay"),
        ("telesurg.services.record.replay", "conftest"),
        ("telesurg.shared.messages", "tests.helpers"),
    ]
    good = [
        ("telesurg.shared.bus", "telesurg.shared.messages"),
        ("telesurg.services.watchdog", "telesurg.services.watchdog.logic"),
        ("telesurg.services.mapping.position", "telesurg.services.mapping.engage"),
        ("telesurg.services.mirror", "telesurg.services.common"),
        ("telesurg.services.record.replay", "telesurg.services.mirror.view"),
        ("telesurg.services.cli", "importlib"),
    ]
    for a, b in bad:
        assert rule_broken(Import(a, b, 0)), (a, b)
    for a, b in good:
        assert rule_broken(Import(a, b, 0)) is None, (a, b)


def test_imports_keep_the_rooms() -> None:
    """No import under shared/ or services/ breaks a rule (beyond the named allow-list)."""
    broken = {(i.importer, i.imported): f"{i}: {why}" for i in ALL_IMPORTS if (why := rule_broken(i))}
    unexpected = sorted(msg for pair, msg in broken.items() if pair not in ALLOWED_RULE_VIOLATIONS)
    assert not unexpected, "\n".join(unexpected)
    stale = ALLOWED_RULE_VIOLATIONS - set(broken)
    assert not stale, f"allow-list entries that no longer occur (delete them): {sorted(stale)}"


def cycles(edges: dict[str, set[str]]) -> list[tuple[str, ...]]:
    """The strongly connected components with more than one module (or a self-import), each
    sorted (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[tuple[str, ...]] = []
    for root in sorted(edges):
        if root in index:
            continue
        work: list[tuple[str, Iterator[str]]] = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp: list[str] = []
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    comp.append(top)
                    if top == node:
                        break
                if len(comp) > 1 or node in edges.get(node, ()):
                    out.append(tuple(sorted(comp)))
    return sorted(out)


def test_the_cycle_check_finds_cycles() -> None:
    """A three-module loop and a self-import are found; a diamond is not a cycle."""
    loop = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"d"}, "e": {"f", "g"}, "f": {"h"}, "g": {"h"}}
    assert cycles(loop) == [("a", "b", "c"), ("d",)]


def test_no_import_cycles() -> None:
    """No module imports itself through others at run time (lazy imports included)."""
    runtime = [i for i in ALL_IMPORTS if i.runtime and i.imported in MODULES]
    edges: dict[str, set[str]] = {m: set() for m in MODULES}
    for i in runtime:
        if i.imported != i.importer:
            edges[i.importer].add(i.imported)
    found = cycles(edges)
    unexpected = [c for c in found if c not in ALLOWED_CYCLES]
    lines = []
    for c in unexpected:
        inside = sorted({str(i) for i in runtime if i.importer in c and i.imported in c})
        lines.append(" ↔ ".join(c) + ": " + "; ".join(inside))
    assert not unexpected, "\n".join(lines)
    stale = ALLOWED_CYCLES - set(found)
    assert not stale, f"allow-list cycles that no longer occur (delete them): {sorted(stale)}"


# --------------------------------------------------------------------------- robots by registry only

#: Fields whose values share a word with the registry without naming a robot: the trocar arm's
#: ``control_mode`` ``trocar`` (an operating-state value), an event's ``kind`` ``vip``, the console's
#: jog ``frame`` ``joint``. A comparison with one of these on the other side is not a robot branch.
NOT_ROBOT_FIELDS = frozenset({"control_mode", "kind", "jog_frame", "frame"})


def registry_words() -> frozenset[str]:
    """Every robot name, mapping mode and slave family the registry knows (built-ins)."""
    from telesurg.shared import robots

    words = set(robots.names()) | set(robots.SLAVE_FAMILIES)
    for name in robots.names():
        words |= set(robots.get(name).mapping_modes)
    return frozenset(words)


def _last_name(node: ast.expr) -> str:
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Subscript):
        return _last_name(node.value)
    return ""


def _strings(node: ast.expr) -> list[str]:
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value]
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return [s for e in node.elts for s in _strings(e)]
    return []


def name_comparisons(tree: ast.AST, words: frozenset[str]) -> list[tuple[int, str]]:
    """(line, word) of every ``if``/``elif``/conditional/``match`` that compares against a word."""
    out: list[tuple[int, str]] = []
    tests: list[ast.expr] = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.If, ast.IfExp, ast.While)):
            tests.append(node.test)
        elif isinstance(node, ast.Match):
            for case in node.cases:
                for sub in ast.walk(case.pattern):
                    if isinstance(sub, ast.MatchValue):
                        out += [(node.lineno, s) for s in _strings(sub.value) if s in words]
    for test in tests:
        for cmp in (n for n in ast.walk(test) if isinstance(n, ast.Compare)):
            sides = [cmp.left, *cmp.comparators]
            if any(_last_name(s) in NOT_ROBOT_FIELDS for s in sides):
                continue
            out += [(cmp.lineno, w) for s in sides for w in _strings(s) if w in words]
    return out


def test_no_service_compares_a_robot_mode_or_family_name() -> None:
    """Services find robots through the registry: no branch on a robot, mapping mode or family."""
    words = registry_words()
    assert {"mh3f", "plas", "vip", "cartesian", "all_joints", "trocar"} <= words
    runtime = {m: p for m, p in MODULES.items() if within(m, SERVICES) and not is_tool(m)}
    found = [
        f"{path.relative_to(ROOT)}:{line}: compares against {word!r}"
        for path in sorted(runtime.values())
        for line, word in name_comparisons(ast.parse(path.read_text()), words)
    ]
    assert found == []


def test_the_name_check_catches_what_it_forbids() -> None:
    words = frozenset({"mh3f", "trocar", "cartesian"})
    src = (
        "if cfg.mode == 'cartesian': pass\n"
        "elif spec.slave_family in ('trocar', 'joint'): pass\n"
        "x = 1 if model != 'mh3f' else 2\n"
        "match cfg.model:\n    case 'mh3f': pass\n"
        "if st.control_mode == 'trocar': pass\n"  # a message field's value: allowed
        "if cfg.backend == 'mujoco': pass\n"  # not a registry word
    )
    assert sorted(w for _, w in name_comparisons(ast.parse(src), words)) == [
        "cartesian",
        "mh3f",
        "mh3f",
        "trocar",
    ]


def _top_imports(folder: str) -> list[tuple[str, str]]:
    """(file, imported top-level package under telesurg or the test tree) for every import."""
    out = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            for n in names:
                parts = n.split(".")
                top = parts[1] if parts[0] == "telesurg" and len(parts) > 1 else parts[0]
                out.append((str(path.relative_to(ROOT)), top))
    return out


def test_runtime_floors_import_only_downward() -> None:
    """shared imports nothing from services, tools or tests; services nothing from tools or tests
    (tools/ may not exist yet: the check holds either way)."""
    tests = TEST_NAMES
    bad = [f"{f} imports {t}" for f, t in _top_imports("shared") if t in {"services", "tools"} | tests]
    bad += [f"{f} imports {t}" for f, t in _top_imports("services") if t in {"tools"} | tests]
    assert bad == []
