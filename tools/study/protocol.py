"""A study's protocol file (TOML) and its schedule: tasks × conditions × repetitions.

::

    [study]
    name = "delay"              # required
    seed = 7                    # required: the order of each participant's trials
    tasks = ["mh3f-targets", "mh3f-wire"]   # required: registered task names (shared/tasks.py)
    repetitions = 3             # required: trials of each task × condition
    blinded = true              # the operator is told a code ("condition C"), not the condition
    practice = 1                # practice trials of each task first (no added delay), not scored
    pause_s = 2.0               # s between trials
    host_margin_ms = 0          # ms added to the watchdog's deadlines on a loaded host (docs/study.md)

    [[condition]]               # one table per condition, at least one
    name = "150 ms"             # required
    delay_ms = 150              # required: added one-way delay, each way (ms, >= 0)
    jitter_ms = 0               # ± uniform jitter on top, each way (ms, >= 0)
    loss = 0.0                  # packet loss (0..1); only 0 on the TCP link impairer
    scale = 0.5                 # motion scale (slave / master), (0, 2]

:func:`load` refuses a bad file with a :class:`ProtocolError` naming its line. :func:`schedule`
orders one participant's trials: the practice block, then every task × condition × repetition
shuffled with a random generator seeded by the study's seed and the participant's id.
"""

from __future__ import annotations

import hashlib
import json
import math
import random
import re
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from telesurg.shared import tasks
from telesurg.shared.errors import ConfigError

STUDY_KEYS = ("name", "seed", "tasks", "repetitions", "blinded", "practice", "pause_s", "host_margin_ms")
STUDY_REQUIRED = ("name", "seed", "tasks", "repetitions")
CONDITION_KEYS = ("name", "delay_ms", "jitter_ms", "loss", "scale")
CONDITION_REQUIRED = ("name", "delay_ms")


class ProtocolError(ConfigError):
    """A protocol file that cannot be run; the message names the file and line."""


@dataclass(frozen=True)
class Condition:
    """One experimental condition (see the module doc for units)."""

    name: str
    delay_ms: float
    jitter_ms: float = 0.0
    loss: float = 0.0
    scale: float = 0.5


@dataclass(frozen=True)
class Protocol:
    """A parsed, checked protocol."""

    name: str
    seed: int
    tasks: tuple[str, ...]
    repetitions: int
    conditions: tuple[Condition, ...]
    blinded: bool = True
    practice: int = 0
    pause_s: float = 0.0
    host_margin_ms: float = 0.0  # ms added to the watchdog's and the mapping's freshness deadlines

    def digest(self) -> str:
        """A short hash of everything that decides the schedule and the trials (resume checks it)."""
        return hashlib.sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:12]


@dataclass(frozen=True)
class Trial:
    """One scheduled trial."""

    index: int  # position in the participant's schedule, from 0
    task: str
    condition: Condition
    repetition: int  # 1-based; 0 for a practice trial
    practice: bool
    code: str  # what a blinded operator is told: "condition C" (or "practice")
    seed: int  # the synthetic operator's seed for this trial


class _Lines:
    """Finds the line of a key in the TOML text (tomllib keeps no positions)."""

    HEADER = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_.\-]+)\s*\]\]?")
    KEY = re.compile(r"^\s*([A-Za-z0-9_\-]+)\s*=")

    def __init__(self, text: str) -> None:
        self.tables: list[tuple[str, int, dict[str, int]]] = []  # (name, header line, key → line)
        current: dict[str, int] = {}
        self.tables.append(("", 0, current))
        for n, line in enumerate(text.splitlines(), 1):
            if m := self.HEADER.match(line):
                current = {}
                self.tables.append((m.group(2), n, current))
            elif (m := self.KEY.match(line)) and m.group(1) not in current:
                current[m.group(1)] = n

    def line(self, table: str, key: str | None = None, index: int = 0) -> int:
        """Line of ``key`` in the ``index``-th ``[table]`` (its header's line without ``key``)."""
        found = [t for t in self.tables if t[0] == table]
        if index >= len(found):
            return 1
        _, header, keys = found[index]
        return keys.get(key, header) if key else header


def _number(v: Any, what: str, lo: float, hi: float, lo_open: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"{what} must be a number, got {v!r}")
    bad = v <= lo if lo_open else v < lo
    if bad or v > hi:
        raise ValueError(f"{what}={v!r} outside {'(' if lo_open else '['}{lo:g}, {hi:g}]")
    return float(v)


