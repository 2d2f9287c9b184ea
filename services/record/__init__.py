"""record: writes everything on a site's bus into an MCAP file, payloads byte-exact.

One raw zenoh subscriber on ``telesurg/<site>/**``. Its callback only appends
``(payload bytes, key, receive time)`` to a queue; a writer thread decodes each sample's header
with the strict decoder (for the timestamps and the sequence check — the payload is never
re-encoded) and writes it to the MCAP file:

* one **channel** per key expression (topic = the full key, e.g. ``telesurg/local/master/m1/buttons``),
  message encoding ``msgpack``;
* one **schema** per message type (name ``telesurg.<type>``, encoding ``jsonschema``), generated
  from the message dataclasses of :mod:`telesurg.shared.messages` with each field's documented unit;
* ``log_time`` = receive time, ``publish_time`` = the header's ``stamp_ns`` (receive time if the
  payload does not decode), ``sequence`` = the header's ``seq`` (mod 2³²);
* metadata ``telesurg.recording`` (site, host, start/stop time, versions) and, at close,
  ``telesurg.summary`` (per key: messages, sequence gaps / lost / reordered / duplicates per
  publisher, undecodable payloads), also printed as a table;
* attachments: files given with ``--attach`` (e.g. the run's TOML configs).

SIGINT / SIGTERM (or ``--seconds``) close the file cleanly, with its summary and index. Replay and
conversion to rerun: :mod:`telesurg.services.record.replay`. Layout and examples: ``docs/console.md``.

Examples::

    telesurg record --out run.mcap --connect tcp/127.0.0.1:7447                 # until Ctrl-C
    telesurg record --out run.mcap --seconds 30 --attach deploy/local/site.toml \\
        --connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import inspect
import json
import logging
import mimetypes
import os
import queue
import re
import socket
import sys
import threading
import time
import typing
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, TYPE_CHECKING, Any

from telesurg.services.common import install_stop_handlers, setup_logging
from telesurg.shared import jsonio
from telesurg.shared.auth import PUT, AuthError, Keyring, is_sealed, unseal, verify
from telesurg.shared.bus import BusConfig, Node, add_bus_args, bus_from_args
from telesurg.shared.clock import wall_ns
from telesurg.shared.errors import ConfigError, MessageError, TelesurgError
from telesurg.shared.keys import Keys, check_id
from telesurg.shared.messages import (
    MAX_STR,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    FieldSpec,
    Header,
    Message,
    decode_any,
)
from telesurg.shared.streams import SeqTracker
from telesurg.shared.timing import settle_gc

if TYPE_CHECKING:
    from mcap.reader import McapReader

log = logging.getLogger(__name__)

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
SCHEMA_PREFIX = "telesurg."
SUMMARY_METADATA = "telesurg.summary"
RECORDING_METADATA = "telesurg.recording"
COMPRESSIONS = ("zstd", "lz4", "none")


@dataclass
class RecordConfig:
    """record config (from the command line)."""

    site: str = "local"  # key prefix telesurg/<site>: the site to record
    service: str = "record"  # instance id (liveliness alive/<service>, heartbeat)
    out: str = ""  # path of the .mcap to write (parent directories are created)
    seconds: float = 0.0  # s: stop after this long (0 = until SIGINT/SIGTERM)
    attach: list[str] = field(default_factory=list)  # files stored as MCAP attachments
    compression: str = "zstd"  # chunk compression: zstd | lz4 | none
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session

    def validate(self) -> None:
        """Raise ConfigError naming what is wrong."""
        check_id("site", self.site)
        check_id("service", self.service)
        if not self.out:
            raise ConfigError("record needs --out FILE.mcap")
        if self.seconds < 0:
            raise ConfigError(f"--seconds {self.seconds} must be >= 0")
        if self.compression not in COMPRESSIONS:
            raise ConfigError(f"compression {self.compression!r} invalid; valid: {', '.join(COMPRESSIONS)}")
        for a in self.attach:
            if not Path(a).is_file():
                raise ConfigError(f"--attach {a}: no such file")
        self.bus.validate()


# --------------------------------------------------------------------------- schemas


_JSON_SCALARS: dict[Any, str] = {str: "string", bool: "boolean", int: "integer", float: "number"}
#: A ``bytes`` field (the camera image's JPEG) is a MessagePack bin: no JSON type of its own.
_JSON_BIN = {"description": "MessagePack bin (raw bytes)"}


def _json_type(tp: Any) -> dict[str, Any]:
    """JSON-schema fragment of a message field's Python type."""
    if tp in _JSON_SCALARS:
        return {"type": _JSON_SCALARS[tp]}
    if tp is bytes:
        return dict(_JSON_BIN)
    args = typing.get_args(tp)
    if typing.get_origin(tp) is tuple and args:
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": "array", "items": _json_type(args[0])}
        if all(a == args[0] for a in args):
            n = len(args)
            return {"type": "array", "items": _json_type(args[0]), "minItems": n, "maxItems": n}
    raise TypeError(f"no JSON schema for field type {tp!r}")


