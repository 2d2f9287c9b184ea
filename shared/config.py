"""Config loading: a site file (or a service's own TOML file) plus ``--set key=value`` overrides
into one dataclass per service; the ``--help`` text of every config key.

A **site file** (``deploy/<site>/site.toml``, docs/deploy.md) holds a ``[site]`` table with the
facts every service shares (:class:`SiteFacts`: the robot, the arm pairs, the workspace box, robot
plugins), stated once, and one table per service (``[mapping]``, ``[watchdog]``, …) holding only
what differs from that service's defaults. :func:`load_config` builds one service's config from
it: the service's table, plus each shared fact the config has a field for (``robot`` → ``model``,
``pairs`` → ``pairs`` / ``arms``, the workspace box); a table that restates a shared fact with
another value is an error. A file without a ``[site]`` table is one service's config on its own.

Rules: every key must be a field of the dataclass (an unknown key is an error naming the file, the
table and the nearest valid key); nested dataclasses are TOML tables; values are type-checked
against the annotations. Overrides use TOML syntax for the value (``--set rate_hz=250``,
``--set bus.connect='["tcp/..."]'``); a bare word is taken as a string (``--set arm=arm2``).

Each config field's help (``telesurg <service> --help``) is the comment beside or above it in the
dataclass's source (or its line in the class docstring's ``Attributes:``); a field right below
another with no comment of its own shares that one's (``workspace_min_mm`` / ``workspace_max_mm``).
The unit comes from the name (``_ms``, ``_hz``, ``_mm``, …) or a leading ``unit:`` in the comment.
"""

from __future__ import annotations

import ast
import copy
import dataclasses
import difflib
import inspect
import io
import json
import re
import textwrap
import tokenize
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from telesurg.shared.authority import AuthorityConfig
from telesurg.shared.errors import ConfigError
from telesurg.shared.service_table import SERVICES

T = TypeVar("T")

#: The site file's name inside a site folder (``deploy/<site>/site.toml``).
SITE_FILE = "site.toml"
#: The tables a site file may hold beside ``[site]``: one per service.
SERVICE_TABLES = tuple(s.name for s in SERVICES)
#: ``[site]`` fact → the service config fields it fills (in every config that has one).
SHARED_FACTS: dict[str, tuple[str, ...]] = {
    "robot": ("model",),
    "pairs": ("pairs", "arms"),
    "workspace_min_mm": ("workspace_min_mm",),
    "workspace_max_mm": ("workspace_max_mm",),
    "authority": ("authority",),
    "patient_box_min_mm": ("patient_box_min_mm",),
    "patient_box_max_mm": ("patient_box_max_mm",),
    "work_frame_rpy_deg": ("work_frame_rpy_deg",),
    "scene": ("scene",),
}


@dataclass
class SiteFacts:
    """The ``[site]`` table: facts stated once for every service of the site."""

    robot: str | None = None  # the slave robot (shared/robots.py): every service's `model`
    pairs: list[str] | None = None  # "master_arm:slave_arm" pairs: the mapping's, watchdog's, console's
    # mm, the slave's frame: the target / tip box of the mapping and the watchdog (unset: theirs)
    workspace_min_mm: tuple[float, float, float] | None = None
    workspace_max_mm: tuple[float, float, float] | None = None
    plugins: list[str] = field(default_factory=list)  # robot plugin files (paths relative to the site file)
    # [site.authority]: who may send which operator command, e-stop or reset, and the confirmation
    # of motion-starting commands (shared/authority.py; unset: the defaults, operator "console")
    authority: AuthorityConfig | None = None
    # mm, the slave's base frame: the patient's body of a trocar-family robot, the keep-out of
    # slave_control's slave-side motions and of the watchdog's check of them (unset: theirs)
    patient_box_min_mm: tuple[float, float, float] | None = None
    patient_box_max_mm: tuple[float, float, float] | None = None
    # deg, roll/pitch/yaw of the work frame (the laparoscope's view) in the slave's base frame:
    # slave_control's `work` jogs and the mapping's `master_frame = "work"` (unset: theirs)
    work_frame_rpy_deg: tuple[float, float, float] | None = None
    # MuJoCo: another scene of the robot, a scene_*.xml in its folder (e.g. the MH3F's
    # "scene_trocar_task.xml"): what slave_control simulates and the camera renders (unset: scene.xml)
    scene: str | None = None


@dataclass
class SiteFile:
    """A parsed site file: its path, the ``[site]`` facts and the raw service tables."""

    path: Path
    facts: SiteFacts
    tables: dict[str, dict[str, Any]]

    @property
    def plugins(self) -> list[Path]:
        """The ``[site] plugins`` files, resolved against the site file's folder."""
        return [(self.path.parent / p).resolve() for p in self.facts.plugins]


