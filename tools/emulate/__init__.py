"""``telesurg device``: tools for the master's encoder board and the slave's servo controller
(``docs/robots.md`` (Hardware)).

* ``emulate --pty`` — an emulated encoder board on a new pseudo-terminal: prints the device path
  (e.g. ``/dev/pts/7``) as the first line on stdout, then serves HELLO and SAMPLE frames of a
  scripted motion (:mod:`telesurg.tools.emulate.emulator`) until SIGINT/SIGTERM or ``--seconds``.
* ``emulate-slave --pty --model mh3f|plas|vip`` (or a robot of a ``--plugin FILE``) — an emulated
  joint-servo controller of a slave arm on a new pseudo-terminal
  (:mod:`telesurg.tools.emulate.servo_emulator`): prints the device path as the first line on
  stdout, then serves the servo protocol (HELLO, STATE; follows SETPOINTs with a lag and the speed
  limits; its own watchdog) with optional injected faults.
* ``check TYPE`` — opens a master device of that type (``spacemouse``, ``touch``, ``omega7``,
  ``gamepad``; also ``scripted``, ``serial``) with master_capture's config and prints its readings
  (position, orientation, clutch, valid) for ``--seconds``: a lab verifies a device in a minute.
  Without the device's library it says which package and vendor SDK it needs (exit 1).
* ``monitor`` — opens the port of a master_capture config (``serial.*`` keys) and prints the
  board's HELLO, raw readings, calibrated joints and frame counters: for wiring checks and
  calibration.

Examples::

    telesurg device emulate --pty --rate 500 --motion sine          # prints /dev/pts/N
    telesurg device emulate --pty --config-dir deploy/plas --link ttyPLAS   # the board deploy/plas expects
    telesurg master-capture --set device=serial --set serial.port=/dev/pts/N
    telesurg device monitor --set serial.port=/dev/ttyACM0 --seconds 10
    telesurg device check spacemouse --set desk.deadband=0.15 --seconds 30
    python -m telesurg.tools.emulate emulate --pty --garbage-every 50 --drop-every 100
    telesurg device emulate-slave --pty --model mh3f --stall-joint 1 --stall-at 10   # prints /dev/pts/N
    telesurg slave-control --set backend=serial --set serial.port=/dev/pts/N --set shadow=true
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from telesurg.services.common import install_stop_handlers, setup_logging
from telesurg.shared.encoder_protocol import (
    Calibration,
    Hello,
    HelloRequest,
    Sample,
    decode_message,
    send_message,
)
from telesurg.shared.errors import ConfigError, MessageError, TelesurgError
from telesurg.shared.serial_link import SerialLink
from telesurg.tools.emulate.emulator import MOTIONS, EmulatorOptions, run_pty
from telesurg.tools.emulate.servo_emulator import FAULTS, ServoEmulatorOptions
from telesurg.tools.emulate.servo_emulator import run_pty as run_servo_pty

if TYPE_CHECKING:
    from telesurg.services.master_capture.devices.serial import SerialMasterConfig

log = logging.getLogger(__name__)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="telesurg device",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    em = sub.add_parser("emulate", help="emulate the encoder board on a new pseudo-terminal")
    em.add_argument(
        "--pty", action="store_true", help="serve on a new pseudo-terminal pair (the only transport)"
    )
    em.add_argument("--rate", type=float, default=500.0, metavar="HZ", help="SAMPLE rate, Hz (500)")
    em.add_argument("--motion", choices=MOTIONS, default="sine", help="scripted joint motion (sine)")
    em.add_argument("--seconds", type=float, default=0.0, metavar="S", help="stop after S s (0: never)")
    em.add_argument(
        "--garbage-every",
        type=int,
        default=0,
        metavar="N",
        help="write 1-16 random bytes after every N-th SAMPLE",
    )
    em.add_argument(
        "--drop-every", type=int, default=0, metavar="N", help="skip every N-th SAMPLE (a seq gap)"
    )
    em.add_argument("--seed", type=int, default=0, help="seed of the random garbage")
    em.add_argument(
        "--clutch-repeat",
        type=float,
        default=EmulatorOptions().clutch_repeat_s,
        metavar="S",
        help="the operator presses the clutch 1 s after the host opens the port and releases it for "
        "0.3 s every S seconds (re-clutching; default 5; 0: keeps it pressed)",
    )
    em.add_argument(
        "--link",
        metavar="PATH",
        help="also make PATH a symlink to the pty while it runs: a stable port name for the host",
    )
    em.add_argument(
        "--config-dir",
        type=Path,
        metavar="DIR",
        help="emulate the board this site's master_capture expects: the calibration of "
        "DIR/site.toml, e.g. deploy/plas (default: master_capture's default calibration)",
    )
    em.add_argument(
        "--counts-per-rev",
        type=int,
        metavar="N",
        help="encoder counts per revolution (default: the calibration's, 400; 1600 = 400 lines decoded x4)",
    )
    em.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    _slave_parser(sub)
    mon = sub.add_parser("monitor", help="print the board's HELLO, readings and counters")
    mon.add_argument("--config", metavar="FILE", help="master_capture TOML config (its [serial] table)")
    mon.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a master_capture key"
    )
    mon.add_argument("--seconds", type=float, default=0.0, metavar="S", help="stop after S s (0: never)")
    mon.add_argument("--print-hz", type=float, default=5.0, metavar="HZ", help="reading lines per second (5)")
    mon.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    chk = sub.add_parser(
        "check",
        help="open a master device of TYPE (spacemouse, touch, omega7, gamepad, …) and print its readings",
    )
    chk.add_argument("type", help="master_capture device type, e.g. spacemouse")
    chk.add_argument("--config", metavar="FILE", help="master_capture TOML config (its [desk] table)")
    chk.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a master_capture key"
    )
    chk.add_argument("--seconds", type=float, default=10.0, metavar="S", help="read for S s (default 10)")
    chk.add_argument("--print-hz", type=float, default=10.0, metavar="HZ", help="lines per second (10)")
    chk.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    return parser


def check(device: object, seconds: float, print_hz: float, out: TextIO, stop: threading.Event) -> int:
    """Print a device's readings (position mm, orientation, clutch, valid) at ``print_hz`` for
    ``seconds``; the number of valid readings."""
    t0 = time.monotonic()
    valid = 0
    while not stop.is_set() and time.monotonic() - t0 < seconds:
        s = device.read(time.monotonic() - t0)  # type: ignore[attr-defined]
        valid += s.valid
        p = " ".join(f"{v * 1e3:8.2f}" for v in s.position)
        q = " ".join(f"{v:+.3f}" for v in s.orientation)
        print(
            f"{time.monotonic() - t0:6.2f} s  p [{p}] mm  q [{q}]  clutch {int(s.clutch)}  "
            f"{'valid' if s.valid else 'INVALID (no fresh reading)'}",
            file=out,
            flush=True,
        )
        stop.wait(1.0 / print_hz)
    return valid


def _check_main(args: argparse.Namespace, stop: threading.Event) -> int:
    from telesurg.services.master_capture import MasterCaptureConfig
    from telesurg.services.master_capture.devices import open_device
    from telesurg.shared.config import load_config

    try:
        cfg = load_config(MasterCaptureConfig, args.config, [*args.set, f"device={json.dumps(args.type)}"])
        device = open_device(cfg.device, cfg)
    except TelesurgError as exc:
        print(f"telesurg device check: {exc}", file=sys.stderr)
        return 2
    install_stop_handlers(stop)
    try:
        with device:
            n = check(device, args.seconds, args.print_hz, sys.stdout, stop)
    except (TelesurgError, ConnectionError) as exc:
        print(f"telesurg device check {args.type}: {exc}", file=sys.stderr)
        return 1
    print(f"{n} valid readings", file=sys.stdout)
    return 0 if n else 1


def _slave_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from telesurg.shared import robots

    em = sub.add_parser(
        "emulate-slave",
        help="emulate a slave arm's joint-servo controller on a new pseudo-terminal",
        description="Fault times count from the first ENABLE (when a host has taken control).",
    )
    em.add_argument(
        "--pty", action="store_true", help="serve on a new pseudo-terminal pair (the only transport)"
    )
    em.add_argument(
        "--plugin",
        action="append",
        default=[],
        metavar="FILE",
        help="robot plugin file (registers more robots for --model; repeatable)",
    )
    em.add_argument("--model", choices=robots.names(), default="mh3f", help="robot model (mh3f)")
    em.add_argument("--rate", type=float, default=200.0, metavar="HZ", help="STATE rate, Hz (200)")
    em.add_argument("--lag-ms", type=float, default=20.0, metavar="MS", help="servo lag time constant (20)")
    em.add_argument("--seconds", type=float, default=0.0, metavar="S", help="stop after S s (0: never)")
    em.add_argument(
        "--fault-at", type=float, metavar="S", help="raise a fault bit S s after the first ENABLE"
    )
    em.add_argument("--fault", choices=tuple(FAULTS), default="overcurrent", help="which (overcurrent)")
    em.add_argument(
        "--stall-joint", type=int, default=0, metavar="J", help="joint J (1-based) sticks at --stall-at"
    )
    em.add_argument("--stall-at", type=float, default=0.0, metavar="S", help="s after the first ENABLE (0)")
    em.add_argument(
        "--silence-at", type=float, metavar="S", help="stop writing frames S s after the first ENABLE"
    )
    em.add_argument(
        "--silence-for", type=float, default=0.0, metavar="S", help="silence length, s (0: for good)"
    )
    em.add_argument(
        "--garbage-every",
        type=int,
        default=0,
        metavar="N",
        help="write 1-16 random bytes after every N-th STATE",
    )
    em.add_argument(
        "--drop-every", type=int, default=0, metavar="N", help="skip every N-th STATE (a seq gap)"
    )
    em.add_argument("--seed", type=int, default=0, help="seed of the random garbage")
    em.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")


def _emulate_slave(parser: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    if not args.pty:
        parser.error("emulate-slave needs a transport: --pty")
    opts = ServoEmulatorOptions(
        model=args.model,
        rate_hz=args.rate,
        lag_ms=args.lag_ms,
        fault_at=args.fault_at,
        fault=args.fault,
        stall_joint=args.stall_joint,
        stall_at=args.stall_at,
        silence_at=args.silence_at,
        silence_for=args.silence_for,
        garbage_every=args.garbage_every,
        drop_every=args.drop_every,
        seed=args.seed,
    )
    try:
        opts.validate()
    except ValueError as exc:
        print(f"telesurg device emulate-slave: {exc}", file=sys.stderr)
        return 2
    install_stop_handlers(stop)
    s = run_servo_pty(opts, stop, args.seconds)
    log.info(
        "sent %d STATEs, %d HELLOs; applied %d SETPOINTs (%d stale, %d while disabled, %d refused); "
        "%d ENABLEs, %d DISABLEs, %d watchdog trips; host frames corrupt %d, invalid %d, gaps %d; "
        "silent %d frames, dropped %d, garbage %d, overflow %d bytes",
        s.states,
        s.hellos,
        s.setpoints,
        s.stale_setpoints,
        s.ignored_setpoints,
        s.bad_setpoints,
        s.enables,
        s.disables,
        s.watchdog_trips,
        s.corrupt,
        s.invalid,
        s.gaps,
        s.silent_frames,
        s.dropped,
        s.garbage,
        s.overflow_bytes,
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg device``; exit 0 on a requested stop, 1 on a device error, 2 on bad options."""
    from telesurg.shared import robots

    pre = argparse.ArgumentParser(add_help=False)  # the plugins first: they add --model choices
    pre.add_argument("--plugin", action="append", default=[])
    for path in pre.parse_known_args(argv)[0].plugin:
        try:
            robots.load_plugin(path)
        except TelesurgError as exc:
            print(f"telesurg device: {exc}", file=sys.stderr)
            return 2
    parser = _parser()
    args = parser.parse_args(argv)
    setup_logging(args.log_level, "device")
    stop = threading.Event()
    if args.command == "emulate-slave":
        return _emulate_slave(parser, args, stop)
    if args.command == "emulate":
        if not args.pty:
            parser.error("emulate needs a transport: --pty")
        opts = EmulatorOptions(
            rate_hz=args.rate,
            motion=args.motion,
            garbage_every=args.garbage_every,
            drop_every=args.drop_every,
            seed=args.seed,
            clutch_repeat_s=args.clutch_repeat,
        )
        try:
            opts.calibration = _emulated_calibration(args.config_dir, args.counts_per_rev)
            opts.validate()
        except (ValueError, TelesurgError) as exc:
            print(f"telesurg device emulate: {exc}", file=sys.stderr)
            return 2
        install_stop_handlers(stop)
        stats = run_pty(opts, stop, args.seconds, args.link or "")
        log.info(
            "sent %d SAMPLEs, %d HELLOs; dropped %d, garbage %d, HELLO_REQUESTs %d, overflow %d bytes",
            stats.samples,
            stats.hellos,
            stats.dropped,
            stats.garbage,
            stats.requests,
            stats.overflow_bytes,
        )
        return 0
    if args.command == "check":
        return _check_main(args, stop)
    return _monitor_main(args, stop)


