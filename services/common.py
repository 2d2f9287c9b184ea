"""What every service process shares: argument parsing, logging, clean shutdown.

Each service provides a config dataclass (with ``site``, ``service`` and ``bus`` fields) and a
``run(cfg, stop)`` function that returns when ``stop`` is set. :func:`service_main` parses
``--config FILE`` (a site file, of which it reads the service's table — ``--table NAME``,
default the service's name — and the ``[site]`` facts; or the service's own TOML file),
``--set key=value`` and the zenoh flags, installs SIGINT/SIGTERM handlers and calls ``run``.
``SIGUSR1`` writes every thread's Python stack to stderr (the service's log) and the process
goes on: what a hung service is doing (the launcher asks for it before it kills a straggler).
``--help`` lists every config key with its type, default, unit and meaning (from the config
dataclass). Exit code 0 on a requested stop, 2 on a config error.
"""

from __future__ import annotations

import argparse
import faulthandler
import gc
import logging
import os
import signal
import socket
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any, Protocol, TypeVar

from telesurg.shared.bus import BusConfig, add_bus_args, bus_from_args
from telesurg.shared.clock import set_skew_ms
from telesurg.shared.config import config_help, load_config, service_table, site_plugins
from telesurg.shared.errors import TelesurgError

log = logging.getLogger("telesurg")


class ServiceConfig(Protocol):
    """Fields every service config has."""

    site: str
    service: str
    bus: BusConfig


C = TypeVar("C", bound=ServiceConfig)


def setup_logging(level: str, service: str) -> None:
    """One log format for every process: time, service, level, logger, message (stderr)."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format=f"%(asctime)s {service} %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


STACKS_SIGNAL = signal.SIGUSR1  # a service writes every thread's stack to its log on this signal


def install_stack_dump() -> None:
    """On :data:`STACKS_SIGNAL`, write every thread's Python stack to stderr and go on.

    ``faulthandler`` writes from the signal handler in C, without the GIL: it answers even when
    a thread is stuck holding the GIL or a lock, where a Python-level handler would never run.
    """
    faulthandler.register(STACKS_SIGNAL, file=sys.stderr, all_threads=True, chain=False)


def install_stop_handlers(stop: threading.Event) -> None:
    """SIGINT and SIGTERM set ``stop`` (a second signal exits at once); :data:`STACKS_SIGNAL`
    writes every thread's stack (:func:`install_stack_dump`)."""

    def handler(signum: int, frame: Any) -> None:
        if stop.is_set():
            os._exit(130)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    install_stack_dump()


def watch_parent(parent_pid: int, stop: threading.Event) -> None:
    """Set ``stop`` if the launcher that started us dies (no orphans after a launcher crash)."""

    def loop() -> None:
        while not stop.wait(0.5):
            if os.getppid() != parent_pid:
                log.warning("launcher %d is gone; stopping", parent_pid)
                stop.set()

    threading.Thread(target=loop, daemon=True, name="parent-watch").start()


def service_main(
    name: str,
    config_cls: type[C],
    run: Callable[[C, threading.Event], None],
    argv: Sequence[str] | None,
    description: str = "",
) -> int:
    """Parse flags into ``config_cls``, then ``run`` until SIGINT/SIGTERM."""
    from telesurg.shared import robots

    table = service_table(config_cls)
    parser = argparse.ArgumentParser(
        prog=f"telesurg {name}",
        description=description,
        epilog=config_help(config_cls, table)
        + (
            f"\n\n{robots.config_help()}"
            if "robot" in getattr(config_cls, "__dataclass_fields__", {})
            else ""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="site file (deploy/<site>/site.toml: its [site] facts and one table) or a TOML file of "
        "this service's keys alone",
    )
    parser.add_argument("--table", metavar="NAME", help=f"the site file's table to read (default: {table})")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key"
    )
    parser.add_argument("--site", help="site id (key prefix telesurg/<site>)")
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    parser.add_argument("--parent-pid", type=int, help=argparse.SUPPRESS)
    parser.add_argument(
        "--plugin",
        action="append",
        default=[],
        metavar="FILE",
        help="plugin: a Python file that registers robots, master devices or safety rules "
        "(docs/extending.md); repeatable",
    )
    add_bus_args(parser)
    args = parser.parse_args(argv)
    try:
        # the robot plugins (--plugin and the site file's [site] plugins) before the config: it may
        # name a plugin's robot
        for plugin in [*args.plugin, *site_plugins(args.config)]:
            robots.load_plugin(str(plugin))
        cfg = load_config(config_cls, args.config, args.set, table=args.table)
        if args.site:
            cfg.site = args.site
        cfg.bus = bus_from_args(args, cfg.bus)
        cfg.bus.validate()
        set_skew_ms(cfg.bus.clock_skew_ms)
    except TelesurgError as exc:
        print(f"telesurg {name}: {exc}", file=sys.stderr)
        return 2
    setup_logging(args.log_level, cfg.service)
    stop = threading.Event()
    install_stop_handlers(stop)
    if args.parent_pid:
        watch_parent(args.parent_pid, stop)
    gc.freeze()  # start-up objects never need collecting: shorter GC pauses in the loops
    try:
        run(cfg, stop)
    except (TelesurgError, ConnectionError) as exc:
        log.error("%s", exc)
        return 1
    log.info("stopped")
    return 0


def gl_backend() -> str:
    """The OpenGL backend MuJoCo's offscreen renderer can use here: ``MUJOCO_GL`` if set, else
    ``"egl"`` (libEGL) or ``"osmesa"`` (libOSMesa) as installed, ``""`` if neither is (the camera
    is then off). A library lookup only: nothing is loaded."""
    import ctypes.util

    chosen = os.environ.get("MUJOCO_GL", "")
    if chosen:
        return chosen
    for lib, backend in (("EGL", "egl"), ("OSMesa", "osmesa")):
        if ctypes.util.find_library(lib):
            return backend
    return ""


def check_port_free(host: str, port: int, what: str) -> None:
    """ConnectionError naming ``what`` if nothing can listen on ``host:port`` now (a port in
    TIME_WAIT counts as free, as for the servers, which set ``SO_REUSEADDR``). Port 0 is free."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ConnectionError(f"{what} {host}:{port} is not available: {exc.strerror or exc}") from exc


def tcp_port(text: str) -> int:
    """argparse type: a TCP port, 0–65535 (0: a free one is picked)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"port {port} outside 0..65535")
    return port


def duration_s(text: str) -> float:
    """argparse type: a duration in seconds, finite and ≥ 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 0.0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"{text} s: must be finite and >= 0")
    return value