def _read_toml(path: Path, what: str) -> dict[str, Any]:
    try:
        return tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} {path} is a directory, not a file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{what} {path}: {exc}") from None


def is_site_data(data: dict[str, Any]) -> bool:
    """A parsed TOML file is a site file when it has a ``[site]`` table."""
    return isinstance(data.get("site"), dict)


def _site_from_data(path: Path, data: dict[str, Any]) -> SiteFile:
    for name, value in data.items():
        if name == "site":
            continue
        if name not in SERVICE_TABLES:
            raise ConfigError(f"{path}: unknown table [{name}]{_suggest(name, ('site', *SERVICE_TABLES))}")
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: {name} must be a table ([{name}]), got {value!r}")
    try:
        facts = from_dict(SiteFacts, data["site"])
    except ConfigError as exc:
        raise ConfigError(f"{path}: [site] {exc}") from None
    return SiteFile(path, facts, {k: v for k, v in data.items() if k != "site"})


def read_site(path: str | Path) -> SiteFile:
    """Parse and check a site file (tables, ``[site]`` facts); the service tables stay raw."""
    p = Path(path)
    data = _read_toml(p, "site file")
    if not is_site_data(data):
        raise ConfigError(f"{p}: not a site file (no [site] table)")
    return _site_from_data(p, data)


def site_plugins(path: str | Path | None) -> list[Path]:
    """The ``[site] plugins`` of a site file, resolved against its folder ([] for no file or a
    service's own TOML file): each service loads them before it builds its config."""
    if not path:
        return []
    p = Path(path)
    data = _read_toml(p, "config file")
    return _site_from_data(p, data).plugins if is_site_data(data) else []


def service_table(cls: type[Any]) -> str:
    """The site-file table of a service config: the default of its ``service`` field."""
    for f in dataclasses.fields(cls):
        if f.name == "service" and isinstance(f.default, str):
            return f.default
    raise ConfigError(f"{cls.__name__} has no service name: give the table")


def load_config(
    cls: type[T],
    path: str | Path | None = None,
    overrides: list[str] | None = None,
    table: str | None = None,
) -> T:
    """Build ``cls`` from an optional site file / TOML file and ``key=value`` overrides.

    A site file gives table ``table`` (default: the config's service name) with the ``[site]``
    facts merged in. Errors name the file (or the ``--set``), the table and the key.
    """
    data: dict[str, Any] = {}
    source, label = "", ""
    if path:
        p = Path(path)
        raw = _read_toml(p, "config file")
        source = str(p)
        if is_site_data(raw):
            site = _site_from_data(p, raw)
            table = table or service_table(cls)
            if table not in SERVICE_TABLES:
                raise ConfigError(f"{p}: no service table [{table}]{_suggest(table, SERVICE_TABLES)}")
            label = f"[{table}] "
            data = _with_facts(cls, site, table)
        else:
            data = raw
    elif table:
        label = f"[{table}] "
    if data:  # the file alone: its own errors name it
        _build(cls, data, source or "config", label)
    for item in overrides or []:
        key, sep, raw_value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"override {item!r} must look like key=value")
        parts = key.strip().split(".")
        value = _parse_value(raw_value.strip())
        try:
            _check_path(cls, parts, value)
            _set_path(data, parts, value)
        except ConfigError as exc:
            raise ConfigError(f"--set {item}: {label}{exc}") from None
    return _build(cls, data, source or "config", label)


def _build(cls: type[T], data: dict[str, Any], source: str, label: str) -> T:
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {label}{exc}") from None


def _with_facts(cls: type[Any], site: SiteFile, table: str) -> dict[str, Any]:
    """Table ``table`` of ``site`` with the shared facts filled into the fields ``cls`` has."""
    data: dict[str, Any] = copy.deepcopy(site.tables.get(table, {}))
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    for fact, targets in SHARED_FACTS.items():
        value = getattr(site.facts, fact)
        if value is None:
            continue
        for target in targets:
            if target not in names:
                continue
            if target in data:
                mine = _coerce(hints[target], data[target], target)
                shared = _coerce(hints[target], _plain(value), target)
                if mine != shared:
                    raise ConfigError(
                        f"{site.path}: [{table}] {target} = {_toml(data[target])} restates the shared "
                        f"fact [site] {fact} = {_toml(value)} differently (state it once, in [site])"
                    )
            data[target] = _plain(value)
    return data


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    return [_plain(v) for v in value] if isinstance(value, (list, tuple)) else value


def _parse_value(raw: str) -> Any:
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        return raw


def _set_path(d: dict[str, Any], parts: list[str], value: Any) -> None:
    for p in parts[:-1]:
        d = d.setdefault(p, {})
        if not isinstance(d, dict):
            raise ConfigError(f"override path {'.'.join(parts)!r} crosses a non-table value")
    d[parts[-1]] = value


