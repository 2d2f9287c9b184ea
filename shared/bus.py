"""One zenoh helper for every service: the same flags, the same safe defaults.

* ``--mode peer|client|router``, ``--connect``, ``--listen``, ``--config FILE`` (a zenoh JSON5
  config file, applied first; the flags override it).
* Multicast and gossip scouting off unless ``--multicast`` is given: robots on one network must
  not find each other by accident.
* ``transport/link/tx/lease`` set on every process (default 1000 ms, keep-alive every 250 ms), so a
  frozen peer is dropped within about a second, not zenoh's default 10 s.
* TLS (``--tls-ca/--tls-cert/--tls-key``, ``--mtls``) for ``tls/`` endpoints, and a router-side
  access-control file (``--acl``: zenoh ``access_control`` rules, JSON5 or TOML). A router with
  TLS or an ACL refuses plain ``tcp/``/``udp/`` listeners beyond loopback unless
  ``--allow-insecure-listen`` (local development): the plain loopback listener is for the site's
  own services. See docs/deploy.md.
* Control streams are published ``express`` (no batching) with ``Priority.REAL_TIME`` and
  ``CongestionControl.BLOCK``: nothing is dropped on a congested link (receivers check sequence
  continuity and the watchdog sees a blocked stream as stale). The site's router keeps BLOCK only
  towards the control services (``BusConfig.zid``, given by the launcher) and sends the control
  streams to every other subscriber as DROP, so a subscriber that stops reading loses samples
  instead of holding them up for the slave (services/router ``congestion_rules``). Other streams
  use ``Priority.DATA_HIGH`` and zenoh's default congestion control.
* Datagram link (``--datagram udp/HOST:PORT``, a console across a lossy WAN): the streams a
  service marks ``datagram`` (the master's pose, joints and buttons) go best effort over a second,
  publish-only session on the site router's ``udp/`` listener — no retransmission, so a lost
  packet costs one sample instead of stalling the stream for a round trip as TLS over TCP does.
  Everything else stays on the main (mutual TLS) session. Each sample is still signed and
  checked for freshness, and encrypted (``shared/auth.py``, sealed payloads); the site's ACL
  lets a UDP transport put those streams and nothing else (docs/deploy.md, "Across a
  distance").
* State streams (``outlet(..., latest=True)``, ``subscribe(..., latest=True)``): the publisher
  answers a query on its key with its last message and a subscriber asks once when it
  subscribes, so a late joiner (a console started mid-session) has the current value at once,
  not at the next publication.

Example::

    with Node(BusConfig(connect=["tcp/127.0.0.1:7447"]), site="local", service="demo") as node:
        out = node.outlet(node.keys.slave("arm1", "servo_jp"))
        out.put(JointSetpoint(out.header(), ("j1",), (0.0,), follow=False))
"""

from __future__ import annotations

import argparse
import contextlib
import ipaddress
import json
import logging
import os
import re
import threading
import time
import tomllib
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, TypeVar

from telesurg.shared.auth import (
    PUT,
    QUERY,
    REPLY,
    AuthError,
    Keyring,
    Sealer,
    Signer,
    attachment_signer,
    default_keys_dir,
    is_sealed,
    unseal,
    verify,
)
from telesurg.shared.clock import MAX_SKEW_MS, ClockSample, wall_ns
from telesurg.shared.errors import AuthorityError, ConfigError, MessageError
from telesurg.shared.fresh import MAX_AGE_MS, TOLERANCE_MS, Freshness, SenderWindow
from telesurg.shared.keys import Keys, check_id
from telesurg.shared.messages import (
    ClockProbe,
    ClockReply,
    Header,
    Heartbeat,
    Message,
    SafetyEvent,
    Sequencer,
    decode_as,
)
from telesurg.shared.presence import Presence
from telesurg.shared.streams import StreamStats, StreamTable

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)

MODES = ("peer", "client", "router")
POLL_CAPACITY = 4096  # messages a polled subscription buffers between polls (4 s at 1 kHz)
PLAIN_PROTOCOLS = ("tcp", "udp")  # unencrypted, unauthenticated link protocols
TLS_PROTOCOLS = ("tls", "quic")  # link protocols that use the tls_* settings


