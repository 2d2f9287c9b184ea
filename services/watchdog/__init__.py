"""watchdog: grants each slave arm a short lease to move, only while everything is healthy.

Signals (first version; a later issue adds limits, latency budget and e-stop):

* liveliness tokens ``alive/<service>`` of every required service — a crash is seen in ms;
* staleness of each control stream against its deadline — a hang, a frozen process or a
  partition, which liveliness only sees after the transport lease.

Every ``1/lease_hz`` s, and at once on any liveliness change, the watchdog publishes
``safety/<arm>/lease`` (``allow``, ``valid_for_ms``, ``reason``). The slave holds the moment the
lease says hold or expires, so the watchdog's own death is fail-safe. State changes go out on
``safety/<arm>/state`` and as events.

Example::

    telesurg watchdog --connect tcp/127.0.0.1:7447 --set 'pairs=["m1:arm1"]'
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

from services.common import service_main
from services.mapping import parse_pair
from shared.bus import BusConfig, Node, Outlet
from shared.errors import ConfigError
from shared.messages import (
    CartesianPose,
    JointSetpoint,
    JointState,
    Message,
    SafetyLease,
    SafetyState,
)

log = logging.getLogger(__name__)


@dataclass
class WatchdogConfig:
    """watchdog config."""

    site: str = "local"  # key prefix telesurg/<site>
    service: str = "watchdog"  # instance id (liveliness alive/<service>, header src)
    pairs: list[str] = field(default_factory=lambda: ["m1:arm1"])  # "master_arm:slave_arm"
    # services whose liveliness token must be present for any arm to move
    required_services: list[str] = field(
        default_factory=lambda: ["master_capture", "mapping", "slave_control"]
    )
    lease_hz: float = 50.0  # Hz: lease publish rate (also at once on any liveliness loss)
    # ms: lease lifetime at the slave. Covers a *frozen* watchdog; a dead one is seen by the
    # slave through liveliness in ms. Long enough to ride out the VM's scheduling stalls.
    lease_valid_ms: float = 250.0
    master_deadline_ms: float = 100.0  # ms: master measured_cp older than this → HOLD
    servo_deadline_ms: float = 100.0  # ms: servo_jp older than this → HOLD
    slave_deadline_ms: float = 100.0  # ms: slave measured_js older than this → HOLD
    state_hz: float = 5.0  # Hz: safety state republish rate (also sent on every change)
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session

    def validate(self) -> None:
        """Raise ConfigError on inconsistent timing."""
        if self.lease_hz <= 0 or self.lease_valid_ms * self.lease_hz / 1e3 < 2.0:
            raise ConfigError("lease_valid_ms must cover at least 2 lease periods")
        for p in self.pairs:
            parse_pair(p)


class ArmWatch:
    """Health of one arm: which streams must be fresh, current state."""

    def __init__(self, node: Node, cfg: WatchdogConfig, master: str, arm: str) -> None:
        k = node.keys
        self.arm = arm
        self.deadlines = {
            k.master(master, "measured_cp"): cfg.master_deadline_ms,
            k.slave(arm, "servo_jp"): cfg.servo_deadline_ms,
            k.slave(arm, "measured_js"): cfg.slave_deadline_ms,
        }
        self.lease_out: Outlet = node.outlet(k.safety(arm, "lease"))
        self.state_out: Outlet = node.outlet(k.safety(arm, "state"), control=False)
        self.state = "HOLD"
        self.causes: tuple[str, ...] = ("starting",)


class Watchdog:
    """Combines liveliness and staleness into per-arm leases."""

    def __init__(self, cfg: WatchdogConfig, node: Node) -> None:
        self.cfg, self.node = cfg, node
        self.lock = threading.Lock()
        self.alive: set[str] = set()
        # Ticks executed, and the tick at which each stream last delivered. A stream is stale
        # only when it is old by wall time *and* by ticks: after the watchdog's own stall
        # (descheduled), queued messages get a chance to arrive before anything is judged stale.
        self.ticks = 0
        self.tick_lock = threading.Lock()
        self.last_tick: dict[str, int] = {}
        self.arms = [ArmWatch(node, cfg, *parse_pair(p)) for p in cfg.pairs]
        types: dict[str, type[Message]] = {
            "measured_cp": CartesianPose,
            "servo_jp": JointSetpoint,
            "measured_js": JointState,
        }
        for a in self.arms:
            for key in a.deadlines:
                node.subscribe(key, types[key.rsplit("/", 1)[-1]], self._on_stream)
        node.watch_liveliness(node.keys.alive(), self._on_alive)

    def _on_stream(self, msg: Message, key: str) -> None:
        self.last_tick[key] = self.ticks  # receive time is tracked by Node.streams

    def _on_alive(self, service: str, alive: bool) -> None:
        with self.lock:
            if alive:
                self.alive.add(service)
            else:
                self.alive.discard(service)
        if not alive and service in self.cfg.required_services:
            self.tick(force_state=True)  # do not wait for the next period

    def causes(self, a: ArmWatch) -> list[str]:
        """Why arm ``a`` must not move now (empty: healthy)."""
        with self.lock:
            alive = set(self.alive)
        out = [f"{s} not alive" for s in self.cfg.required_services if s not in alive]
        for key, deadline in a.deadlines.items():
            age_ms = self.node.streams.get(key).age_s() * 1e3
            ticks = self.ticks - self.last_tick.get(key, -(10**9))
            if age_ms > deadline and ticks * 1e3 / self.cfg.lease_hz >= deadline:
                stream = key.split("/", 2)[-1]
                out.append(
                    f"{stream} never received"
                    if age_ms == float("inf")
                    else f"{stream} stale ({age_ms:.0f} ms > {deadline:.0f} ms)"
                )
        return out

    def tick(self, *, force_state: bool = False) -> None:
        """Evaluate every arm, publish leases (and states on change or when forced)."""
        with self.tick_lock:  # the main loop and the liveliness callback both tick
            self._tick(force_state)

    def _tick(self, force_state: bool) -> None:
        self.ticks += 1
        for a in self.arms:
            causes = self.causes(a)
            state = "OK" if not causes else "HOLD"
            allow = state == "OK"
            a.lease_out.put(
                SafetyLease(
                    a.lease_out.header(),
                    a.arm,
                    allow,
                    self.cfg.lease_valid_ms,
                    "; ".join(causes)[:500],
                )
            )
            changed = state != a.state
            if changed:
                self.node.event(
                    "safety_transition",
                    f"{a.state} → {state}" + (f": {'; '.join(causes)}" if causes else ""),
                    arm=a.arm,
                    severity="warning" if state != "OK" else "info",
                )
            a.state, a.causes = state, tuple(c[:500] for c in causes)
            if changed or force_state:
                self.publish_state(a)

    def publish_state(self, a: ArmWatch) -> None:
        """Send the current safety state of ``a``."""
        a.state_out.put(SafetyState(a.state_out.header(), a.arm, a.state, a.causes))


def run(cfg: WatchdogConfig, stop: threading.Event) -> None:
    """Watch until ``stop``; leases stop with the process (fail-safe)."""
    cfg.validate()
    with Node(cfg.bus, cfg.site, cfg.service) as node:
        wd = Watchdog(cfg, node)
        period = 1.0 / cfg.lease_hz
        state_every = max(1, round(cfg.lease_hz / cfg.state_hz))
        n = 0
        next_t = time.monotonic()
        log.info("watching %s; required services: %s", cfg.pairs, cfg.required_services)
        while not stop.is_set():
            wd.tick()
            n += 1
            if n % state_every == 0:
                with wd.tick_lock:
                    for a in wd.arms:
                        wd.publish_state(a)
            next_t += period
            stop.wait(max(0.0, next_t - time.monotonic()))
        # Last word: revoke every lease explicitly before going away.
        for a in wd.arms:
            a.lease_out.put(
                SafetyLease(a.lease_out.header(), a.arm, False, cfg.lease_valid_ms, "watchdog stopped")
            )


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg watchdog``."""
    return service_main("watchdog", WatchdogConfig, run, argv, __doc__ or "")