def _json_rules(s: FieldSpec) -> dict[str, Any]:
    """The decoder's rules of one declared field as JSON-schema keywords."""
    out: dict[str, Any] = {}
    if s.kind == "str":
        if s.choices is not None:
            out["enum"] = sorted(s.choices)
        out["maxLength"] = MAX_STR
        if s.nonempty:
            out["minLength"] = 1
        if s.pattern:
            out["pattern"] = f"^(?:{s.pattern})$"
    elif s.kind in ("int", "float"):
        if s.lo is not None:
            out["exclusiveMinimum" if s.lo_open else "minimum"] = s.lo
        if s.hi is not None:
            out["exclusiveMaximum" if s.hi_open else "maximum"] = s.hi
    elif s.kind in ("floats", "strs", "names"):
        out["maxItems"] = s.max_len
        if s.kind == "names":
            out.update(minItems=1, uniqueItems=True)
    return out


def _docstring_parts(cls: type) -> tuple[str, dict[str, str]]:
    """(first paragraph, {attribute: text}) of a class docstring in Google style."""
    doc = inspect.cleandoc(cls.__doc__ or "")
    summary = " ".join(doc.split("\n\n", 1)[0].split())
    attrs: dict[str, str] = {}
    current: list[str] = []
    inside = False
    for line in doc.splitlines():
        if line.strip() == "Attributes:":
            inside = True
            continue
        if not inside:
            continue
        if line and not line.startswith(" "):
            break
        m = re.match(r"^ {4}(\w+(?:\s*/\s*\w+)*):\s*(.*)$", line)
        if m:
            current = [n.strip() for n in m.group(1).split("/")]
            for n in current:
                attrs[n] = m.group(2).strip()
        elif current and line.strip():
            for n in current:
                attrs[n] += " " + line.strip()
    return summary, attrs


def wire_fields(cls: type[Message]) -> list[tuple[str, str, Any]]:
    """``(wire key, dataclass field, Python type)`` of each body field of ``cls``, in order.

    Every message's ``body()`` lists its fields in dataclass order (checked here against
    ``BODY``), so the two line up one to one.
    """
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.name != "header"]
    wire = list(cls(Header("schema", 0, 0)).body())
    if len(wire) != len(names) or set(wire) != cls.BODY:
        raise TypeError(f"{cls.__name__}: body() keys {wire} do not match its fields {names}")
    return [(w, n, hints[n]) for w, n in zip(wire, names, strict=True)]


def json_schema(cls: type[Message]) -> dict[str, Any]:
    """JSON schema of the decoded MessagePack map of ``cls`` (header + body, nothing else)."""
    summary, attrs = _docstring_parts(cls)
    props: dict[str, Any] = {
        "v": {"const": SCHEMA_VERSION, "description": "schema version"},
        "type": {"const": cls.TYPE, "description": "message type tag"},
        "src": {"type": "string", "minLength": 1, "description": "publishing service instance id"},
        "seq": {"type": "integer", "minimum": 0, "description": "per-stream sequence number"},
        "ts": {"type": "integer", "minimum": 0, "description": "source timestamp, ns since the Unix epoch"},
    }
    specs = {s.name: s for s in cls.FIELDS}  # declared with fld(): the decoder's rules too
    for wire, name, tp in wire_fields(cls):
        props[wire] = _json_type(tp)
        if name in specs:
            props[wire].update(_json_rules(specs[name]))
        if name in attrs:
            props[wire]["description"] = attrs[name]
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"{SCHEMA_PREFIX}{cls.TYPE}",
        "description": f"{cls.__name__}: {summary} MessagePack map, schema version {SCHEMA_VERSION}.",
        "type": "object",
        "properties": props,
        "required": list(props),
        "additionalProperties": False,
    }


