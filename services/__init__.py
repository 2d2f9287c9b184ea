"""telesurg services: one subpackage per process, and the one table that names them.

:data:`SERVICES` has a row per site process (:class:`Service`); :data:`COMMANDS` a row per other
``telesurg`` command (:class:`Command`). The CLI's commands (``services/cli.py``), the launcher's
start and stop order, priorities and session ids (``services/launcher``) and the packaged
modules are derived from them; nothing else lists the services. Adding a service is one row here
plus its package (docs/extending.md, "Add a service").

Example::

    Service("mirror", "stream everything to rerun (web viewer or .rrd)", "MirrorConfig",
            start=4, stop=7, best_effort=True)
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
    start: int  # start order (the router is 0: first)
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


@dataclass(frozen=True)
class Command:
    """A ``telesurg`` command that is not a site process: ``module`` has ``main(argv) -> int``."""

    name: str
    module: str
    help: str
    own_session: bool = False  # from the command line it runs in a session (autogroup) of its own
    extra: str = ""  # the optional dependencies it needs: ``pip install 'telesurg[<extra>]'``


SERVICES: tuple[Service, ...] = (
    Service(
        ROUTER, "zenoh router for a site (Python process, no zenohd)", "RouterConfig", 0, 8, control=True
    ),
    Service(
        "watchdog",
        "grant slave leases while every service is healthy",
        "WatchdogConfig",
        start=1,
        stop=4,
        control=True,
        zid=True,
    ),
    Service(
        "slave_control",
        "run the slave arm (MuJoCo) under a lease",
        "SlaveControlConfig",
        start=2,
        stop=5,
        control=True,
        zid=True,
    ),
    Service(
        "mapping",
        "master pose → slave joint setpoints (clutch, scale, IK)",
        "MappingConfig",
        start=3,
        stop=3,
        control=True,
        zid=True,
    ),
    Service(
        "mirror",
        "stream everything to rerun (web viewer or .rrd)",
        "MirrorConfig",
        start=4,
        stop=7,
        best_effort=True,
    ),
    Service(
        "master_capture",
        "publish a master device's pose and buttons",
        "MasterCaptureConfig",
        start=5,
        stop=2,
        control=True,
        zid=True,
    ),
    Service(
        "camera",
        "the endoscope view: MuJoCo render or a real camera → JPEG frames",
        "CameraConfig",
        start=6,
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
        start=7,
        stop=1,
        on_request=True,
        args=("--web",),
    ),
)

_S = "telesurg.services"
_T = "telesurg.tools"
COMMANDS: tuple[Command, ...] = (
    Command(
        "up", f"{_S}.launcher", "start router + all services locally; Ctrl-C stops all", own_session=True
    ),
    Command("demo", f"{_S}.launcher.demo", "the whole simulated teleop session (scripted circle)", True),
    Command("site", f"{_S}.launcher.site", "write the packaged site files to DIR (init), check one"),
    Command("estop", f"{_S}.estop", "e-stop (or --reset) one arm or every arm of a site"),
    Command("cmd", f"{_S}.command", "send an operator command (trocar mode, jog, …) to a slave arm"),
    Command("certs", f"{_S}.certs", "make a CA and per-identity certificates for mutual TLS"),
    Command("keys", f"{_S}.keys", "the site keyring that authenticates every message (init, list, …)"),
    Command("record", f"{_S}.record", "record every message of a site into an MCAP file"),
    Command("replay", f"{_S}.record.replay", "replay a recording's master streams into a live site, compare"),
    Command(
        "export", f"{_S}.record.export", "a recording in Foxglove / ROS 2 schemas (MCAP) or as a rerun .rrd"
    ),
    Command("view", f"{_S}.camera.view", "show a site's live camera picture in a small web page"),
    Command("bridge", f"{_S}.bridge", "bridge ros2: an arm's CRTK topics for ROS 2 (rmw_zenoh)"),
    Command("docs", f"{_S}.docs", "regenerate (or --check) the docs pages built from the code"),
    # tools beside the runtime (tools/): the runtime never imports them
    Command("bench", f"{_T}.bench", "fault-injection and fuzz benchmarks (tables + JSON)", True, "lab"),
    Command(
        "experiment",
        f"{_T}.experiment",
        "reproduce a paper's evaluation (figures + metrics.json)",
        extra="lab",
    ),
    Command("impair", f"{_T}.bench.impair", "userspace TCP link impairer (cut / delay) for fault tests"),
    Command("device", f"{_T}.emulate", "serial device tools: emulate an encoder board on a pty, monitor one"),
)