@dataclass
class BusConfig:
    """How a process joins the zenoh network."""

    mode: str = "client"  # peer | client | router; services are clients of the site router
    connect: list[str] = field(default_factory=list)  # endpoints to connect to, e.g. tcp/127.0.0.1:7447
    listen: list[str] = field(default_factory=list)  # endpoints to listen on
    config_file: str = ""  # optional zenoh JSON5 config, applied before the fields above
    lease_ms: int = 1000  # transport lease, ms: a silent peer is dropped after this
    multicast: bool = False  # multicast scouting; off so robots never discover each other by accident
    # TLS for tls/ endpoints (PEM files; "" = unset, zenoh's defaults). A client needs tls_root_ca
    # to verify the router; with mtls both sides present tls_cert, and the router reads its CN.
    tls_root_ca: str = ""  # CA certificate that verifies the other side's certificate
    tls_cert: str = ""  # this process's certificate: server cert when listening, client cert with mtls
    tls_key: str = ""  # private key of tls_cert (PKCS#8 PEM, e.g. from `telesurg certs`)
    mtls: bool = False  # mutual TLS: a router requires, a client presents, a certificate from tls_root_ca
    acl_file: str = ""  # access-control rules (zenoh `access_control` object; .json5/.json or .toml)
    # A secured process (TLS or ACL) listens on plain tcp/ or udp/ only on loopback, unless this is
    # set for local development: anyone reaching a plain listener bypasses the certificates.
    allow_insecure_listen: bool = False
    # zenoh's own log to stderr, a Rust tracing filter ("" = off; RUST_LOG wins if set), e.g.
    # "zenoh::net::routing::interceptor::access_control=trace" logs every ACL denial (router)
    zenoh_log: str = ""
    # the site keyring (shared/auth.py): every message is signed with this process's key and every
    # message received is verified with the signer's ("" = the default: $TELESURG_KEYS, else
    # $XDG_STATE_HOME/telesurg/<site>/keys; `telesurg keys init DIR`, made by `telesurg up`/`demo`)
    keys_dir: str = ""
    # this process's zenoh session id: 1-32 lowercase hex digits, no leading 0 ("" = random).
    # The launcher gives the control services one each and lists them in the router's
    # control_zids: the router may hold up a control stream for them (CongestionControl.BLOCK)
    # but drops it for every other subscriber that does not keep up, so a stalled viewer cannot
    # stall the control path
    zid: str = ""
    # freshness (shared/fresh.py): a message whose header stamp is older than this, ms, on the
    # receiver's clock is refused as stale (a replay), and so is one stamped before the receiver
    # started, or more than clock_tolerance_ms in the future
    max_age_ms: int = MAX_AGE_MS
    # ms of clock offset between two hosts tolerated by the freshness rules (one host: scheduling)
    clock_tolerance_ms: int = TOLERANCE_MS
    # ms added to this process's wall clock (shared/clock.py): a test or bench playing a host
    # whose clock is off; 0 in a real site
    clock_skew_ms: float = 0.0
    # the site router's udp/ endpoint for the datagram streams ("" = none: every stream on the
    # main session); a second, publish-only session (module docstring)
    datagram: str = ""

    @property
    def secured(self) -> bool:
        """TLS or access control is configured."""
        return bool(self.tls_cert or self.tls_root_ca or self.mtls or self.acl_file)

    def validate(self) -> None:
        """Raise ConfigError naming the valid options."""
        if self.mode not in MODES:
            raise ConfigError(f"bus mode {self.mode!r} invalid; valid: {', '.join(MODES)}")
        if not 100 <= self.lease_ms <= 60_000:
            raise ConfigError(f"bus lease_ms={self.lease_ms} outside [100, 60000]")
        if not 100 <= self.max_age_ms <= 600_000:
            raise ConfigError(f"bus max_age_ms={self.max_age_ms} outside [100, 600000]")
        if not 0 <= self.clock_tolerance_ms <= 60_000:
            raise ConfigError(f"bus clock_tolerance_ms={self.clock_tolerance_ms} outside [0, 60000]")
        if not abs(self.clock_skew_ms) <= MAX_SKEW_MS:
            raise ConfigError(f"bus clock_skew_ms={self.clock_skew_ms} outside ±{MAX_SKEW_MS:g}")
        if self.zid and not valid_zid(self.zid):
            raise ConfigError(f"bus zid {self.zid!r} invalid: 1-32 lowercase hex digits, no leading 0")
        if self.datagram and (protocol_of(self.datagram) != "udp" or "?" in self.datagram):
            raise ConfigError(
                f"bus datagram {self.datagram!r} invalid: a udp/HOST:PORT endpoint of the site router"
            )
        if self.mode == "client" and not self.connect:
            raise ConfigError("bus mode 'client' needs at least one --connect endpoint")
        for name in ("tls_root_ca", "tls_cert", "tls_key", "acl_file"):
            path = getattr(self, name)
            if path and not os.path.isfile(path):
                raise ConfigError(f"bus {name}: file {path!r} not found")
        if bool(self.tls_cert) != bool(self.tls_key):
            raise ConfigError("bus tls_cert and tls_key go together (--tls-cert and --tls-key)")
        if self.mtls and not (self.tls_root_ca and self.tls_cert):
            raise ConfigError(
                "bus mtls needs tls_root_ca, tls_cert and tls_key (--tls-ca/--tls-cert/--tls-key)"
            )
        if any(protocol_of(ep) in TLS_PROTOCOLS for ep in self.listen) and not self.tls_cert:
            raise ConfigError(
                "a tls/ or quic/ listen endpoint needs tls_cert and tls_key (--tls-cert/--tls-key)"
            )
        if any(protocol_of(ep) in TLS_PROTOCOLS for ep in self.connect) and not self.tls_root_ca:
            raise ConfigError(
                "a tls/ or quic/ connect endpoint needs tls_root_ca (--tls-ca) to verify the router"
            )
        if self.secured and not self.allow_insecure_listen:
            for ep in self.listen:
                if protocol_of(ep) == "udp" and self.acl_file:
                    continue  # the datagram listener: the ACL says what a UDP transport may do
                if protocol_of(ep) in PLAIN_PROTOCOLS and not is_loopback(ep):
                    raise ConfigError(
                        f"plain listen endpoint {ep} on a secured bus (TLS/ACL): bind it to 127.0.0.1, "
                        "or pass --allow-insecure-listen (local development only)"
                    )


def _report_due(reported: dict[str, tuple[int, float]], key: str) -> bool:
    """Whether a refusal on ``key`` is reported: the first five, then at most one a second
    (``reported``: key → (reports so far, monotonic s of the last); the caller holds its lock)."""
    n, last = reported.get(key, (0, 0.0))
    now = time.monotonic()
    if n < 5 or now - last >= 1.0:
        reported[key] = (n + 1, now)
        return True
    return False


def valid_zid(zid: str) -> bool:
    """``zid`` is a zenoh session id as zenoh writes one: 1-32 lowercase hex digits, no leading 0."""
    return bool(re.fullmatch(r"[1-9a-f][0-9a-f]{0,31}", zid))


def protocol_of(endpoint: str) -> str:
    """``"tls"`` for ``tls/host:7447``."""
    return endpoint.partition("/")[0].lower()