def _check_path(cls: type[Any], parts: list[str], value: Any) -> None:
    """An override's key exists (else the nearest one is suggested) and its value has the type."""
    tp: Any = cls
    for i, name in enumerate(parts):
        where = ".".join(parts[: i + 1])
        if not (dataclasses.is_dataclass(tp) and isinstance(tp, type)):
            if typing.get_origin(tp) is dict:
                return  # a free-form table: its keys are data
            raise ConfigError(f"{'.'.join(parts[:i])} is not a table")
        fields = {f.name for f in dataclasses.fields(tp) if f.init}
        if name not in fields:
            prefix = ".".join(parts[:i])
            raise ConfigError(_unknown(name, fields, prefix))
        tp = typing.get_type_hints(tp)[name]
        if i == len(parts) - 1:
            _coerce(tp, value, where)


def _suggest(name: str, valid: typing.Iterable[str]) -> str:
    best = difflib.get_close_matches(name, list(valid), n=1, cutoff=0.6)
    return f" (did you mean {best[0]!r}?)" if best else ""


def _unknown(name: str, valid: set[str], prefix: str = "") -> str:
    dotted = f"{prefix}.{name}" if prefix else name
    hint = _suggest(name, valid)
    if hint:
        best = difflib.get_close_matches(name, list(valid), n=1, cutoff=0.6)[0]
        hint = f" (did you mean {(prefix + '.' if prefix else '') + best!r}?)"
    return f"unknown key {dotted!r}{hint}; valid: {', '.join(sorted(valid))}"


def from_dict(cls: type[T], data: dict[str, Any], where: str = "") -> T:
    """Build a dataclass from a dict, recursively, with type checks."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls} is not a dataclass")
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - fields)
    if unknown:
        raise ConfigError(_unknown(unknown[0], fields, where))
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints[name], value, f"{where}.{name}" if where else name)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where + ': ' if where else ''}{exc}") from None


def _coerce(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise ConfigError(f"{where} must be a table, got {value!r}")
        return from_dict(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        for a in args:
            try:
                return _coerce(a, value, where)
            except ConfigError:
                pass
        raise ConfigError(f"{where} must be {type_name(tp)}, got {value!r}")
    if tp is type(None):
        if value is not None:
            raise ConfigError(f"{where} must be empty")
        return None
    if origin in (list, tuple):
        if not isinstance(value, list):
            raise ConfigError(f"{where} must be an array ({type_name(tp)}), got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{where} must have {len(args)} elements ({type_name(tp)}), got {value!r}")
            return tuple(
                _coerce(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True))
            )
        inner = args[0] if args else Any
        items = [_coerce(inner, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where} must be a table, got {value!r}")
        return {str(k): _coerce(args[1], v, f"{where}.{k}") for k, v in value.items()}
    if tp is Any:
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported config type {tp}")


# -- help: every key with its type, default, unit and meaning, from the dataclass source ----------

#: name suffix → unit (longest first)
_SUFFIX_UNITS = (
    ("_mb_s", "MB/s"),
    ("_mm_s", "mm/s"),
    ("_deg_s", "deg/s"),
    ("_rad_s", "rad/s"),
    ("_rpy_deg", "deg"),
    ("_ms", "ms"),
    ("_hz", "Hz"),
    ("_mm", "mm"),
    ("_mb", "MB"),
    ("_rad", "rad"),
    ("_deg", "deg"),
    ("_nm", "N·m"),
    ("_s", "s"),
)
#: a leading "unit:" or "unit," in a field's comment
_COMMENT_UNIT = re.compile(r"^(ms|s|Hz|rad|m|mm|deg|mm/s|deg/s|rad/s|bit/s|counts)[,:]\s+")


@dataclass(frozen=True)
class FieldDoc:
    """What ``--help`` says of one config key."""

    key: str  # dotted key, e.g. scripted.radius
    type: str  # e.g. float, list[str], table
    default: str  # TOML text of the default
    unit: str  # "" when the value has none
    help: str  # the meaning (the field's comment)


def type_name(tp: Any) -> str:
    """A readable annotation: ``float``, ``list[str]``, ``tuple[float, float, float]``, ``table``."""
    if dataclasses.is_dataclass(tp):
        return "table"
    if isinstance(tp, type) and not typing.get_args(tp):
        return tp.__name__
    if tp is type(None):
        return "none"
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return " | ".join(type_name(a) for a in args)
    if origin is not None:
        inner = ", ".join("..." if a is Ellipsis else type_name(a) for a in args)
        return f"{getattr(origin, '__name__', str(origin))}[{inner}]"
    return str(tp).replace("typing.", "")


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"
    if value is None:
        return "(unset)"
    return repr(value)


_COMMENTS: dict[type[Any], dict[str, str]] = {}


def field_comments(cls: type[Any]) -> dict[str, str]:
    """Field name → its help text, from the comments in ``cls``'s source (see the module doc)."""
    if cls not in _COMMENTS:
        _COMMENTS[cls] = _read_comments(cls)
    return _COMMENTS[cls]


