"""``telesurg demo``: the whole simulated teleop session on this machine.

Starts the router and every service (scripted master drawing a circle, mapping, MuJoCo slave,
watchdog, mirror), serves the rerun web viewer and prints its URL; Ctrl-C stops everything.
Headless, it runs for ``--seconds`` and writes a report::

    telesurg demo --headless --seconds 20 --save out.rrd --report out.json

The report (strict JSON) holds per-stream message counts and sequence gaps, the tip tracking
error against the mapping's published target ``setpoint_cp`` (mean/max mm, after settling), the
motion scales and teleop states the mapping published (an operator's ``set_scale`` mid-session
included), the watchdog's transitions into HOLD / DEGRADED / ESTOP with their causes (what the
operator experienced) beside the slave's own fault holds; see
:mod:`telesurg.services.launcher.report`. The closing log line names both, e.g.
``watchdog [arm1]: 2 HOLD, 1 DEGRADED, 0 ESTOP (causes: HOLD: master/m1/measured_cp stale ×2;
DEGRADED: latency p90 # ms > budget # ms ×1); slave holds: 1``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from telesurg.services.common import install_stop_handlers, setup_logging, tcp_port
from telesurg.services.launcher import (
    Site,
    add_site_args,
    announce_login,
    config_class,
    console_url,
    spec_from_args,
    with_console,
)
from telesurg.services.launcher.report import SessionRecorder
from telesurg.shared import jsonio
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.config import load_config
from telesurg.shared.errors import TelesurgError
from telesurg.shared.pairs import parse_pair
from telesurg.shared.viewer import viewer_url

log = logging.getLogger("telesurg.demo")


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg demo``."""
    parser = argparse.ArgumentParser(
        prog="telesurg demo",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_site_args(parser)
    parser.add_argument("--headless", action="store_true", help="no viewer; needs --seconds")
    parser.add_argument("--save", metavar="FILE.rrd", help="also record the session to an .rrd")
    parser.add_argument("--report", metavar="FILE.json", help="write the session report here")
    parser.add_argument("--web-port", type=tcp_port, default=9090, help="rerun web viewer port")
    parser.add_argument("--grpc-port", type=tcp_port, default=9876, help="rerun gRPC port")
    parser.add_argument("--no-camera", action="store_true", help="run without the camera service (no video)")
    args = parser.parse_args(argv)
    setup_logging("INFO", "demo")
    if args.headless and args.seconds <= 0:
        print("telesurg demo: --headless needs --seconds N", file=sys.stderr)
        return 2
    services = ["watchdog", "slave_control", "mapping", "master_capture"]
    if not args.no_camera:
        services.insert(0, "camera")
    if not args.headless or args.save:
        services.append("mirror")
    if not args.headless:
        args.console = True  # the web surgeon console beside the rerun viewer
    services = with_console(args, services)
    try:
        spec = spec_from_args(args, services)
        overrides = spec.overrides.get("mapping", [])
        # the mapping config as the mapping will build it (the launcher checks each service's table
        # through its config class, by module name): only its pairs are used here
        mapping = load_config(config_class("mapping"), spec.site_file, overrides, table="mapping")
    except TelesurgError as exc:
        print(f"telesurg demo: {exc}", file=sys.stderr)
        return 2
    mirror = spec.overrides.setdefault("mirror", [])
    if args.save:
        mirror.append(f"save={json.dumps(str(Path(args.save).resolve()))}")
    if not args.headless:
        mirror += ["serve=true", f"web_port={args.web_port}", f"grpc_port={args.grpc_port}"]
    web_url = console_url(args, spec)
    if web_url:
        log.info("web surgeon console: %s", web_url)
    log.info("site file %s", spec.site_file)
    stop = threading.Event()
    install_stop_handlers(stop)
    master_arm, slave_arm = parse_pair(mapping.pairs[0])
    # checked with the router's before anything starts (Site.start)
    if web_url:
        spec.ports += (("the web console's port", args.console_port, "--console-port 0 picks a free one"),)
    if not args.headless:
        spec.ports += (
            ("the rerun web viewer's port", args.web_port, "--web-port picks another"),
            ("rerun's gRPC port", args.grpc_port, "--grpc-port picks another"),
        )
    try:
        with Site(spec) as site:
            bus = BusConfig(mode="client", connect=[spec.endpoint])
            with Node(bus, spec.site, "demo_report") as node:
                rec = SessionRecorder(node, master_arm, slave_arm)
                # --seconds of session once everything is up (start-up is not counted)
                deadline = time.monotonic() + args.seconds if args.seconds > 0 else float("inf")
                if not args.headless:
                    url = viewer_url(f"rerun+http://127.0.0.1:{args.grpc_port}/proxy", args.web_port)
                    print(f"\nrerun web viewer: {url}", flush=True)
                    print(
                        "  (without a GPU, the browser draws it with the CPU the demo leaves: start "
                        "Chromium with Mesa's llvmpipe, --use-angle=gl-egl --ignore-gpu-blocklist, "
                        "or --force-device-scale-factor=0.5 to keep near live; docs/performance.md)",
                        flush=True,
                    )
                    if web_url:
                        announce_login(web_url, site.login_token)
                    print("Ctrl-C stops everything.\n", flush=True)
                while not stop.wait(0.2) and time.monotonic() < deadline:
                    for name, rc in site.dead().items():
                        log.error("%s exited with code %d", name, rc)
                        stop.set()
                report = rec.report()
                rec.close()
            codes = site.stop()
    except (TelesurgError, ConnectionError) as exc:
        print(f"telesurg demo: {exc}", file=sys.stderr)
        return 1
    report["exit_codes"] = codes
    report["seconds"] = args.seconds
    report["site_file"] = str(spec.site_file)  # the site file every service read its table of
    err = report["tip_tracking_error_mm"]
    log.info(
        "tip tracking error (vs setpoint_cp): mean %s mm, max %s mm over %d samples; scale %s; "
        "engagements: %d; %s",
        err["mean_mm"],
        err["max_mm"],
        err["samples"],
        report["mapping"]["scale"],
        report["engagements"],
        report["summary"],
    )
    if args.report:
        out = Path(args.report)
        out.parent.mkdir(parents=True, exist_ok=True)  # as record --out: a fresh checkout has no out/
        out.write_text(jsonio.dumps(report, indent=2))
        log.info("report written to %s", args.report)
    return 0 if all(c == 0 for c in codes.values()) else 1