def is_loopback(endpoint: str) -> bool:
    """The endpoint's address is a loopback address (``127.0.0.0/8``, ``::1``, ``localhost``)."""
    addr = endpoint.partition("/")[2]
    for sep in ("?", "#"):  # zenoh endpoint metadata / config
        addr = addr.partition(sep)[0]
    host = addr.rpartition(":")[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def load_acl(path: str) -> str:
    """JSON5 text of the ``access_control`` object in ``path`` (TOML converted; JSON5 as is)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"acl file {path!r}: {exc}") from None
    if path.endswith(".toml"):
        try:
            return json.dumps(tomllib.loads(text))
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"acl file {path!r}: {exc}") from None
    return text


#: ms a datagram session keeps trying to connect at start (its UDP handshake is not retransmitted)
DATAGRAM_CONNECT_MS = 5000

#: Cycles after a change of a state sample on a datagram stream (the master's buttons) in which it
#: goes out again: a lost packet must not lose a clutch press or release (1.2 % loss, 6 in a row:
#: ~3e-12)
DATAGRAM_REPEAT = 5


class Resend:
    """When a state sample of a datagram stream (a master's buttons) goes out: on every change
    and in the :data:`DATAGRAM_REPEAT` calls after it, and at least every ``every`` calls.
    :meth:`reset`: the next one goes out whatever it is (readings resume after a gap)."""

    def __init__(self, every: int) -> None:
        self.every = max(1, every)
        self._last: object = None
        self._left = 0  # calls left in which it goes out again after a change
        self._calls = 0

    def reset(self) -> None:
        self._last = None

    def due(self, state: object) -> bool:
        """Whether ``state``, this call's, goes out."""
        self._calls += 1
        if state != self._last:
            self._last, self._left = state, DATAGRAM_REPEAT + 1
        self._left -= 1
        return self._left >= 0 or self._calls % self.every == 0


#: The endpoint a client connects to when no ``--connect`` (nor ``--zenoh-config``) is given: the
#: router of the local site (``telesurg up`` / ``demo`` listen there by default).
LOCAL_ROUTER = "tcp/127.0.0.1:7447"


def add_bus_args(parser: argparse.ArgumentParser) -> None:
    """Add the common zenoh flags (``--mode --connect --listen --zenoh-config --lease-ms``, TLS, ACL)."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("--mode", choices=MODES, help="zenoh mode (default: client)")
    g.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help=f"router to connect to, repeatable (a client without one: {LOCAL_ROUTER}, the local site)",
    )
    g.add_argument("--listen", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    g.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config file")
    g.add_argument("--lease-ms", type=int, help="transport lease, ms (default 1000)")
    g.add_argument("--multicast", action="store_true", default=None, help="enable multicast scouting")
    g.add_argument("--tls-ca", metavar="FILE", help="CA certificate (PEM) that verifies the other side")
    g.add_argument("--tls-cert", metavar="FILE", help="this process's certificate (PEM)")
    g.add_argument("--tls-key", metavar="FILE", help="private key of --tls-cert (PEM)")
    g.add_argument("--mtls", action="store_true", default=None, help="mutual TLS (both sides show a cert)")
    g.add_argument("--acl", metavar="FILE", help="access-control rules, JSON5 or TOML (router)")
    g.add_argument("--zenoh-log", metavar="FILTER", help="zenoh's own log, e.g. zenoh=info (stderr)")
    g.add_argument(
        "--keyring",
        metavar="DIR",
        help="site keyring (default: $TELESURG_KEYS or $XDG_STATE_HOME/telesurg/<site>/keys)",
    )
    g.add_argument(
        "--allow-insecure-listen",
        action="store_true",
        default=None,
        help="with TLS/ACL, still allow plain tcp/udp listeners beyond loopback (development only)",
    )
    g.add_argument(
        "--datagram",
        metavar="ENDPOINT",
        help="the site router's udp/HOST:PORT: the master's pose, joints and buttons go there best effort",
    )


def bus_from_args(args: argparse.Namespace, base: BusConfig | None = None) -> BusConfig:
    """BusConfig from parsed flags, on top of ``base`` (e.g. from a TOML file)."""
    cfg = base or BusConfig()
    if args.mode:
        cfg.mode = args.mode
    if args.connect:
        cfg.connect = list(args.connect)
    if args.listen:
        cfg.listen = list(args.listen)
    if args.zenoh_config:
        cfg.config_file = args.zenoh_config
    if args.lease_ms:
        cfg.lease_ms = args.lease_ms
    if args.multicast:
        cfg.multicast = True
    for flag, name in (("tls_ca", "tls_root_ca"), ("tls_cert", "tls_cert"), ("tls_key", "tls_key")):
        if value := getattr(args, flag, None):
            setattr(cfg, name, value)
    if getattr(args, "mtls", None):
        cfg.mtls = True
    if acl := getattr(args, "acl", None):
        cfg.acl_file = acl
    if getattr(args, "allow_insecure_listen", None):
        cfg.allow_insecure_listen = True
    if zlog := getattr(args, "zenoh_log", None):
        cfg.zenoh_log = zlog
    if keyring := getattr(args, "keyring", None):
        cfg.keys_dir = keyring
    if datagram := getattr(args, "datagram", None):
        cfg.datagram = datagram
    if cfg.mode == "client" and not cfg.connect and not cfg.config_file:
        cfg.connect = [LOCAL_ROUTER]  # every command line: the local site's router by default
    return cfg


def zenoh_config(cfg: BusConfig) -> zenoh.Config:
    """Build a zenoh.Config: file first, then mode/endpoints/scouting/lease."""
    import zenoh

    cfg.validate()
    z = zenoh.Config.from_file(cfg.config_file) if cfg.config_file else zenoh.Config()
    z.insert_json5("mode", json.dumps(cfg.mode))
    if cfg.zid:
        z.insert_json5("id", json.dumps(cfg.zid))
    if cfg.connect:
        z.insert_json5("connect/endpoints", json.dumps(cfg.connect))
    if cfg.listen:
        z.insert_json5("listen/endpoints", json.dumps(cfg.listen))
    z.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast))
    if not cfg.multicast:
        z.insert_json5("scouting/gossip/enabled", json.dumps(cfg.mode != "client"))
    z.insert_json5("transport/link/tx/lease", json.dumps(cfg.lease_ms))
    z.insert_json5("transport/link/tx/keep_alive", json.dumps(4))
    tls = "transport/link/tls"
    if cfg.tls_root_ca:
        z.insert_json5(f"{tls}/root_ca_certificate", json.dumps(os.path.abspath(cfg.tls_root_ca)))
    if cfg.tls_cert:
        for side in ("listen", "connect"):
            z.insert_json5(f"{tls}/{side}_certificate", json.dumps(os.path.abspath(cfg.tls_cert)))
            z.insert_json5(f"{tls}/{side}_private_key", json.dumps(os.path.abspath(cfg.tls_key)))
    if cfg.mtls:
        z.insert_json5(f"{tls}/enable_mtls", json.dumps(True))
    if cfg.acl_file:
        try:
            z.insert_json5("access_control", load_acl(cfg.acl_file))
        except zenoh.ZError as exc:
            raise ConfigError(
                f"acl file {cfg.acl_file!r} is not a valid zenoh access_control: {exc}"
            ) from None
    return z


def open_datagram_session(bus: BusConfig) -> zenoh.Session:
    """The publish-only session of ``bus``'s datagram streams, on ``bus.datagram`` (the module
    docstring); it keeps trying to connect for :data:`DATAGRAM_CONNECT_MS`."""
    cfg = BusConfig(mode="client", connect=[bus.datagram], lease_ms=bus.lease_ms, zenoh_log=bus.zenoh_log)
    return open_session(cfg, retry_ms=DATAGRAM_CONNECT_MS)


def open_session(cfg: BusConfig, *, retry_ms: int = 0) -> zenoh.Session:
    """Open a zenoh session; errors name the endpoint that failed. ``retry_ms``: keep trying to
    connect this long (a UDP handshake has no retransmission: on a lossy link one try can fail)."""
    import zenoh

    if cfg.zenoh_log:
        zenoh.init_log_from_env_or(cfg.zenoh_log)
    try:
        z = zenoh_config(cfg)
        if retry_ms:
            z.insert_json5("connect/timeout_ms", json.dumps(retry_ms))
            retry = {"period_init_ms": 200, "period_max_ms": 1000, "period_increase_factor": 2}
            z.insert_json5("connect/retry", json.dumps(retry))
        return zenoh.open(z)
    except zenoh.ZError as exc:
        tls = tls_diagnosis(cfg)
        if cfg.mode == "client" and not tls and "Unable to connect to any of" in str(exc):
            where = ", ".join(cfg.connect) or "any router"
            raise ConnectionError(
                f"zenoh session failed: no router at {where}: start a site with `telesurg up`, "
                "or pass --connect ENDPOINT"
            ) from exc
        raise ConnectionError(
            f"zenoh session failed ({cfg.mode}, connect={cfg.connect}, listen={cfg.listen}): {exc}" + tls
        ) from exc


def tls_diagnosis(cfg: BusConfig) -> str:
    """``"; TLS: <why>"`` for a client's failed ``tls/`` connect (shared/tlsdiag.py), else ``""``."""
    from telesurg.shared.tlsdiag import TlsFiles, diagnose

    if not cfg.tls_root_ca:
        return ""
    files = TlsFiles(cfg.tls_root_ca, cfg.tls_cert if cfg.mtls else "", cfg.tls_key if cfg.mtls else "")
    found = [d for ep in cfg.connect if protocol_of(ep) == "tls" and (d := diagnose(ep, files))]
    return f"; TLS: {' | '.join(found)}" if found else ""


def _raw(attachment: Any) -> bytes | None:
    """The bytes of a zenoh attachment (None: none)."""
    return attachment.to_bytes() if attachment is not None else None


def only(service: str) -> list[str] | None:
    """``sources=`` value for :meth:`Node.subscribe` allowing one service id, or several
    comma-separated (``"master_capture,master_capture_2"``: a site with two masters); "" = anyone."""
    return [s.strip() for s in service.split(",") if s.strip()] if service else None


class Outlet:
    """A publisher plus the sequencer of its stream (and, for a ``latest`` outlet, its last
    message, which :class:`Node` serves to late joiners)."""

    def __init__(
        self, publisher: Any, source: str, signer: Signer, key: str, sealer: Sealer | None = None
    ) -> None:
        self._pub = publisher
        self._seq = Sequencer(source)
        self._signer = signer
        self._key = key
        self._sealer = sealer  # a datagram outlet's: the payload is encrypted (shared/auth.py)
        self.last: bytes | None = None  # the last payload put (kept by a ``latest`` outlet only)
        self._keep = False

    def header(self) -> Header:
        """Header for the next message on this stream."""
        return self._seq.next()

    def put(self, msg: Message) -> None:
        """Encode, sign and publish."""
        payload = msg.encode()
        if self._keep:
            self.last = payload
        if self._sealer is not None:
            payload = self._sealer.seal(self._key, payload)
        self._pub.put(payload, attachment=self._signer.attach(PUT, self._key, payload))

    @property
    def sent(self) -> int:
        """Messages sent so far."""
        return self._seq.seq


class Node:
    """A service's presence on the bus: session, liveliness token, heartbeat, events, inputs.

    Every message it sends is signed with the service's key from the site keyring
    (:mod:`telesurg.shared.auth`; ``bus.keys_dir``, default :func:`~telesurg.shared.auth.default_keys_dir`;
    no keyring → ConfigError saying how to make one); every message it receives is verified
    first, before decoding: one that fails (no authenticator, unknown signer, bad MAC, signer ≠
    header ``src``) is rejected, counted (``unauthenticated``, within ``rejected``), reported as
    an ``unauthenticated`` event (rate-limited) and changes nothing else. An authenticated
    message that is not fresh (too old, stamped before this node started, not newer than what its
    signer sent on the key before, a query already taken; :mod:`telesurg.shared.fresh`) is
    rejected the same way (``replayed``, a ``replayed`` event). Replies are bound to their query.
    Every subscription made
    with :meth:`subscribe` decodes through the strict decoder; malformed or out-of-order messages
    are counted per key in :attr:`streams` and never reach the callback.
    Use as a context manager; it undeclares everything on exit.
    """

    def __init__(self, bus: BusConfig, site: str, service: str) -> None:
        self.keys = Keys(site)
        self.service = check_id("service", service)
        self.keyring = Keyring.load(bus.keys_dir or default_keys_dir(site))
        self.signer = Signer(self.service, self.keyring.ensure(self.service), links=self.keyring.send_keys())
        self._auth_reported: dict[str, tuple[int, float]] = {}  # key -> (reports, last report monotonic s)
        self._replay_reported: dict[str, tuple[int, float]] = {}  # the same for replays
        # freshness (shared/fresh.py): started now, so nothing stamped before this start gets in
        self.fresh = Freshness(bus.max_age_ms, bus.clock_tolerance_ms)
        self.streams = StreamTable()
        self._lock = threading.Lock()
        self._start = time.monotonic()
        self._handles: list[Any] = []  # publishers; keep references: zenoh undeclares on GC
        self._inputs: list[Any] = []  # subscribers, undeclared first on close
        self._subscribed: set[str] = set()
        self._polled: list[tuple[Any, Callable[[Any, int], None]]] = []  # (subscriber, on_sample)
        self._last_poll_ns = 0
        self._polled_ns = 0  # when the last poll() finished (heartbeat's polled_s)
        self._closed = False
        self.session = open_session(bus)
        self._datagram: Any = None  # the publish-only session of the datagram streams
        self._sealer_obj: Sealer | None = None
        if bus.datagram:
            try:
                self._datagram = open_datagram_session(bus)
            except ConnectionError:
                self.session.close()  # type: ignore[no-untyped-call]
                raise
        # presence by authenticated session (shared/presence.py): the token carries this node's sid
        self.presence = Presence()
        self._liveliness_subs: set[str] = set()
        self._token: Any = self.session.liveliness().declare_token(
            self.keys.alive_token(service, self.signer.sid.hex())
        )
        self._events = self.outlet(self.keys.events(service), control=False)
        self._heartbeat = self.outlet(self.keys.heartbeat(service), control=False)
        # Echo: answers clock probes at once (signed), so a peer on another host can measure the
        # round trip and this host's clock offset (shared/clock.py)
        self._probe_seq = Sequencer(service)  # the probes this node sends
        self._reply_seq = Sequencer(service)  # its answers (on zenoh's threads)
        self.serve(self.keys.echo(service), ClockProbe, self._on_clock_probe)
        self._hb_stop = threading.Event()
        self._hb_thread = threading.Thread(target=self._heartbeat_loop, daemon=True)
        self._hb_thread.start()

    def _sealer(self) -> Sealer:
        """The encrypter of this node's datagram streams (made once)."""
        if self._sealer_obj is None:
            self._sealer_obj = Sealer(self.keyring, self.service)
        return self._sealer_obj

    # -- outputs --------------------------------------------------------------------------
    def outlet(
        self, key: str, *, control: bool = True, latest: bool = False, datagram: bool = False
    ) -> Outlet:
        """Declare a publisher; control streams get express + real-time priority + block.

        ``latest``: also answer queries on ``key`` with the last message put, so a subscriber
        that joins later (``subscribe(..., latest=True)``) gets the current value at once instead
        of at the next publication (a state stream, e.g. the teleop state).
        ``datagram``: a control stream where the newest sample is all that counts (a pose); with
        ``BusConfig.datagram`` set it goes best effort over the datagram session (express,
        real-time priority, dropped rather than queued), else as any control stream."""
        import zenoh

        if datagram and self._datagram is not None:
            pub = self._datagram.declare_publisher(
                key,
                express=True,
                priority=zenoh.Priority.REAL_TIME,
                congestion_control=zenoh.CongestionControl.DROP,
                reliability=zenoh.Reliability.BEST_EFFORT,
            )
        elif control:
            pub = self.session.declare_publisher(
                key,
                express=True,
                priority=zenoh.Priority.REAL_TIME,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        else:
            pub = self.session.declare_publisher(key, priority=zenoh.Priority.DATA_HIGH)
        self._handles.append(pub)
        sealed = datagram and self._datagram is not None  # no TLS on that link: encrypted here
        out = Outlet(pub, self.service, self.signer, key, self._sealer() if sealed else None)
        if latest:
            out._keep = True

            def on_query(query: Any) -> None:
                last = out.last
                with contextlib.suppress(Exception):  # the querier may be gone
                    if last is not None:  # bound to the query: valid as an answer to it only
                        bind = _raw(query.attachment) or b""
                        query.reply(key, last, attachment=self.signer.attach(REPLY, key, last, bind=bind))

            self._handles.append(self.session.declare_queryable(key, on_query))
        return out

    def event(self, kind: str, text: str, *, arm: str = "", severity: str = "info") -> None:
        """Publish an event and log it."""
        level = {"info": logging.INFO, "warning": logging.WARNING}.get(severity, logging.ERROR)
        log.log(level, "%s%s: %s", f"[{arm}] " if arm else "", kind, text)
        if not self._closed:
            self._events.put(SafetyEvent(self._events.header(), arm, kind, severity, text))

    # -- inputs ---------------------------------------------------------------------------
    def subscribe(
        self,
        key: str,
        cls: type[M],
        callback: Callable[[M, str], None],
        *,
        sources: Collection[str] | Callable[[str, str], bool] | None = None,
        polled: bool = False,
        latest: bool = False,
        keep: int = POLL_CAPACITY,
    ) -> None:
        """Subscribe with strict decoding; ``callback(msg, key)`` runs on a zenoh thread.

        ``sources``: if given, only these publishers (header ``src``) may publish on ``key`` —
        a collection of service ids, or ``trusted(key, source) -> bool``; messages from any other
        source are rejected and counted (``foreign``) before the sequence check.

        ``polled``: the messages wait in a ring buffer in zenoh (:data:`POLL_CAPACITY`, the
        oldest dropped beyond it, and counted as lost) until :meth:`poll`, which runs the same
        checks and calls ``callback`` on the polling thread. For a service that looks at a stream
        at its own tick (staleness, counts): no thread wake-up and GIL hand-over per message,
        which costs more CPU here than the message's own handling. ``keep``: the buffer's size — a
        fast stream read for its newest value at a slower tick keeps a few (the rest are dropped
        unread: neither checked nor decoded, counted as lost by the sequence).

        ``latest``: also query ``key`` once, right after subscribing, and deliver the replies of
        ``latest`` outlets (``outlet(..., latest=True)``) through the same checks: a state stream's
        current value arrives at once, not at its next publication. A reply that is not newer than
        what the subscription already delivered is dropped without being counted. Not with
        ``polled``.
        """
        if latest and polled:
            raise ValueError("subscribe: latest and polled do not go together")
        # Per-key bookkeeping lives in ``self.streams``; a second subscription to the same key
        # expression gets its own table (else it would see every message as a duplicate).
        table = self.streams if key not in self._subscribed else StreamTable()
        self._subscribed.add(key)
        if sources is None or callable(sources):
            trusted = sources
        else:
            allowed = frozenset(sources)

            def trusted(key: str, source: str) -> bool:
                return source in allowed

        def on_sample(sample: Any, rx_ns: int = 0, bind: bytes = b"") -> None:
            queried = bool(bind)  # a latest value answering our own query (bound to it)
            k = str(sample.key_expr)
            stats = table.get(k)
            payload = sample.payload.to_bytes()
            att = sample.attachment
            try:  # authentication first: nothing of a forged message is looked at
                who = verify(self.keyring, REPLY if queried else PUT, k, payload, _raw(att), bind=bind)
                if is_sealed(payload):  # (a datagram stream's)
                    payload = unseal(self.keyring, who.signer, k, payload)
            except AuthError as exc:
                self._unauthenticated(stats, k, _raw(att), str(exc))
                return
            try:
                msg = decode_as(payload, cls)
            except Exception as exc:  # MessageError; anything else is a decoder bug, still rejected
                with self._lock:
                    stats.rejected += 1
                    bad = stats.rejected - stats.foreign
                if not isinstance(exc, MessageError):
                    log.error("decoder bug on %s (message rejected): %r", k, exc)
                elif bad <= 5 or bad % 1000 == 0:
                    log.warning("rejected message on %s (%d so far): %s", k, bad, exc)
                return
            if msg.header.source != who.signer:
                self._unauthenticated(stats, k, _raw(att), f"signer {who.signer!r} is not the header src")
                return
            if trusted is not None and not trusted(k, msg.header.source):
                with self._lock:
                    stats.rejected += 1
                    stats.foreign += 1
                if stats.foreign <= 5 or stats.foreign % 1000 == 0:
                    log.warning(
                        "rejected %s from %r on %s: not an allowed source", cls.TYPE, msg.header.source, k
                    )
                return
            h = msg.header
            with self._lock:
                win = stats.senders.get(who.signer)
                if win is None:
                    win = stats.senders[who.signer] = SenderWindow()
                if queried and win.sid == who.sid and h.seq <= win.top:
                    return  # a queried current value the subscription has delivered already
                why = self.fresh.put_problem(
                    who.signer, win, who.sid, h.seq, h.stamp_ns, wall_ns(), bound=queried
                )
                fresh = False
                if why and win.sid == who.sid and h.seq in stats.seq.holes and stats.source == who.signer:
                    # a number the stream skipped, arriving late (e.g. two threads putting on one
                    # outlet): dropped and counted as reordered, as ever — not a replay
                    stats.accept(h.source, h.seq, rx_ns, who.sid, h.stamp_ns)
                    why = ""
                elif why:
                    stats.rejected += 1
                    stats.replayed += 1
                else:
                    fresh = stats.accept(h.source, h.seq, rx_ns, who.sid, h.stamp_ns)
                    if fresh:
                        self.fresh.took(win, who.sid, h.seq, h.stamp_ns)
            if why:
                self._replayed(stats, k, who.signer, why)
            if not fresh:
                return
            if calls := self.presence.authenticated(who.signer, who.sid):
                self.presence.run(calls)
            try:
                callback(msg, k)
            except Exception:  # a bug in a handler must not kill the zenoh callback thread
                log.exception("handler for %s failed", k)

        if polled:
            import zenoh

            if not 1 <= keep <= POLL_CAPACITY:
                raise ValueError(f"subscribe: keep={keep} outside [1, {POLL_CAPACITY}]")
            sub = self.session.declare_subscriber(key, zenoh.handlers.RingChannel(keep))
            self._polled.append((sub, on_sample))
            self._inputs.append(sub)
        else:
            self._inputs.append(self.session.declare_subscriber(key, on_sample))
        if latest:
            import zenoh

            latest_att = self.signer.attach(QUERY, key, b"")

            def on_reply(reply: Any) -> None:
                if reply.ok is not None and not self._closed:
                    on_sample(reply.ok, bind=latest_att)

            # every reply (no consolidation): a stranger's answer must not hide the genuine one
            self.session.get(  # (returns at once: replies come to on_reply)
                key,
                on_reply,
                attachment=latest_att,
                timeout=2.0,
                consolidation=zenoh.ConsolidationMode.NONE,
            )

    def received(self, key: str) -> float:
        """When the message being handled on ``key`` arrived (monotonic s); for a polled stream
        that is the previous poll, the earliest it can have come; now if nothing is recorded."""
        return self.streams.get(key).last_rx_ns / 1e9 or time.monotonic()

    def poll(self, limit: int | None = None) -> int:
        """Deliver what the ``polled`` subscriptions buffered since the last call; returns the count.

        A buffered message counts as received at the previous poll (the earliest it can have
        come), so a stream's age is never under-estimated by the polling interval. ``limit``: at
        most this many messages per subscription in this call (the rest wait for the next; beyond
        the buffer the oldest are dropped and counted lost) — a process starved of CPU whose
        streams arrive faster than it checks them still returns; None: until each is empty. Call
        it from one thread at a time (each service polls from its own loop)."""
        now = time.monotonic_ns()
        since = self._last_poll_ns or now
        self._last_poll_ns = now
        n = 0
        for sub, on_sample in self._polled:
            k = 0
            while (limit is None or k < limit) and (sample := sub.try_recv()) is not None:
                on_sample(sample, since)
                k += 1
            n += k
        self._polled_ns = time.monotonic_ns()
        return n

    def serve(
        self,
        key: str,
        cls: type[M],
        handler: Callable[[M], Message],
        *,
        sources: Collection[str] | None = None,
    ) -> None:
        """Answer queries on ``key``: each request payload is strictly decoded as ``cls``.

        ``handler(request) -> reply message`` runs on a zenoh thread. A malformed request, a
        request from a source not in ``sources``, or a handler exception is answered with a
        zenoh error reply naming the problem (and counted in ``streams`` under ``key``); it never
        reaches the handler twice and never crashes the service. A handler that raises
        :class:`~telesurg.shared.errors.AuthorityError` (the operator authority refused the
        request) is answered ``refused: <reason>`` the same way, counted as rejected.
        """
        allowed = frozenset(sources) if sources is not None else None

        def on_query(query: Any) -> None:
            stats = self.streams.get(key)
            payload = query.payload
            k = str(query.key_expr)
            att = query.attachment
            raw = _raw(att)
            try:  # authentication first
                who = verify(self.keyring, QUERY, k, payload.to_bytes() if payload is not None else b"", raw)
            except AuthError as exc:
                self._unauthenticated(stats, k, raw, str(exc))
                with contextlib.suppress(Exception):
                    query.reply_err(f"rejected: {exc}".encode())
                return
            try:
                if payload is None:
                    raise MessageError("empty request")
                req = decode_as(payload.to_bytes(), cls)
                if req.header.source != who.signer:
                    self._unauthenticated(stats, k, raw, f"signer {who.signer!r} is not the header src")
                    with contextlib.suppress(Exception):
                        query.reply_err(b"rejected: signer is not the header src")
                    return
                h = req.header
                if why := self.fresh.query_problem(who.signer, who.sid, h.seq, h.stamp_ns, wall_ns()):
                    with self._lock:
                        stats.rejected += 1
                        stats.replayed += 1
                    self._replayed(stats, k, who.signer, why)
                    with contextlib.suppress(Exception):
                        query.reply_err(f"rejected: {why}".encode())
                    return
                if allowed is not None and req.header.source not in allowed:
                    with self._lock:
                        stats.foreign += 1
                    raise MessageError(f"{req.header.source!r} may not send {cls.TYPE} here")
            except MessageError as exc:
                with self._lock:
                    stats.rejected += 1
                with contextlib.suppress(Exception):
                    query.reply_err(f"rejected: {exc}".encode())
                return
            with self._lock:
                stats.received += 1
            try:
                reply = handler(req)
            except AuthorityError as exc:  # the operator authority refused it: the reason, no trace
                with self._lock:
                    stats.rejected += 1
                with contextlib.suppress(Exception):
                    query.reply_err(f"refused: {exc}".encode())
                return
            except Exception as exc:  # a handler bug is answered, logged, and survived
                log.exception("handler for %s failed", key)
                with contextlib.suppress(Exception):
                    query.reply_err(f"handler error: {type(exc).__name__}: {exc}".encode())
                return
            out = reply.encode()
            with contextlib.suppress(Exception):  # the querier may have gone; bound to its query
                query.reply(
                    query.key_expr, out, attachment=self.signer.attach(REPLY, k, out, bind=raw or b"")
                )

        self._handles.append(self.session.declare_queryable(key, on_query))

    def request(self, key: str, msg: Message, reply_cls: type[M], timeout: float = 2.0) -> M:
        """Send ``msg`` as a query to ``key`` and return the strictly decoded reply.

        A reply counts only if it is signed for this query (bound to its attachment,
        :mod:`telesurg.shared.fresh`), decodes, is signed by its header ``src`` and is fresh; any
        other (a stranger's replayed reply) is counted under ``key`` (``replayed`` or
        ``unauthenticated``), reported, and skipped: the genuine reply may still come.

        Raises:
            TimeoutError: nobody answered within ``timeout`` s.
            AuthError: only replies that failed those checks came (the last one's reason).
            MessageError: the server refused the request (its reason), or the reply is malformed.
        """
        import zenoh

        payload = msg.encode()
        att = self.signer.attach(QUERY, key, payload)
        problem: AuthError | None = None
        for reply in self.session.get(
            key, payload=payload, attachment=att, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE
        ):
            if reply.ok is not None:
                sample = reply.ok
                body = sample.payload.to_bytes()
                a = _raw(sample.attachment)
                k = str(sample.key_expr)
                stats = self.streams.get(key)
                try:
                    who = verify(self.keyring, REPLY, k, body, a, bind=att)
                except AuthError as exc:
                    problem = AuthError(f"reply on {k}: {exc} (not a reply to this query)")
                    self._unauthenticated(stats, k, a, str(problem))
                    continue
                out = decode_as(body, reply_cls)
                if out.header.source != who.signer:
                    raise AuthError(f"reply signed by {who.signer!r} claims src {out.header.source!r}")
                if why := self.fresh.reply_problem(who.signer, out.header.stamp_ns, wall_ns()):
                    problem = AuthError(f"reply on {k} from {who.signer!r}: {why}")
                    with self._lock:
                        stats.rejected += 1
                        stats.replayed += 1
                    self._replayed(stats, k, who.signer, why)
                    continue
                return out
            err = reply.err
            raise MessageError(err.payload.to_string() if err is not None else "error reply")
        if problem is not None:
            raise problem
        raise TimeoutError(f"no reply on {key} within {timeout:g} s (is the service running?)")

    def watch_liveliness(self, pattern: str, callback: Callable[[str, bool], None]) -> None:
        """``callback(service, alive)`` when a service under ``pattern`` (``keys.alive(service)``
        or ``keys.alive()``) comes or goes, with history. Alive means: the token of the session
        whose messages this node authenticated is present (before anything of the service is
        authenticated: any token of it) — a token of another session, a stranger's, does not
        keep a dead service alive (:mod:`telesurg.shared.presence`)."""
        import zenoh

        service = self.keys.service_of_alive(pattern)
        if pattern not in self._liveliness_subs:
            self._liveliness_subs.add(pattern)

            def on_sample(sample: Any) -> None:
                svc, sid = self.keys.parse_alive(str(sample.key_expr))
                try:
                    raw = bytes.fromhex(sid)
                except ValueError:
                    raw = b""
                if not raw:
                    return  # not a token of a node (no session id): nobody's presence
                self.presence.run(self.presence.token(svc, raw, sample.kind == zenoh.SampleKind.PUT))

            sub = self.session.liveliness().declare_subscriber(pattern, on_sample, history=True)
            self._handles.append(sub)
        self.presence.run(self.presence.watch(lambda s: service in ("*", s), callback))

    def _on_clock_probe(self, probe: ClockProbe) -> ClockReply:
        received = wall_ns()
        return ClockReply(
            header=self._reply_seq.next(),
            probe_ns=probe.header.stamp_ns,
            received_ns=received,
            sent_ns=wall_ns(),
        )

    def clock_probe(self, service: str, timeout: float = 0.5) -> ClockSample | None:
        """One clock probe of ``service`` (its echo queryable): the four timestamps, or None if no
        signed answer came within ``timeout`` s."""
        probe = ClockProbe(header=self._probe_seq.next())
        try:
            reply = self.request(self.keys.echo(service), probe, ClockReply, timeout=timeout)
        except (TimeoutError, MessageError):  # (AuthError is a MessageError: a forged answer)
            return None
        t4 = wall_ns()
        if reply.probe_ns != probe.header.stamp_ns:
            return None  # (signed for this query, yet not about it: not a sample)
        return ClockSample(probe.header.stamp_ns, reply.received_ns, reply.sent_ns, t4)

    def echo_rtt(self, service: str, timeout: float = 0.5) -> float | None:
        """Round-trip time to ``service``'s echo queryable, s, the responder's own time taken out
        (None: no signed answer within timeout)."""
        s = self.clock_probe(service, timeout)
        return None if s is None else s.delay_ns / 1e9

    @property
    def rejected(self) -> int:
        """Messages rejected by the strict decoder so far, all keys."""
        return self.streams.rejected

    def _unauthenticated(self, stats: StreamStats, key: str, attachment: bytes | None, why: str) -> None:
        """Count a message that failed authentication and report it (at most one event per key
        per second, after the first five)."""
        with self._lock:
            stats.rejected += 1
            stats.unauthenticated += 1
            report = _report_due(self._auth_reported, key)
        if report and not self._closed:
            claimed = attachment_signer(attachment)
            with contextlib.suppress(Exception):  # the session may be closing
                self.event(
                    "unauthenticated",
                    f"rejected message on {key} (claimed signer {claimed!r}; "
                    f"{stats.unauthenticated} so far): {why}",
                    severity="warning",
                )

    def replayed(self, key: str, signer: str, why: str) -> None:
        """Count and report a message of ``signer`` on ``key`` a service refused as not fresh
        (e.g. an e-stop reset older than the latest e-stop)."""
        stats = self.streams.get(key)
        with self._lock:
            stats.rejected += 1
            stats.replayed += 1
        self._replayed(stats, key, signer, why)

    def _replayed(self, stats: StreamStats, key: str, signer: str, why: str) -> None:
        """Report a message refused by the freshness rules (counted by the caller): at most one
        event per key per second, after the first five. Never acted on otherwise."""
        with self._lock:
            report = _report_due(self._replay_reported, key)
        if report and not self._closed:
            with contextlib.suppress(Exception):  # the session may be closing
                self.event(
                    "replayed",
                    f"rejected message on {key} signed by {signer!r} ({stats.replayed} so far): {why}",
                    severity="warning",
                )

    def _heartbeat_loop(self) -> None:
        while not self._hb_stop.wait(0.5):
            try:
                self._heartbeat.put(
                    Heartbeat(
                        self._heartbeat.header(),
                        self.service,
                        time.monotonic() - self._start,
                        self.rejected,
                        (time.monotonic_ns() - self._polled_ns) / 1e9 if self._polled_ns else -1.0,
                        self.streams.replayed,
                        self.streams.lost,
                    )
                )
            except Exception:  # session closing under us
                return

    # -- lifetime -------------------------------------------------------------------------
    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        if self._closed:
            return
        self._hb_stop.set()
        self._hb_thread.join(timeout=1.0)
        for h in self._inputs:  # no more callbacks from here on
            with contextlib.suppress(Exception):  # already undeclared
                h.undeclare()
        self._closed = True
        self._token.undeclare()
        for h in self._handles:
            with contextlib.suppress(Exception):
                h.undeclare()
        self._inputs.clear()
        self._polled.clear()
        self._handles.clear()
        self.session.close()  # type: ignore[no-untyped-call]
        if self._datagram is not None:
            self._datagram.close()

    def __enter__(self) -> Node:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