def _emulated_calibration(config_dir: Path | None, counts_per_rev: int | None) -> Calibration:
    """The board to emulate: the calibration of ``config_dir``'s master_capture (its site file),
    else the default one; ``counts_per_rev`` overrides."""
    from telesurg.services.master_capture import MasterCaptureConfig
    from telesurg.shared.config import SITE_FILE, load_config

    cal = Calibration()
    if config_dir is not None:
        if not (config_dir / SITE_FILE).is_file():
            raise ConfigError(f"site file {config_dir / SITE_FILE} not found (--config-dir)")
        cfg = load_config(MasterCaptureConfig, config_dir / SITE_FILE, table="master_capture")
        cal = cfg.serial.calibration
    return cal if counts_per_rev is None else dataclasses.replace(cal, counts_per_rev=counts_per_rev)


def _monitor_main(args: argparse.Namespace, stop: threading.Event) -> int:
    from telesurg.services.master_capture import MasterCaptureConfig  # zenoh: only for this subcommand
    from telesurg.shared.config import load_config

    try:
        cfg = load_config(MasterCaptureConfig, args.config, args.set).serial
        cfg.validate()
        if args.print_hz <= 0:
            raise ValueError(f"--print-hz must be > 0, got {args.print_hz}")
    except (TelesurgError, ValueError) as exc:
        print(f"telesurg device monitor: {exc}", file=sys.stderr)
        return 2
    install_stop_handlers(stop)
    try:
        monitor(cfg, stop, seconds=args.seconds, print_hz=args.print_hz)
    except (TelesurgError, ConnectionError) as exc:
        log.error("%s", exc)
        return 1
    return 0