def _read_comments(cls: type[Any]) -> dict[str, str]:
    try:
        src = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    lines = src.splitlines()
    comments: dict[int, str] = {}  # line (1-based) → comment text
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            if text.startswith("--") and text.endswith("--"):  # a section header: "-- title --"
                text = text.strip("- ") + ":"
            comments[tok.start[0]] = text
    body = next(n for n in ast.parse(src).body if isinstance(n, ast.ClassDef)).body
    out: dict[str, str] = {}
    prev_end, prev_help = -1, ""
    for node in body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            prev_end = node.end_lineno or node.lineno
            prev_help = ""
            continue
        above: list[str] = []
        ln = node.lineno - 1
        while ln >= 1 and lines[ln - 1].strip().startswith("#"):
            above.insert(0, comments.get(ln, ""))
            ln -= 1
        end = node.end_lineno or node.lineno
        inline = [comments[i] for i in range(node.lineno, end + 1) if i in comments]
        text = " ".join(t for t in (*above, *inline) if t)
        if not text and prev_end == node.lineno - 1:
            text = prev_help  # a group of fields under one comment
        out[node.target.id] = text
        prev_end, prev_help = node.end_lineno or node.lineno, text
    for name, text in _docstring_attributes(cls.__doc__ or "").items():
        if not out.get(name):
            out[name] = text
    return out


def _docstring_attributes(doc: str) -> dict[str, str]:
    """The ``Attributes:`` section of a Google-style class docstring: name → text."""
    out: dict[str, str] = {}
    lines = textwrap.dedent("\n".join(doc.splitlines()[1:])).splitlines()
    in_section, current = False, ""
    for line in lines:
        if line.strip() == "Attributes:":
            in_section = True
            continue
        if not in_section:
            continue
        if line and not line.startswith(" "):
            break
        m = re.match(r"^\s{2,8}(\w+):\s*(.*)$", line)
        if m and (not current or len(line) - len(line.lstrip()) <= 8):
            current = m.group(1)
            out[current] = m.group(2).strip()
        elif current and line.strip():
            out[current] += " " + line.strip()
    return out


def _unit_and_help(name: str, text: str) -> tuple[str, str]:
    unit = ""
    m = _COMMENT_UNIT.match(text)
    if m:
        unit, text = m.group(1), text[m.end() :]
    if not unit:
        unit = next((u for suffix, u in _SUFFIX_UNITS if name.endswith(suffix)), "")
    return unit, text


def field_docs(cls: type[Any], prefix: str = "") -> list[FieldDoc]:
    """Every key of ``cls`` (nested tables flattened to dotted keys), in declaration order."""
    hints = typing.get_type_hints(cls)
    comments = field_comments(cls)
    out: list[FieldDoc] = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        key = f"{prefix}{f.name}"
        tp = hints[f.name]
        if f.default is not dataclasses.MISSING:
            default: Any = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = None
        unit, text = _unit_and_help(f.name, comments.get(f.name, ""))
        if dataclasses.is_dataclass(tp) and isinstance(tp, type):
            out.append(FieldDoc(key, "table", f"[{key}]", "", text))
            out += field_docs(tp, f"{key}.")
        else:
            out.append(FieldDoc(key, type_name(tp), _toml(default), unit, text))
    return out


def config_help(cls: type[Any], table: str | None = None) -> str:
    """The ``--help`` epilog of a service: every config key, its type, default, unit and meaning."""
    table = table or service_table(cls)
    filled = {t: fact for fact, targets in SHARED_FACTS.items() for t in targets}
    docs = field_docs(cls)
    nested = next((d.key for d in docs if "." in d.key), "bus.mode")
    outer = nested.rsplit(".", 1)[0]
    lines = [
        f"config keys: table [{table}] of a site file (--config FILE), or --set KEY=VALUE; a nested key",
        f"is --set {nested}=... or {nested.rsplit('.', 1)[1]} in a [{table}.{outer}] table (docs/deploy.md):",
        "",
    ]
    for d in docs:
        if d.type == "table":
            lines.append(f"  {d.key}  (table)")
        else:
            unit = f" [{d.unit}]" if d.unit else ""
            lines.append(f"  {d.key} : {d.type} = {d.default}{unit}")
        note = f" (site file: [site] {filled[d.key]})" if d.key in filled else ""
        for wrapped in textwrap.wrap(d.help + note, 96) or [""]:
            lines.append(f"      {wrapped}")
    return "\n".join(lines)