# --------------------------------------------------------------------------- bookkeeping


#: Sequence bookkeeping of one (key, source) stream of a recording: the project's one
#: :class:`~telesurg.shared.streams.SeqTracker` (nothing is dropped: a late message fills its gap,
#: so it counts as reordered and no longer as lost; a number seen before is a duplicate; ``seq`` 0
#: after a higher one is a restart of the publisher). Up to ``MAX_HOLES`` missing numbers per
#: stream are remembered (``streams.MAX_HOLES``); a gap larger than that is counted but its numbers are not.
SeqCheck = SeqTracker


#: bytes of received samples waiting for the writer thread at most (then dropped and counted)
MAX_BACKLOG_BYTES = 256 * 1024 * 1024


@dataclass
class KeyStats:
    """Everything counted for one key expression."""

    messages: int = 0
    bytes: int = 0
    undecodable: int = 0
    first_ns: int = 0
    last_ns: int = 0
    types: set[str] = field(default_factory=set)
    sources: dict[str, SeqCheck] = field(default_factory=dict)

    def row(self) -> dict[str, Any]:
        """JSON-able summary of this key (``sources`` holds the per-publisher counts)."""
        span = (self.last_ns - self.first_ns) / 1e9
        total = {k: 0 for k in ("gaps", "lost", "reordered", "duplicates", "restarts")}
        for s in self.sources.values():
            for k in total:
                total[k] += getattr(s, k)
        return {
            "messages": self.messages,
            "bytes": self.bytes,
            "rate_hz": round((self.messages - 1) / span, 2) if span > 0 else 0.0,
            "types": sorted(self.types),
            "undecodable": self.undecodable,
            **total,
            "sources": {src: s.counts() for src, s in sorted(self.sources.items())},
        }


# --------------------------------------------------------------------------- writing


