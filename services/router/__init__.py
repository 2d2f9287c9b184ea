"""The site's zenoh router, as a Python process (no zenohd needed).

Besides routing, the router is where the site bounds what a client can send and says what it
refused (docs/security.md):

* **size caps** (zenoh's ``low_pass_filter`` interceptor, on ingress): a put, query or reply on a
  control or service key (:data:`CAPPED_CLASSES`) larger than ``max_message_bytes`` (payload +
  attachment; default the decoders' 64 KiB limit + 1 KiB for an authenticator) is dropped where it
  enters, before it is delivered to any subscriber; bulk keys (:data:`BULK_CLASSES`: camera
  frames) have their own, larger ``max_bulk_bytes``;
* **link guard** (services/router/linkguard.py): a client link (TCP connection) that receives
  more than ``link_rx_budget_mb_s`` on average, beyond a burst of ``link_rx_burst_mb``, is shut
  down, so zenoh closes that session: a flooder's megabytes stop crossing the host. The new links
  of a session cut before (a zenoh client reconnects by itself; its session id from the router's
  admin space) are cut at once for ``link_cooldown_s``, doubling per cut. Each cut is logged and
  published as a ``link_cut`` event on ``events/router`` naming the link and the session;
* **control streams never wait for an observer** (:func:`congestion_rules`): a control stream
  is published with ``CongestionControl.BLOCK``, so without a rule the router waits — up to 5 s,
  for every subscriber alike — whenever one subscriber's link cannot take the next sample: a
  viewer, recorder or console that falls behind (starved at low priority, hung, or hostile) then
  holds up the samples of every other subscriber too, the mapping's and the slave's, and the
  watchdog HOLDs. With ``control_zids`` (the launcher fills it: it gives each control service a
  zenoh session id) the router keeps BLOCK only towards those sessions and sends the control
  streams to every other subscriber as ``DROP``: a subscriber that does not keep up loses samples
  (it sees the sequence gaps), the control path does not wait for it;
* **diagnostics** (services/router/zlog.py): ``acl_log = "denied"`` logs access-control denials
  only (``"all"``: every decision), refused TLS handshakes are always logged with the peer and
  the reason.

Example::

    telesurg router --listen tcp/127.0.0.1:7447
    telesurg router --listen tls/0.0.0.0:7447 --tls-ca ca.pem --tls-cert s.pem --tls-key s.key \\
        --mtls --acl deploy/slave-site/acl.json5 --set acl_log='"denied"'
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from telesurg.services.common import service_main
from telesurg.services.router.linkguard import LinkCut, LinkGuard
from telesurg.services.router.zlog import ACL_MODES, ZenohLogRelay
from telesurg.shared.bus import BusConfig, valid_zid
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import MAX_PAYLOAD_BYTES

log = logging.getLogger(__name__)

#: key classes (under telesurg/<site>/) capped at ``max_message_bytes``: every control stream,
#: command, state and service stream the decoders read (their limit is MAX_PAYLOAD_BYTES)
CAPPED_CLASSES = (
    "master/**",
    "slave/**",
    "safety/**",
    "mapping/**",
    "console/**",
    "estop",
    "echo/**",
    "events/**",
    "heartbeat/**",
)
#: key classes with the larger ``max_bulk_bytes`` (camera frames)
BULK_CLASSES = ("camera/**",)
CAPPED_MESSAGES = ("put", "delete", "query", "reply")


@dataclass
class RouterConfig:
    """Router process config."""

    site: str = "local"  # key prefix telesurg/<site> of the router's events (link guard)
    service: str = "router"  # instance id for logs
    bus: BusConfig = field(default_factory=lambda: BusConfig(mode="router", listen=["tcp/127.0.0.1:7447"]))
    # bytes (payload + attachment) a put/query/reply on a control or service key may have; larger
    # ones are dropped at the router's ingress. Default: the decoders' 64 KiB limit + 1 KiB for an
    # authenticator. 0 = no cap.
    max_message_bytes: int = MAX_PAYLOAD_BYTES + 1024
    # bytes a message on a bulk key (camera/**) may have: a 1080p RGB frame is 6.2 MB. 0 = no cap.
    max_bulk_bytes: int = 8 * 1024 * 1024
    # access-control log: "off", "denied" (denials only, at most 20 lines/s, the rest counted)
    # or "all" (every decision, DEBUG; megabytes a minute on a busy site)
    acl_log: str = "off"
    # zenoh's shared-memory transport on the router's links (off): with it, zenoh 1.x maps the
    # 16 MiB SHM pool of every client on this host that sent it a message over 3 KiB
    # (transport/shared_memory/transport_optimization) and keeps it mapped after that client's
    # session ends — +16 MB of router RSS per such session (a flooder's included; measured,
    # docs/security.md#flood-memory-and-holds). The site's messages are small and cross loopback
    # TCP at ~1 GB/s; off, no client negotiates SHM with the router.
    shared_memory: bool = False
    # MB/s (10**6 bytes) a client link may send to the router on average (link guard,
    # services/router/linkguard.py); a link whose bucket of link_rx_burst_mb runs dry is shut down.
    # The busiest genuine link measured peaked at 0.28 MB/s, the camera at its defaults sends 0.14
    # (docs/security.md#link-guard-the-router-cuts-off-a-flooding-link); a 1 MiB flood 150-1500.
    # 0 = no guard.
    link_rx_budget_mb_s: float = 50.0
    # MB a link may send at once above the budget (a burst of camera frames, a recording's start)
    link_rx_burst_mb: float = 50.0
    # s between two looks at the links' byte counters: bounds what a flooder sends before the cut
    link_guard_period_s: float = 0.05
    # s a cut client session's new links are cut at once (it reconnects by itself), doubling with
    # each further cut of the same zenoh session up to link_max_cooldown_s. 0 = no cool-down.
    link_cooldown_s: float = 1.0
    link_max_cooldown_s: float = 60.0
    # zenoh session ids (hex) of the control services — the only subscribers a control stream
    # waits for (:func:`congestion_rules`); the launcher sets them. [] = every subscriber alike
    # (zenoh's default: one that stops reading holds up all, the router warns)
    control_zids: list[str] = field(default_factory=list)

    def validate(self) -> None:
        """Raise ConfigError naming the valid options."""
        if self.acl_log not in ACL_MODES:
            raise ConfigError(f"router acl_log {self.acl_log!r} invalid; valid: {', '.join(ACL_MODES)}")
        for name in ("max_message_bytes", "max_bulk_bytes"):
            value = getattr(self, name)
            if value != 0 and not 1024 <= value <= 1 << 30:
                raise ConfigError(f"router {name}={value} outside [1024, 2**30] (0 = no cap)")
        if self.link_rx_budget_mb_s != 0 and not 1.0 <= self.link_rx_budget_mb_s <= 10_000.0:
            raise ConfigError(
                f"router link_rx_budget_mb_s={self.link_rx_budget_mb_s} outside [1, 10000] MB/s "
                "(0 = no guard)"
            )
        if not 1.0 <= self.link_rx_burst_mb <= 10_000.0:
            raise ConfigError(f"router link_rx_burst_mb={self.link_rx_burst_mb} outside [1, 10000] MB")
        if not 0.0 <= self.link_cooldown_s <= self.link_max_cooldown_s <= 86_400.0:
            raise ConfigError(
                f"router link_cooldown_s={self.link_cooldown_s}, link_max_cooldown_s="
                f"{self.link_max_cooldown_s}: need 0 <= link_cooldown_s <= link_max_cooldown_s <= 86400"
            )
        for zid in self.control_zids:
            if not valid_zid(zid):
                raise ConfigError(
                    f"router control_zids: {zid!r} is not a zenoh id "
                    "(1-32 lowercase hex digits, no leading 0)"
                )
        if not 0.01 <= self.link_guard_period_s <= 1.0:
            raise ConfigError(f"router link_guard_period_s={self.link_guard_period_s} outside [0.01, 1] s")


def size_caps(cfg: RouterConfig, site: str = "*") -> list[dict[str, Any]]:
    """The zenoh ``low_pass_filter`` list of ``cfg`` (empty if both caps are 0)."""
    caps = []
    for cap_id, limit, classes in (
        ("control", cfg.max_message_bytes, CAPPED_CLASSES),
        ("bulk", cfg.max_bulk_bytes, BULK_CLASSES),
    ):
        if limit:
            caps.append(
                {
                    "id": f"size-cap-{cap_id}",
                    "flows": ["ingress"],
                    "messages": list(CAPPED_MESSAGES),
                    "key_exprs": [f"telesurg/{site}/{c}" for c in classes],
                    "size_limit": limit,
                }
            )
    return caps


#: batches of the router's REAL_TIME queue per link (zenoh's maximum; default 2): each express
#: sample is a batch, so this is how many control samples a link may have waiting
REAL_TIME_QUEUE = 16


def congestion_rules(control_zids: Sequence[str]) -> list[dict[str, Any]]:
    """zenoh ``qos/network`` rules of the router: control streams (``Priority.REAL_TIME`` puts,
    shared/bus.py ``Node.outlet``) leave the router as ``DROP`` towards every session, then as
    ``BLOCK`` again towards ``control_zids`` (zenoh applies the rules in this order). [] without
    control sessions: no rule, every subscriber blocks the stream alike."""
    if not control_zids:
        return []
    match = {"messages": ["put", "delete"], "flows": ["egress"], "qos": {"priority": "real_time"}}
    return [
        {"id": "observers-drop", **match, "overwrite": {"congestion_control": "drop"}},
        {
            "id": "control-block",
            "zids": list(control_zids),
            **match,
            "overwrite": {"congestion_control": "block"},
        },
    ]


def run(cfg: RouterConfig, stop: threading.Event) -> None:
    """Serve until ``stop``."""
    import zenoh
    from telesurg.shared.bus import zenoh_config

    cfg.validate()
    cfg.bus.mode = "router"
    relay = ZenohLogRelay(cfg.acl_log, cfg.bus.zenoh_log)
    relay.start()
    zenoh.init_log_from_env_or(relay.filter)
    cfg.bus.zenoh_log = ""  # initialised above
    caps = size_caps(cfg)
    z = zenoh_config(cfg.bus)
    if caps:
        z.insert_json5("low_pass_filter", json.dumps(caps))
    z.insert_json5("transport/shared_memory/enabled", json.dumps(cfg.shared_memory))
    if rules := congestion_rules(cfg.control_zids):
        z.insert_json5("qos/network", json.dumps(rules))
        # room for REAL_TIME_QUEUE express samples a link (zenoh's default 2): a router thread a
        # few ms late drops nothing for a subscriber that keeps up, and blocks no control stream
        z.insert_json5("transport/link/tx/queue/size/real_time", json.dumps(REAL_TIME_QUEUE))
    if cfg.link_rx_budget_mb_s and cfg.link_cooldown_s:
        # the link guard asks its own session which client session is at a link address; a client
        # reaches the admin space (@/**) only where the ACL lets it query that (the site's: no)
        z.insert_json5(
            "adminspace", json.dumps({"enabled": True, "permissions": {"read": True, "write": False}})
        )
    try:
        session = zenoh.open(z)
    except zenoh.ZError as exc:
        raise ConnectionError(f"zenoh router failed (listen={cfg.bus.listen}): {exc}") from exc
    log.info(
        "router %s listening on %s; size caps %s; acl log %s; shared memory %s",
        session.zid(),
        ", ".join(ep.partition("#")[0] for ep in cfg.bus.listen),
        ", ".join(f"{c['id']} {c['size_limit']} B" for c in caps) or "off",
        cfg.acl_log,
        "on" if cfg.shared_memory else "off",
    )
    if cfg.control_zids:
        log.info(
            "control streams wait only for the %d control sessions (%s); other subscribers get them as DROP",
            len(cfg.control_zids),
            ", ".join(cfg.control_zids),
        )
    else:
        log.warning(
            "no control_zids: a subscriber of a control stream that stops reading holds it up for "
            "every other subscriber (the launcher sets them; docs/deploy.md)"
        )
    guard = None
    if cfg.link_rx_budget_mb_s:
        report = link_cut_reporter(session, cfg)
        guard = LinkGuard(
            cfg.link_rx_budget_mb_s,
            cfg.link_rx_burst_mb,
            report,
            cfg.link_guard_period_s,
            identify=link_sessions(session) if cfg.link_cooldown_s else None,
            cooldown_s=cfg.link_cooldown_s,
            max_cooldown_s=cfg.link_max_cooldown_s,
        )
        guard.start()
        log.info(
            "link guard: %g MB/s a link, burst %g MB, every %g s",
            cfg.link_rx_budget_mb_s,
            cfg.link_rx_burst_mb,
            cfg.link_guard_period_s,
        )
    try:
        stop.wait()
    finally:
        if guard is not None:
            guard.stop()
            busiest = sorted(guard.peaks(cut=False).items(), key=lambda kv: -kv[1][0])[:8]
            log.info(
                "link guard: %d links cut; busiest links not cut (peak MB/s over 0.5 s, MB in all): %s",
                guard.n_cuts,
                ", ".join(f"{peer} {rate} MB/s {mb} MB" for peer, (rate, mb) in busiest) or "none",
            )
        session.close()  # type: ignore[no-untyped-call]
        log.info(
            "router stopped: %d ACL denials, %d refused TLS handshakes", relay.denied, relay.tls_failures
        )


def link_sessions(session: Any) -> Callable[[list[str]], dict[str, str]]:
    """The link guard's look-up: peer addresses (``host:port``) -> the zenoh session id of the
    client at each, from the router's admin space (``@/<zid>/router``: each session's links)."""
    key = f"@/{session.zid()}/router"

    def identify(peers: list[str]) -> dict[str, str]:
        wanted = set(peers)
        out: dict[str, str] = {}
        for reply in session.get(key, timeout=1.0):
            if reply.ok is None:
                continue
            for s in json.loads(reply.ok.payload.to_bytes()).get("sessions", []):
                for link in s.get("links", []):
                    addr = str(link.get("dst", "")).partition("/")[2].partition("#")[0]
                    if addr in wanted:
                        out[addr] = str(s.get("peer", ""))
        return out

    return identify


def link_cut_reporter(session: Any, cfg: RouterConfig) -> Callable[[LinkCut], None]:
    """What the link guard does with a cut: log it (WARNING) and publish a ``link_cut`` event
    (severity ``warning``) on ``events/router``, signed as ``router`` like every service's events
    — if the router has a keyring (``--keyring``; ``telesurg up`` gives it the site's). Without
    one the cut is only logged."""
    from telesurg.shared.auth import Keyring, Signer, default_keys_dir
    from telesurg.shared.bus import Outlet
    from telesurg.shared.keys import Keys
    from telesurg.shared.messages import SafetyEvent

    outlet: Outlet | None = None
    try:
        keyring = Keyring.load(cfg.bus.keys_dir or default_keys_dir(cfg.site))
        signer = Signer(cfg.service, keyring.ensure(cfg.service), links=keyring.send_keys())
        key = Keys(cfg.site).events(cfg.service)
        outlet = Outlet(session.declare_publisher(key), cfg.service, signer, key)
    except ConfigError as exc:
        log.warning("link guard: cuts are logged, not published as events (%s)", exc)

    def report(cut: LinkCut) -> None:
        log.warning("link_cut: %s", cut.describe())
        if outlet is not None:
            outlet.put(SafetyEvent(outlet.header(), "", "link_cut", "warning", cut.describe()))

    return report


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg router``."""
    return service_main("router", RouterConfig, run, argv, __doc__ or "")
