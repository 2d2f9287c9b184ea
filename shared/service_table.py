"""The service table: one row (:class:`Service`) per process a site runs.

The CLI's service commands (``services/cli.py``), the launcher's start and stop order, priorities
and session ids (``services/launcher``) and the site file's tables (:mod:`telesurg.shared.config`)
are derived from it; nothing else lists the services. Adding a service is one row here plus its
package ``services/<name>/`` (docs/extending.md, "Add a service").

Example::

    Service("mirror", "stream everything to rerun (web viewer or .rrd)", "MirrorConfig",
            start=1, stop=7, best_effort=True)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

#: The site's router: started first (the others connect to it), stopped last.
ROUTER = "router"


@dataclass(frozen=True)
class Service:
    """One process a site runs (``telesurg up`` starts it; ``telesurg <cli>`` runs it alone).

    Its package is ``telesurg.services.<name>`` with ``main(argv) -> int`` and the config class
    ``config`` (a dataclass read from the site file's ``[<name>]`` table)."""

    name: str  # package and site-file table name, e.g. "slave_control"
    help: str  # one line for ``telesurg --help``
    config: str  # its config dataclass, in its package
    start: int  # start stage (the router is 0: first); one stage's services start together
    stop: int  # stop order (1 stops first)
    control: bool = False  # control path: the launcher raises its priority (CONTROL_NICE)
    zid: bool = False  # the router waits for its session when a control stream's subscriber lags
    best_effort: bool = False  # steps down to the best-effort nice once up
    optional: bool = False  # the site runs without it when it cannot start
    # what the other services are set to when this optional one is off: service → ["key=value"]
    without: Mapping[str, tuple[str, ...]] = field(default_factory=lambda: MappingProxyType({}))
    on_request: bool = False  # started only when asked for (after the others)
    args: tuple[str, ...] = ()  # flags the launcher adds to its command line

    @property
    def cli(self) -> str:
        """Its ``telesurg`` command: the name with dashes (``slave-control``)."""
        return self.name.replace("_", "-")

    @property
    def module(self) -> str:
        """Its package."""
        return f"telesurg.services.{self.name}"


SERVICES: tuple[Service, ...] = (
    Service(
        ROUTER, "zenoh router for a site (Python process, no zenohd)", "RouterConfig", 0, 8, control=True
    ),
    Service(
        "watchdog",
        "grant slave leases while every service is healthy",
        "WatchdogConfig",
        start=1,
        stop=2,
        control=True,
        zid=True,
    ),
    Service(
        "slave_control",
        "run the slave arm (MuJoCo) under a lease",
        "SlaveControlConfig",
        start=1,
        stop=5,
        control=True,
        zid=True,
    ),
    Service(
        "mapping",
        "master pose → slave joint setpoints (clutch, scale, IK)",
        "MappingConfig",
        start=1,
        stop=4,
        control=True,
        zid=True,
    ),
    Service(
        "mirror",
        "stream everything to rerun (web viewer or .rrd)",
        "MirrorConfig",
        start=1,
        stop=7,
        best_effort=True,
    ),
    Service(
        "master_capture",
        "publish a master device's pose and buttons",
        "MasterCaptureConfig",
        start=2,
        stop=3,
        control=True,
        zid=True,
    ),
    Service(
        "camera",
        "the endoscope view: MuJoCo render or a real camera → JPEG frames",
        "CameraConfig",
        start=3,
        stop=6,
        best_effort=True,
        optional=True,
        without=MappingProxyType(
            {"watchdog": ('video_camera=""',), "mapping": ('camera=""',), "slave_control": ('camera=""',)}
        ),
    ),
    Service(
        "console",
        "operator console (terminal UI): state, clutch, commands, e-stop",
        "ConsoleConfig",
        start=4,
        stop=1,
        on_request=True,
        args=("--web",),
    ),
)