def _compression(name: str) -> Any:
    from mcap.writer import CompressionType

    return {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[name]


def telesurg_version() -> str:
    """Installed telesurg version ("unknown" from a bare checkout)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("telesurg")
    except PackageNotFoundError:
        return "unknown"


class Recorder:
    """Raw bus samples → one MCAP file, written on a thread of its own.

    :meth:`push` (the zenoh callback, or a test) only queues ``(payload, key, receive ns)``.
    The writer thread decodes the header (strict decoder; payload bytes stay as received),
    registers channels and schemas on first use, writes the message and keeps the counts.
    :meth:`close` stops the subscription, drains the queue, writes ``telesurg.summary`` and the
    MCAP summary/index, and returns the per-key summary. A context manager.

    Args:
        path: the .mcap to write.
        site: site id; keys are reported relative to ``telesurg/<site>/``.
        attachments: files stored as attachments (name = the path as given).
        info: extra ``telesurg.recording`` metadata entries.
        compression: ``zstd`` / ``lz4`` / ``none``.
    """

    def __init__(
        self,
        path: str | Path,
        site: str,
        *,
        attachments: Sequence[str | Path] = (),
        info: dict[str, str] | None = None,
        compression: str = "zstd",
    ) -> None:
        from mcap.writer import Writer

        self.path = Path(path)
        self.prefix = Keys(site).prefix + "/"
        self.stats: dict[str, KeyStats] = {}
        self.error: BaseException | None = None
        self.unauthenticated = 0  # samples not recorded: their authenticator did not verify
        self._queue: queue.SimpleQueue[tuple[bytes, str, int] | None] = queue.SimpleQueue()
        # bytes queued for the writer, bounded: beyond MAX_BACKLOG_BYTES (a flood, a disk too slow)
        # a sample is dropped and counted (``dropped``) instead of growing memory without limit
        self._backlog_bytes = 0
        self._backlog_lock = threading.Lock()
        self.dropped = 0  # samples not recorded because the writer's backlog was full
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._subscribers: list[Any] = []
        self._closed = False
        self._started_ns = wall_ns()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: IO[bytes] = self.path.open("wb")
        try:
            self._writer = Writer(self._file, compression=_compression(compression))
            self._writer.start(profile="", library=f"telesurg {telesurg_version()} (python mcap)")
            meta = {
                "site": site,
                "prefix": Keys(site).prefix,
                "host": socket.gethostname(),
                "started_ns": str(self._started_ns),
                "telesurg_version": telesurg_version(),
                "message_schema_version": str(SCHEMA_VERSION),
                **(info or {}),
            }
            self._writer.add_metadata(RECORDING_METADATA, meta)
            for a in attachments:
                p = Path(a)
                data = p.read_bytes()
                media = mimetypes.guess_type(p.name)[0] or (
                    "application/toml" if p.suffix == ".toml" else "application/octet-stream"
                )
                self._writer.add_attachment(
                    create_time=p.stat().st_mtime_ns,
                    log_time=wall_ns(),
                    name=str(a),
                    media_type=media,
                    data=data,
                )
        except BaseException:
            self._file.close()
            raise
        self._thread = threading.Thread(target=self._write_loop, name="mcap-writer", daemon=True)
        self._thread.start()

    # -- input (any thread) ---------------------------------------------------------------
    def push(self, payload: bytes, key: str, rx_ns: int) -> None:
        """Queue one received sample (the only thing a zenoh callback does); dropped and counted
        while :data:`MAX_BACKLOG_BYTES` are waiting for the writer."""
        with self._backlog_lock:
            if self._backlog_bytes + len(payload) > MAX_BACKLOG_BYTES:
                self.dropped += 1
                return
            self._backlog_bytes += len(payload)
        self._queue.put((payload, key, rx_ns))

    def subscribe(self, session: Any, key: str, keyring: Keyring | None = None) -> None:
        """Declare one raw subscriber on ``key`` feeding :meth:`push`.

        ``keyring``: record only samples whose authenticator verifies (shared/auth.py); the others
        are counted in :attr:`unauthenticated`, never written (a replay must not re-sign a
        forgery). The payload is written byte-exact either way."""
        push = self.push

        def on_sample(sample: Any) -> None:
            payload = sample.payload.to_bytes()
            k = str(sample.key_expr)
            if keyring is not None:
                att = sample.attachment
                try:
                    who = verify(keyring, PUT, k, payload, att.to_bytes() if att is not None else None)
                    if is_sealed(payload):  # a datagram stream's: written opened (its msgpack)
                        payload = unseal(keyring, who.signer, k, payload)
                except AuthError:
                    self.unauthenticated += 1
                    return
            push(payload, k, wall_ns())

        self._subscribers.append(session.declare_subscriber(key, on_sample))

    @property
    def healthy(self) -> bool:
        """False once the writer thread failed (see :attr:`error`)."""
        return self.error is None and self._thread.is_alive()

    @property
    def backlog(self) -> int:
        """Samples queued but not yet written."""
        return self._queue.qsize()

    # -- writer thread ----------------------------------------------------------------------
    def _write_loop(self) -> None:
        try:
            while (item := self._queue.get()) is not None:
                with self._backlog_lock:
                    self._backlog_bytes -= len(item[0])
                self._write(*item)
        except BaseException as exc:  # disk full, ...: reported by close() and `healthy`
            self.error = exc
            log.exception("MCAP writer failed; recording stopped")

    def _write(self, payload: bytes, key: str, rx_ns: int) -> None:
        st = self.stats.get(key)
        if st is None:
            st = self.stats[key] = KeyStats(first_ns=rx_ns)
        try:
            msg: Message | None = decode_any(payload)
        except MessageError:
            msg = None
        channel = self._channels.get(key)
        if channel is None:
            schema = self._schema(msg.TYPE) if msg is not None else 0
            channel = self._writer.register_channel(key, MESSAGE_ENCODING, schema)
            self._channels[key] = channel
        st.messages += 1
        st.bytes += len(payload)
        st.last_ns = rx_ns
        if msg is None:
            st.undecodable += 1
            self._writer.add_message(channel, log_time=rx_ns, data=payload, publish_time=rx_ns)
            return
        h = msg.header
        st.types.add(msg.TYPE)
        seq = st.sources.get(h.source)
        if seq is None:
            seq = st.sources[h.source] = SeqCheck()
        seq.add(h.seq)
        self._writer.add_message(
            channel, log_time=rx_ns, data=payload, publish_time=h.stamp_ns, sequence=h.seq & 0xFFFFFFFF
        )

    def _schema(self, type_tag: str) -> int:
        sid = self._schemas.get(type_tag)
        if sid is None:
            data = json.dumps(json_schema(MESSAGE_TYPES[type_tag]), indent=1).encode()
            sid = self._writer.register_schema(f"{SCHEMA_PREFIX}{type_tag}", SCHEMA_ENCODING, data)
            self._schemas[type_tag] = sid
        return sid

    # -- lifetime -------------------------------------------------------------------------
    def summary(self) -> dict[str, dict[str, Any]]:
        """Per-key summary (keys relative to the site prefix), sorted by key."""
        return {self.relative(k): s.row() for k, s in sorted(self.stats.items())}

    def relative(self, key: str) -> str:
        """``telesurg/<site>/master/m1/buttons`` → ``master/m1/buttons``."""
        return key[len(self.prefix) :] if key.startswith(self.prefix) else key

    def close(self) -> dict[str, dict[str, Any]]:
        """Stop, drain, write summary + index, close the file; the per-key summary (idempotent)."""
        if self._closed:
            return self.summary()
        self._closed = True
        for sub in self._subscribers:  # no more callbacks from here on
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._subscribers.clear()
        self._queue.put(None)
        self._thread.join()
        summary = self.summary()
        try:
            if self.error is None:
                meta = {k: jsonio.dumps(v, separators=(",", ":")) for k, v in summary.items()}
                meta["_recording"] = jsonio.dumps(
                    {
                        "started_ns": self._started_ns,
                        "stopped_ns": wall_ns(),
                        "messages": sum(s.messages for s in self.stats.values()),
                        "keys": len(self.stats),
                        "dropped_backlog_full": self.dropped,
                    }
                )
                self._writer.add_metadata(SUMMARY_METADATA, meta)
                self._writer.finish()  # type: ignore[no-untyped-call]
        finally:
            self._file.close()
        if self.error is not None:
            raise OSError(f"writing {self.path} failed: {self.error}") from self.error
        return summary

    def __enter__(self) -> Recorder:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc is None:
            self.close()
        else:  # keep the original error; still leave a readable file behind
            with contextlib.suppress(Exception):
                self.close()


@contextlib.contextmanager
def written_whole(out: str | Path) -> Iterator[Path]:
    """The path to write ``out`` at: its sibling ``<out>.part``, renamed to ``out`` when the block
    ends and removed if it raises. A conversion that fails half-way (a damaged recording) leaves
    no partial file, and an ``out`` that was there already stays as it was."""
    out = Path(out)
    part = out.with_name(out.name + ".part")
    try:
        yield part
        os.replace(part, out)
    finally:
        part.unlink(missing_ok=True)


# --------------------------------------------------------------------------- reading


@contextlib.contextmanager
def open_mcap(path: str | Path) -> Iterator[McapReader]:
    """An MCAP reader on ``path`` (the file closes on exit)."""
    from mcap.reader import make_reader

    with Path(path).open("rb") as f:
        yield make_reader(f)


def read_metadata(reader: McapReader, name: str) -> dict[str, str]:
    """The metadata record ``name`` ({} if absent; the last one if repeated)."""
    out: dict[str, str] = {}
    for m in reader.iter_metadata():
        if m.name == name:
            out = dict(m.metadata)
    return out


def read_summary(reader: McapReader) -> dict[str, dict[str, Any]]:
    """The ``telesurg.summary`` metadata, decoded: relative key → counts."""
    raw = read_metadata(reader, SUMMARY_METADATA)
    return {k: json.loads(v) for k, v in raw.items() if not k.startswith("_")}


def recording_site(reader: McapReader) -> str:
    """Site the file was recorded on (``telesurg.recording`` metadata, else "local")."""
    return read_metadata(reader, RECORDING_METADATA).get("site", "local")


def iter_decoded(
    reader: McapReader, want: Callable[[str], bool] | None = None
) -> Iterator[tuple[str, int, int, bytes, Message | None]]:
    """``(topic, log_time, publish_time, payload, message or None)`` in log-time order.

    ``want(topic)`` selects channels (all if None); payloads that do not decode give ``None``.
    """
    summary = reader.get_summary()
    topics = None
    if summary is not None and want is not None:
        topics = [c.topic for c in summary.channels.values() if want(c.topic)]
        if not topics:
            return
    for _schema, channel, m in reader.iter_messages(topics=topics, log_time_order=True):
        if topics is None and want is not None and not want(channel.topic):
            continue
        try:
            msg: Message | None = decode_any(m.data)
        except MessageError:
            msg = None
        yield channel.topic, m.log_time, m.publish_time, m.data, msg


# --------------------------------------------------------------------------- reports


COLUMNS = ("messages", "rate_hz", "undecodable", "gaps", "lost", "reordered", "duplicates", "restarts")


def print_summary(summary: dict[str, dict[str, Any]], title: str, file: Any = None) -> None:
    """The per-key summary as a rich table (to stdout by default)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, title_justify="left")
    table.add_column("key")
    table.add_column("type")
    table.add_column("sources")
    for c in COLUMNS:
        table.add_column(c.replace("_", " "), justify="right")
    for key, row in summary.items():
        bad = any(row[c] for c in ("undecodable", "gaps", "lost", "reordered", "duplicates"))
        table.add_row(
            key,
            ",".join(row["types"]) or "-",
            ",".join(row["sources"]) or "-",
            *(f"{row[c]:g}" if isinstance(row[c], float) else str(row[c]) for c in COLUMNS),
            style="yellow" if bad else None,
        )
    Console(file=file or sys.stdout, width=200).print(table)


