"""The site's zenoh router, as a Python process (no zenohd needed).

Besides routing, the router is where the site bounds what a client can send and says what it
refused (docs/security.md):

* **size caps** (zenoh's ``low_pass_filter`` interceptor, on ingress): a put, query or reply on a
  control or service key (:data:`CAPPED_CLASSES`) larger than ``max_message_bytes`` (payload +
  attachment; default the decoders' 64 KiB limit + 1 KiB for an authenticator) is dropped where it
  enters, before it is delivered to any subscriber; bulk keys (:data:`BULK_CLASSES`: camera
  frames) have their own, larger ``max_bulk_bytes``;
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
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from telesurg.services.common import service_main
from telesurg.services.router.zlog import ACL_MODES, ZenohLogRelay
from telesurg.shared.bus import BusConfig
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

    site: str = "local"  # unused by the router itself; kept for a uniform CLI
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

    def validate(self) -> None:
        """Raise ConfigError naming the valid options."""
        if self.acl_log not in ACL_MODES:
            raise ConfigError(f"router acl_log {self.acl_log!r} invalid; valid: {', '.join(ACL_MODES)}")
        for name in ("max_message_bytes", "max_bulk_bytes"):
            value = getattr(self, name)
            if value != 0 and not 1024 <= value <= 1 << 30:
                raise ConfigError(f"router {name}={value} outside [1024, 2**30] (0 = no cap)")


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
    try:
        stop.wait()
    finally:
        session.close()  # type: ignore[no-untyped-call]
        log.info(
            "router stopped: %d ACL denials, %d refused TLS handshakes", relay.denied, relay.tls_failures
        )


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg router``."""
    return service_main("router", RouterConfig, run, argv, __doc__ or "")
