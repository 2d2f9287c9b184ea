"""``telesurg console``: the operator console, a terminal UI (textual) for a local or remote site.

Per arm it shows what the slave, the watchdog and the mapping report — operating state, control
mode, follow / hold reason, lease, the clutch pedal, the mapping's teleop state (DISABLED / IDLE /
ENGAGING / ENABLED / HOLDING with its reason, since when, the operator's scale), the
motion-scale factor, latency p50/p99 over the watchdog's window (1 s), the safety state with its
causes and the arm's last events — and lets the operator act:

* **clutch / engage / disengage**: the console is a clutch pedal for the arm's master. It
  publishes its clutch on ``telesurg/<site>/console/<master>/clutch`` (a ``MasterButtons`` from
  the console's service id, on every change and at ``clutch_hz``); master_capture ORs it with the
  device's own pedal. A terminal sees no key release, so the keyboard clutch is a toggle.
* **operator commands** on ``slave/<arm>/command`` (trocar, posture, insert, remove, jog, stop,
  abort, motion mode, teach point, play …, see ``docs/trocar.md``), by key or typed on the
  command line; every reply is logged and every refusal is shown with its reason; a
  motion-starting command (PTP, jog, insert / remove, playback, mode changes, VIP) is answered
  ``confirm required`` by the server: the console shows the server's summary as a yes/no question
  and sends the command again with the server's token only on yes (``ConsoleModel.confirm``);
  the console's service id (``console``) is the operator identity of ``[site.authority]``;
* **scale up / down**: ``scale_up`` / ``scale_down`` to the mapping's ``mapping/<arm>/command``;
* **e-stop and reset** on ``estop`` (reset asks for confirmation), re-sent until the watchdog
  confirms.

Bus work (subscriptions, the clutch publisher, command requests in a small thread pool) lives in
:class:`ConsoleModel`; zenoh callbacks only store the latest message. The teleop state is asked
of the mapping when the console starts (``mapping/<arm>/teleop_state`` answers a query with the
current state) and then follows its 10 Hz stream, so a console started after an engage shows the
mapping engaged at once. The UI
(:mod:`telesurg.services.console.app`) redraws from a snapshot at 10 Hz.

Examples::

    telesurg console --connect tcp/127.0.0.1:7447                      # local site, arm1 ← m1
    telesurg console --site lab --arm m1:arm1 --arm m2:arm2 --connect tls/slave-host:7447 \\
        --tls-ca certs/ca.pem --tls-cert certs/console.pem --tls-key certs/console.key --mtls
    deploy/console.sh slave-host                                        # the same, with master_capture
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable, Sequence

from telesurg.services.console.model import (
    JOG_AXES,
    JOG_FRAMES,
    ArmState,
    ConsoleConfig,
    ConsoleModel,
    Notice,
    console_clutch_key,
    parse_arm,
)
from telesurg.shared.bus import Node, add_bus_args, bus_from_args
from telesurg.shared.config import config_help, load_config
from telesurg.shared.errors import TelesurgError

log = logging.getLogger(__name__)

__all__ = [
    "JOG_AXES",
    "JOG_FRAMES",
    "ArmState",
    "ConsoleConfig",
    "ConsoleModel",
    "Notice",
    "console_clutch_key",
    "main",
    "parse_args",
    "parse_arm",
    "run",
]


def parse_args(argv: Sequence[str] | None) -> tuple[ConsoleConfig, str]:
    """Config from ``--config FILE``, ``--set``, ``--site``, ``--arm`` and the zenoh flags."""
    ap = argparse.ArgumentParser(
        prog="telesurg console",
        description=__doc__,
        epilog=config_help(ConsoleConfig),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--config", metavar="FILE", help="site file (its [console] table) or a TOML file")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    ap.add_argument("--site", help="site id (default: local)")
    ap.add_argument(
        "--arm",
        action="append",
        metavar="[MASTER:]ARM",
        help="an arm to show and drive, e.g. arm1 or m1:arm1 (repeatable; default m1:arm1)",
    )
    ap.add_argument("--log-file", default="", help="write the console's log here (the terminal is the UI)")
    ap.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    ap.add_argument(
        "--web",
        action="store_true",
        help="the web surgeon console instead of the terminal UI: serves the page (and its browser "
        "masters) on web.host:web.port (telesurg.services.console.web)",
    )
    ap.add_argument("--port", type=int, help="with --web: the page's TCP port (web.port, default 8470)")
    ap.add_argument("--table", default=None, help="site-file table to read (default: console)")
    ap.add_argument("--parent-pid", type=int, default=0, help="stop when this process is gone (launcher)")
    ap.add_argument("--plugin", action="append", default=[], metavar="FILE", help="robot plugin file")
    add_bus_args(ap)
    a = ap.parse_args(argv)
    if a.plugin:
        from telesurg.shared import robots

        for plugin in a.plugin:
            robots.load_plugin(plugin)
    cfg = load_config(ConsoleConfig, a.config, a.set, table=a.table)
    if a.port is not None:
        cfg.web.port = a.port
    WEB_FLAGS.update(web=a.web, parent_pid=a.parent_pid)
    if a.site:
        cfg.site = a.site
    if a.arm:
        cfg.arms = list(a.arm)
    cfg.bus = bus_from_args(a, cfg.bus)
    cfg.bus.validate()
    cfg.validate()
    level = getattr(logging, a.log_level.upper(), logging.INFO)
    if a.web:  # the terminal is free: log there (or to --log-file)
        logging.basicConfig(
            level=level,
            filename=a.log_file or None,
            format=f"%(asctime)s {cfg.service} %(levelname)s %(name)s: %(message)s",
        )
    elif a.log_file:
        logging.basicConfig(
            level=level,
            filename=a.log_file,
            format=f"%(asctime)s {cfg.service} %(levelname)s %(name)s: %(message)s",
        )
    else:  # nothing may write to the terminal under the UI
        logging.basicConfig(level=logging.CRITICAL + 1, handlers=[logging.NullHandler()])
    return cfg, a.log_file


#: flags of the last :func:`parse_args` that are not config: --web, --parent-pid
WEB_FLAGS: dict[str, int] = {"web": False, "parent_pid": 0}


def run(cfg: ConsoleConfig, ui: Callable[[ConsoleModel], None] | None = None) -> None:
    """Open the node and the model, run the UI until the operator quits, close everything."""
    if ui is None:
        from telesurg.services.console.app import run_app

        ui = run_app
    with Node(cfg.bus, cfg.site, cfg.service) as node:
        model = ConsoleModel(cfg, node)
        try:
            ui(model)
        finally:
            model.close()


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg console``: 0 on quit, 1 on a connection error, 2 on a config error."""
    try:
        cfg, _ = parse_args(argv)
    except TelesurgError as exc:
        print(f"telesurg console: {exc}", file=sys.stderr)
        return 2
    try:
        if WEB_FLAGS["web"]:
            from telesurg.services.console.web import run_web

            run_web(cfg, parent_pid=WEB_FLAGS["parent_pid"])
        else:
            run(cfg)
    except ConnectionError as exc:
        print(f"telesurg console: {exc}", file=sys.stderr)
        return 1
    except TelesurgError as exc:  # e.g. no keyring: what to do, in one line
        print(f"telesurg console: {exc}", file=sys.stderr)
        return 2
    log.info("console %s (pid %d) stopped", cfg.service, os.getpid())
    return 0