# --------------------------------------------------------------------------- service


def run(cfg: RecordConfig, stop: threading.Event) -> dict[str, dict[str, Any]]:
    """Record until ``stop`` or ``cfg.seconds``; the file is complete when this returns."""
    cfg.validate()
    info = {"argv": json.dumps(sys.argv), "pid": str(os.getpid())}
    with (
        Node(cfg.bus, cfg.site, cfg.service) as node,
        Recorder(cfg.out, cfg.site, attachments=cfg.attach, info=info, compression=cfg.compression) as rec,
    ):
        rec.subscribe(node.session, node.keys.all, node.keyring)
        log.info("recording %s to %s", node.keys.all, cfg.out)
        settle_gc()
        deadline = time.monotonic() + cfg.seconds if cfg.seconds > 0 else float("inf")
        warned = False
        while not stop.wait(0.2) and time.monotonic() < deadline:
            if not rec.healthy:
                break
            if not warned and rec.backlog > 50_000:
                warned = True
                log.warning("writer is %d samples behind (disk or CPU too slow)", rec.backlog)
        summary = rec.close()
    if rec.dropped:
        log.warning(
            "%d samples not recorded: the writer's backlog was full (%d bytes)",
            rec.dropped,
            MAX_BACKLOG_BYTES,
        )
    if rec.unauthenticated:
        log.warning("%d unauthenticated samples were not recorded", rec.unauthenticated)
    total = sum(r["messages"] for r in summary.values())
    log.info("wrote %d messages on %d keys to %s", total, len(summary), cfg.out)
    return summary


