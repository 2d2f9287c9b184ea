"""The site's zenoh router, as a Python process (no zenohd needed).

Example::

    telesurg router --listen tcp/127.0.0.1:7447
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field

from telesurg.services.common import service_main
from telesurg.shared.bus import BusConfig, open_session

log = logging.getLogger(__name__)


@dataclass
class RouterConfig:
    """Router process config."""

    site: str = "local"  # unused by the router itself; kept for a uniform CLI
    service: str = "router"  # instance id for logs
    bus: BusConfig = field(default_factory=lambda: BusConfig(mode="router", listen=["tcp/127.0.0.1:7447"]))


def run(cfg: RouterConfig, stop: threading.Event) -> None:
    """Serve until ``stop``."""
    cfg.bus.mode = "router"
    session = open_session(cfg.bus)
    log.info("router %s listening on %s", session.zid(), ", ".join(cfg.bus.listen))
    try:
        stop.wait()
    finally:
        session.close()  # type: ignore[no-untyped-call]


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg router``."""
    return service_main("router", RouterConfig, run, argv, __doc__ or "")