def parse(text: str, source: str = "<protocol>") -> Protocol:
    """Parse and check a protocol; ProtocolError ``source:line: what is wrong``."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        m = re.search(r"line (\d+)", str(e))
        raise ProtocolError(f"{source}:{m.group(1) if m else 1}: not valid TOML: {e}") from e
    lines = _Lines(text)

    def fail(what: str, table: str, key: str | None = None, index: int = 0) -> ProtocolError:
        return ProtocolError(f"{source}:{lines.line(table, key, index)}: {what}")

    for top in doc:
        if top not in ("study", "condition"):
            raise fail(f"unknown table [{top}]; valid: [study], [[condition]]", top)
    study = doc.get("study")
    if not isinstance(study, dict):
        raise ProtocolError(f"{source}:1: missing the [study] table ({', '.join(STUDY_REQUIRED)})")
    for k in study:
        if k not in STUDY_KEYS:
            raise fail(f"[study] unknown key {k!r}; valid: {', '.join(STUDY_KEYS)}", "study", k)
    for k in STUDY_REQUIRED:
        if k not in study:
            raise fail(f"[study] missing field {k!r}", "study")
    try:
        name = study["name"]
        if not isinstance(name, str) or not name:
            raise ValueError("name must be a non-empty string")
        seed = study["seed"]
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ValueError(f"seed must be an integer, got {seed!r}")
    except ValueError as e:
        raise fail(f"[study] {e}", "study", "name" if "name" in str(e) else "seed") from e
    task_names = study["tasks"]
    if not isinstance(task_names, list) or not task_names or not all(isinstance(t, str) for t in task_names):
        raise fail("[study] tasks must be a list of task names", "study", "tasks")
    known = tasks.names()
    for t in task_names:
        if t not in known:
            raise fail(f"[study] unknown task {t!r}; known: {', '.join(known)}", "study", "tasks")
    if len(set(task_names)) != len(task_names):
        raise fail("[study] a task is listed twice", "study", "tasks")
    for key, lo_n, hi_n in (("repetitions", 1, 1000), ("practice", 0, 100)):
        v = study.get(key, 0)
        if isinstance(v, bool) or not isinstance(v, int) or not lo_n <= v <= hi_n:
            raise fail(f"[study] {key} must be an integer in [{lo_n}, {hi_n}], got {v!r}", "study", key)
    num: dict[str, float] = {}
    for key, upper in (("pause_s", 3600.0), ("host_margin_ms", 2000.0)):
        try:
            num[key] = _number(study.get(key, 0.0), key, 0.0, upper)
        except ValueError as e:
            raise fail(f"[study] {e}", "study", key) from e
    blinded = study.get("blinded", True)
    if not isinstance(blinded, bool):
        raise fail(f"[study] blinded must be true or false, got {blinded!r}", "study", "blinded")

    raw = doc.get("condition")
    if not isinstance(raw, list) or not raw:
        raise ProtocolError(f"{source}:1: no [[condition]] table: at least one is needed")
    conditions = []
    for i, c in enumerate(raw):
        for k in c:
            if k not in CONDITION_KEYS:
                raise fail(
                    f"[[condition]] unknown key {k!r}; valid: {', '.join(CONDITION_KEYS)}", "condition", k, i
                )
        for k in CONDITION_REQUIRED:
            if k not in c:
                raise fail(f"[[condition]] #{i + 1} missing field {k!r}", "condition", None, i)
        if not isinstance(c["name"], str) or not c["name"]:
            raise fail("[[condition]] name must be a non-empty string", "condition", "name", i)
        checks = (
            ("delay_ms", 0.0, 10_000.0, False),
            ("jitter_ms", 0.0, 10_000.0, False),
            ("loss", 0.0, 0.999, False),
            ("scale", 0.0, 2.0, True),
        )
        vals: dict[str, float] = {}
        for k, lo, hi, lo_open in checks:
            if k in c:
                try:
                    vals[k] = _number(c[k], k, lo, hi, lo_open)
                except ValueError as e:
                    raise fail(f"[[condition]] {c['name']!r}: {e}", "condition", k, i) from e
        if vals.get("loss", 0.0) > 0.0:
            raise fail(
                f"[[condition]] {c['name']!r}: loss={vals['loss']:g}: the study's link impairer is a TCP "
                "proxy (tools/bench/impair.py), which cannot lose packets; loss needs a packet link "
                "between network namespaces (PacketLink), not wired into the study yet",
                "condition",
                "loss",
                i,
            )
        if vals.get("jitter_ms", 0.0) > vals["delay_ms"]:
            raise fail(
                f"[[condition]] {c['name']!r}: jitter_ms={vals['jitter_ms']:g} > "
                f"delay_ms={vals['delay_ms']:g} (the delay would go negative)",
                "condition",
                "jitter_ms",
                i,
            )
        conditions.append(Condition(c["name"], **vals))
    if len({c.name for c in conditions}) != len(conditions):
        raise ProtocolError(f"{source}:1: two conditions have the same name")
    return Protocol(
        name,
        seed,
        tuple(task_names),
        int(study["repetitions"]),
        tuple(conditions),
        blinded,
        int(study.get("practice", 0)),
        num["pause_s"],
        num["host_margin_ms"],
    )


def load(path: str | Path) -> Protocol:
    """Read and check the protocol file ``path`` (ProtocolError naming its line)."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise ProtocolError(f"{p}: cannot read: {e.strerror}") from e
    return parse(text, str(p))


def codes(protocol: Protocol, participant: str) -> dict[str, str]:
    """Condition name → the code a blinded operator is told ("A", "B", …), shuffled per participant
    (so a code says nothing about the condition across participants)."""
    rng = random.Random(f"{protocol.seed}:{participant}:codes")
    letters = [chr(ord("A") + i) if i < 26 else f"Z{i}" for i in range(len(protocol.conditions))]
    rng.shuffle(letters)
    return {c.name: letters[i] for i, c in enumerate(protocol.conditions)}


def schedule(protocol: Protocol, participant: str) -> list[Trial]:
    """One participant's trials in order: the practice block (each task ``practice`` times with no
    impairment), then every task × condition × repetition, shuffled (seed + participant)."""
    rng = random.Random(f"{protocol.seed}:{participant}")
    code = codes(protocol, participant)
    clean = Condition("practice", 0.0, 0.0, 0.0, protocol.conditions[0].scale)
    practice = [(t, clean, 0, True) for _ in range(protocol.practice) for t in protocol.tasks]
    main = [
        (t, c, r, False)
        for t in protocol.tasks
        for c in protocol.conditions
        for r in range(1, protocol.repetitions + 1)
    ]
    rng.shuffle(main)
    out = []
    for i, (task, cond, rep, prac) in enumerate(practice + main):
        label = "practice" if prac else f"condition {code[cond.name]}"
        out.append(Trial(i, task, cond, rep, prac, label, rng.randrange(2**31)))
    return out