def parser() -> argparse.ArgumentParser:
    """Command-line flags of ``telesurg record``."""
    p = argparse.ArgumentParser(
        prog="telesurg record", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--out", required=True, metavar="FILE.mcap", help="MCAP file to write")
    p.add_argument("--seconds", type=float, default=0.0, help="stop after S seconds (default: Ctrl-C)")
    p.add_argument("--site", default="local", help="site id (key prefix telesurg/<site>)")
    p.add_argument("--service", default="record", help="instance id on the bus (default: record)")
    p.add_argument(
        "--attach", action="append", default=[], metavar="FILE", help="store FILE in the recording"
    )
    p.add_argument("--compression", choices=COMPRESSIONS, default="zstd", help="chunk compression")
    p.add_argument("--json", metavar="FILE", help="also write the summary as JSON")
    p.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    add_bus_args(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg record``: 0 when the file was closed cleanly, 1 on a failure, 2 on bad flags."""
    args = parser().parse_args(argv)
    cfg = RecordConfig(
        site=args.site,
        service=args.service,
        out=args.out,
        seconds=args.seconds,
        attach=list(args.attach),
        compression=args.compression,
    )
    try:
        cfg.bus = bus_from_args(args, cfg.bus)
        cfg.validate()
    except TelesurgError as exc:
        print(f"telesurg record: {exc}", file=sys.stderr)
        return 2
    setup_logging(args.log_level, cfg.service)
    stop = threading.Event()
    install_stop_handlers(stop)
    try:
        summary = run(cfg, stop)
    except (TelesurgError, ConnectionError, OSError) as exc:
        log.error("%s", exc)
        return 1
    print_summary(summary, f"{cfg.out}: {sum(r['messages'] for r in summary.values())} messages")
    if args.json:
        Path(args.json).write_text(jsonio.dumps(summary, indent=2) + "\n")
    return 0