def monitor(
    cfg: SerialMasterConfig,
    stop: threading.Event,
    *,
    seconds: float = 0.0,
    print_hz: float = 5.0,
    out: TextIO | None = None,
) -> None:
    """Print the board's HELLOs, a reading line at ``print_hz`` and the counters at the end.

    Raises:
        DeviceConnectionError: the port cannot be opened or fails.
    """
    stream = out or sys.stdout
    cal = cfg.calibration
    end = time.monotonic() + seconds if seconds > 0 else math.inf
    latest: Sample | None = None
    invalid = 0
    next_print = time.monotonic()
    with SerialLink(cfg.port, baudrate=cfg.baud) as link:
        send_message(link, HelloRequest())
        while not stop.is_set() and time.monotonic() < end:
            first = link.receive(timeout=0.05)
            for frame in [first, *link.poll()] if first is not None else []:
                try:
                    msg = decode_message(frame)
                except MessageError as exc:
                    invalid += 1
                    print(f"invalid frame seq {frame.seq}: {exc}", file=stream, flush=True)
                    continue
                if isinstance(msg, Hello):
                    try:
                        cal.check_hello(msg)
                        verdict = "matches the calibration"
                    except MessageError as exc:
                        verdict = f"REFUSED: {exc}"
                    print(f"HELLO seq {frame.seq}: {msg.body()} — {verdict}", file=stream, flush=True)
                elif isinstance(msg, Sample):
                    latest = msg
            if latest is not None and time.monotonic() >= next_print:
                next_print = time.monotonic() + 1.0 / print_hz
                print(_reading_line(cfg, latest), file=stream, flush=True)
        r = link.reader
        print(
            f"frames {r.frames}, corrupt {r.error_count} {dict(r.errors)}, invalid {invalid}",
            file=stream,
            flush=True,
        )


def _reading_line(cfg: SerialMasterConfig, s: Sample) -> str:
    """Raw counts, pot, switches, then every joint in deg (encoders) or mm (pot)."""
    cal = cfg.calibration
    raw = f"t_us={s.t_us} counts={list(s.counts)} pot={s.pot} sw=0b{s.sw:03b}"
    try:
        q = cal.convert(s).joints
    except MessageError as exc:
        return f"{raw} | {exc}"
    parts = []
    for i, (name, v) in enumerate(zip(cfg.joint_names, q, strict=True)):
        if i + 1 in cal.encoder_joints:
            parts.append(f"{name}={math.degrees(v):+7.2f}°")
        elif i + 1 == cal.pot_joint:
            parts.append(f"{name}={v * 1000:+6.2f}mm")
        else:
            parts.append(f"{name}=-")
    return f"{raw} | {' '.join(parts)}"
