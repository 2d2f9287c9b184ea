"""A running local pipeline with a probe, a link impairer and fault injectors.

Used by ``telesurg bench faults`` / ``bench fuzz`` and by the process-level safety tests, so
the figures in ``docs/safety.md`` and the test assertions come from the same code.

The console side (master_capture) reaches the slave-side router through a
:class:`~telesurg.tools.bench.impair.LinkImpairer` in a process of its own
(:class:`~telesurg.tools.bench.impair.ImpairerProcess`) on loopback, so a link cut or delay can
be injected between the two sides. The probe is a zenoh client that records, on its own monotonic
clock, what a user would look at: the slave tip (from MuJoCo), the slave's operating state, the
watchdog's state, the clutch pedal and every event.

Example::

    with Pipeline(Path("out/logs")) as pipe:
        pipe.wait_following(20)
        t = pipe.inject_kill("mapping")
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

import numpy as np
from telesurg.services.launcher import Site, SiteSpec, default_config_dir, free_port, lock_down
from telesurg.shared.bus import Node, Outlet
from telesurg.shared.messages import (
    CartesianPose,
    EStop,
    Heartbeat,
    JointSetpoint,
    JointState,
    MasterButtons,
    OperatingState,
    SafetyEvent,
    SafetyLease,
    SafetyState,
    TeleopState,
)
from telesurg.tools.bench.impair import ImpairerProcess
from telesurg.tools.bench.netprofile import LinkProfile

log = logging.getLogger(__name__)

#: Clutch schedule of the bench's scripted master: pressed 0.5–3.5 s of every 4 s, so after any
#: hold a new engage comes within 4 s.
BENCH_CLUTCH = ["scripted.clutch=[[0.5, 3.5]]", "scripted.clutch_repeat_s=4.0"]


HEARTBEAT_SOURCES = ("watchdog", "slave_control", "mapping", "master_capture", "mirror")
CONTROL_STREAMS = ("master/m1/measured_cp", "slave/arm1/servo_jp", "slave/arm1/measured_js")


def now_ns() -> int:
    """The probe's clock (monotonic, ns)."""
    return time.monotonic_ns()


def _published_ns(received_ns: int, stamp_ns: int) -> int:
    """A message's publication time on the probe's clock ``now_ns``: its receipt minus the age of
    its wall-clock stamp (publisher and probe on one host)."""
    return received_ns - max(0, time.time_ns() - stamp_ns)


@dataclass
class Probe:
    """Everything the probe saw, stamped with the probe's receive time (monotonic ns)."""

    node: Node
    arm: str = "arm1"
    master: str = "m1"
    lock: threading.Lock = field(default_factory=threading.Lock)
    tip: list[tuple[int, float, float, float]] = field(default_factory=list)
    op: list[tuple[int, bool, bool, str, str, int, int, int, int]] = field(default_factory=list)
    safety: list[tuple[int, str, tuple[str, ...], float, float, float]] = field(default_factory=list)
    clutch: list[tuple[int, bool]] = field(default_factory=list)
    events: list[tuple[int, str, str, str]] = field(default_factory=list)
    heartbeats: dict[str, int] = field(default_factory=dict)  # service → rejected so far
    hb_replayed: dict[str, int] = field(default_factory=dict)  # service → of those, refused as not fresh
    hb_lost: dict[str, int] = field(default_factory=dict)  # service → sequence numbers it never saw
    # service → when (this process's monotonic clock) its loop last took in its buffered streams
    polled_at: dict[str, float] = field(default_factory=dict)
    beat_at: dict[str, float] = field(default_factory=dict)  # service → its last heartbeat's arrival
    joints: list[tuple[float, ...]] = field(default_factory=list)  # slave measured_js positions
    teleop: tuple[str, str] = ("", "")  # the mapping's last teleop state and its reason

    def __post_init__(self) -> None:
        k = self.node.keys
        # Only the genuine publishers count (fuzzing publishes look-alikes on the same keys).
        sub, slave, master = self.node.subscribe, ["slave_control"], ["master_capture"]
        sub(k.slave(self.arm, "measured_cp"), CartesianPose, self._on_tip, sources=slave)
        sub(k.slave(self.arm, "operating_state"), OperatingState, self._on_op, sources=slave)
        sub(k.safety(self.arm, "state"), SafetyState, self._on_safety, sources=["watchdog"])
        sub(k.master(self.master, "buttons"), MasterButtons, self._on_buttons, sources=master)
        sub(k.events(), SafetyEvent, self._on_event)
        teleop = k.mapping(self.arm, "teleop_state")
        sub(teleop, TeleopState, self._on_teleop, sources=["mapping"], latest=True)
        sub(k.master(self.master, "measured_cp"), CartesianPose, lambda m, k: None, sources=master)
        sub(k.slave(self.arm, "servo_jp"), JointSetpoint, lambda m, k: None, sources=["mapping"])
        # (counted only: forged leases that reach a subscriber show in its unauthenticated count)
        sub(k.safety(self.arm, "lease"), SafetyLease, lambda m, k: None, sources=["watchdog"])
        sub(k.slave(self.arm, "measured_js"), JointState, self._on_js, sources=slave)
        for svc in HEARTBEAT_SOURCES:
            self.node.subscribe(k.heartbeat(svc), Heartbeat, self._on_heartbeat, sources=[svc])

    def _on_tip(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            self.tip.append((now_ns(), *m.position))

    def _on_teleop(self, m: TeleopState, key: str) -> None:
        with self.lock:
            self.teleop = (m.state, m.reason)

    def _on_js(self, m: JointState, key: str) -> None:
        with self.lock:
            self.joints.append(m.position)

    def _on_op(self, m: OperatingState, key: str) -> None:
        t = now_ns()
        published = _published_ns(t, m.header.stamp_ns)
        with self.lock:
            self.op.append(
                (
                    t,
                    m.follow,
                    m.lease_ok,
                    m.reason,
                    m.state,
                    m.holds,
                    m.clipped,
                    m.rejected,
                    published,  # when the slave published it, on the probe's clock
                )
            )

    def _on_safety(self, m: SafetyState, key: str) -> None:
        with self.lock:
            self.safety.append((now_ns(), m.state, m.causes, m.scale, m.latency_p50_ms, m.latency_p99_ms))

    def _on_buttons(self, m: MasterButtons, key: str) -> None:
        with self.lock:
            if not self.clutch or self.clutch[-1][1] != m.clutch:
                # when master_capture published it (as ``op[8]``): the press and the follow it
                # causes come on different paths, and the follow's state may reach the probe first
                self.clutch.append((_published_ns(now_ns(), m.header.stamp_ns), m.clutch))

    def _on_event(self, m: SafetyEvent, key: str) -> None:
        with self.lock:
            self.events.append((now_ns(), m.header.source, m.kind, m.text))

    def _on_heartbeat(self, m: Heartbeat, key: str) -> None:
        with self.lock:
            self.heartbeats[m.service] = m.rejected
            self.hb_replayed[m.service] = m.replayed
            self.hb_lost[m.service] = m.lost
            self.beat_at[m.service] = t = time.monotonic()
            if m.polled_s >= 0:
                self.polled_at[m.service] = t - m.polled_s

    # -- queries ------------------------------------------------------------------------------
    def following(self) -> bool:
        """The slave's last operating state says it follows."""
        with self.lock:
            return bool(self.op) and self.op[-1][1]

    def safety_state(self) -> str:
        """The watchdog's last state ("" if none yet)."""
        with self.lock:
            return self.safety[-1][1] if self.safety else ""

    def tips(self) -> np.ndarray:
        """(n, 4): receive ns, x, y, z (m)."""
        with self.lock:
            return np.array(self.tip, dtype=float).reshape(-1, 4)

    def first_op_after(self, t_ns: int, pred) -> tuple[int, tuple] | None:  # type: ignore[no-untyped-def,type-arg]
        """First operating-state record after ``t_ns`` matching ``pred(record)``."""
        with self.lock:
            for rec in self.op:
                if rec[0] >= t_ns and pred(rec):
                    return rec[0], rec
        return None

    def first_safety_after(self, t_ns: int, states: tuple[str, ...]) -> int | None:
        """Receive time of the first watchdog state in ``states`` after ``t_ns``."""
        with self.lock:
            for rec in self.safety:
                if rec[0] >= t_ns and rec[1] in states:
                    return rec[0]
        return None

    def press_between(self, t0: int, t1: int) -> bool:
        """A clutch press (released → pressed) was published between t0 and t1."""
        with self.lock:
            return any(t0 <= t <= t1 and pressed for t, pressed in self.clutch)

    def lost(self) -> dict[str, int]:
        """Lost + reordered messages per control stream, as the probe saw them."""
        out = {}
        for s in CONTROL_STREAMS:
            st = self.node.streams.get(f"{self.node.keys.prefix}/{s}")
            out[s] = st.lost + st.reordered
        return out

    def motion_after(self, t_ns: int, window_s: float) -> float:
        """Largest tip distance (mm) from its position at ``t_ns`` over the next window."""
        tips = self.tips()
        if tips.size == 0:
            return float("nan")
        i = max(int(np.searchsorted(tips[:, 0], t_ns, side="right")) - 1, 0)
        p0 = tips[i, 1:]
        sel = (tips[:, 0] >= t_ns) & (tips[:, 0] <= t_ns + window_s * 1e9)
        if not sel.any():
            return float("nan")
        return float(np.linalg.norm(tips[sel, 1:] - p0, axis=1).max() * 1e3)


#: Largest share of a 1 kHz stream an observer (a probe, the demo's report node: not a control
#: service) may lose on this 2-core host. The router drops samples for an observer rather than
#: hold up the control path when the host leaves it behind: 0.02–1.9 % seen in CI, 4.4 % beside
#: other load. A broken or stalled stream loses far more.
OBSERVER_LOSS_MAX = 0.05


class Pipeline:
    """Router + every service (+ link impairer on the console side) + probe; a context manager."""

    def __init__(
        self,
        log_dir: Path,
        *,
        overrides: dict[str, list[str]] | None = None,
        mirror: bool = True,
        impair: bool = True,
        master: bool = True,
        probe: bool = True,
        log_level: str = "INFO",
        config_dir: Path | None = None,
        acl: Path | None = None,
        camera: bool = False,
        mapping: bool = True,
        link: LinkProfile | None = None,
        console: bool = False,
    ) -> None:
        self.log_dir = log_dir
        self._link = link  # the impairer's delay and jitter from before anything connects
        port = free_port()
        # (its own process: the test's, busy with its subscriptions, would delay the link)
        self.impairer = ImpairerProcess(("127.0.0.1", port)) if impair else None
        ov: dict[str, list[str]] = {"master_capture": list(BENCH_CLUTCH)}
        if mirror:  # the mirror records the whole run next to the logs
            ov["mirror"] = [f"save={json.dumps(str(log_dir / 'session.rrd'))}"]
        for name, items in (overrides or {}).items():
            ov.setdefault(name, []).extend(items)
        # (without the mapping another master stands in for it, e.g. telesurg bridge ros2)
        services: tuple[str, ...] = ("watchdog", "slave_control") + (("mapping",) if mapping else ())
        services += (("master_capture",) if master else ()) + (("mirror",) if mirror else ())
        services += ("camera",) if camera else ()  # (its video then guards the arm: Site._camera_first)
        # the web console, its page the master (telesurg up --master web): it reaches the site
        # through the impairer as master_capture does
        self.console_port = free_port() if console else 0
        if console:
            services += ("console",)
            ov.setdefault("console", []).insert(0, f"web.port={self.console_port}")
        self.spec = SiteSpec(
            port=port,
            config_dir=config_dir or default_config_dir(),
            services=services,
            overrides=ov,
            log_dir=log_dir,
            log_level=log_level,
        )
        if acl is not None:  # a locked-down site (telesurg up --acl): local mutual TLS, the ACL
            self.spec.router_flags = ("--acl", str(acl), "--set", 'acl_log="denied"')
            lock_down(self.spec, log_dir / "credentials")
        self.site = Site(self.spec)
        self._node: Node | None = None
        self.probe: Probe | None = None
        self._want_probe = probe
        self._estop_outs: dict[str, Outlet] = {}
        self._extra_nodes: list[Node] = []  # the e-stop senders, one per identity

    def __enter__(self) -> Pipeline:
        try:
            if self.impairer is not None:
                self.impairer.start()
                if self._link is not None:
                    self.impairer.set_profile(self._link)
                self.spec.connect["master_capture"] = self.impairer.endpoint
                if self.console_port:
                    self.spec.connect["console"] = self.impairer.endpoint
            self.site.start()
            # (without master_capture the caller acts as the master, e.g. a test console)
            self._node = Node(self.spec.client_bus("operator"), self.spec.site, "bench_probe")
            if self._want_probe:  # (a test doing its own subscriptions can skip the probe's load)
                self.probe = Probe(self._node)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> dict[str, int]:
        """Stop everything this pipeline started; exit codes of the services still running."""
        for _name, p in self.site.procs.items():  # a frozen process cannot stop: thaw it first
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(p.pid, signal.SIGCONT)
        for n in self._extra_nodes:
            n.close()
        self._extra_nodes.clear()
        self._estop_outs.clear()
        if self._node is not None:
            self._node.close()
            self._node = None
        codes = self.site.stop()
        if self.impairer is not None:
            self.impairer.close()
        return codes

    def keep(self, node: Node) -> Node:
        """Close ``node`` with the pipeline (a node of the caller's, e.g. another identity)."""
        self._extra_nodes.append(node)
        return node

    def console_login(self, timeout: float = 30.0) -> str:
        """The web console's one-time login URL, once its page is served (``console=True``)."""
        from telesurg.services.launcher import login_url, wait_port

        if not self.console_port:
            raise RuntimeError("this pipeline has no web console (console=True)")
        wait_port("127.0.0.1", self.console_port, timeout)
        return login_url(f"http://127.0.0.1:{self.console_port}/", self.site.login_token)

    @property
    def p(self) -> Probe:
        """The probe (after start)."""
        assert self.probe is not None
        return self.probe

    @property
    def node(self) -> Node:
        """The probe's zenoh node."""
        assert self._node is not None
        return self._node

    def wait(self, pred, timeout: float) -> bool:  # type: ignore[no-untyped-def]
        """Poll ``pred()`` every 10 ms until true (True) or ``timeout`` s (False)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred():
                return True
            time.sleep(0.01)
        return False

    def settled_heartbeats(self, timeout: float = 20.0) -> dict[str, int]:
        """Rejection counters once every service has caught up with what was sent before the call.

        A service that fell behind under load is still working through its queue for a while
        after the last message was sent: the counts are taken once each service that buffers
        streams and still beats has taken them in since the call (its heartbeat's ``polled_s``)
        and the counts are unchanged over two heartbeats.
        """
        since = time.monotonic()
        deadline = since + timeout
        last: dict[str, int] = {}
        stable = 0
        while time.monotonic() < deadline:
            time.sleep(0.6)  # heartbeats are 2 Hz
            with self.p.lock:
                now = dict(self.p.heartbeats)
                # (a service silent for three heartbeats is gone: nothing to wait for)
                alive = time.monotonic() - 1.5
                behind = [s for s, t in self.p.polled_at.items() if t < since and self.p.beat_at[s] > alive]
            stable = stable + 1 if now == last and not behind else 0
            if stable >= 2:
                break
            last = now
        return last

    def tallies(self) -> dict[str, tuple[int, int, int]]:
        """Each service's last heartbeat: rejected, of those replayed (refused as not fresh), lost."""
        p = self.p
        with p.lock:
            return {s: (n, p.hb_replayed.get(s, 0), p.hb_lost.get(s, 0)) for s, n in p.heartbeats.items()}

    def wait_following(self, timeout: float) -> bool:
        """Wait until the slave follows the master."""
        return self.wait(self.p.following, timeout)

    def wait_ready(self, timeout: float) -> bool:
        """Wait until the mapping is ready to engage (teleop state IDLE: what the console shows
        an operator before he presses; a press made earlier is refused and needs a new one)."""
        return self.wait(lambda: self.p.teleop[0] == "IDLE", timeout)

    def diagnose(self, lines: int = 12) -> str:
        """What a failed wait needs to be understood: the slave's and the watchdog's last states,
        the last clutch state and the tail of each service's log (for an assertion's message)."""
        out = []
        if self.probe is not None:
            with self.p.lock:
                op = self.p.op[-1] if self.p.op else None
                safety = self.p.safety[-1] if self.p.safety else None
                clutch = self.p.clutch[-1] if self.p.clutch else None
            if op is not None:
                out.append(f"slave: follow={op[1]} lease_ok={op[2]} reason={op[3]!r} state={op[4]!r}")
            if safety is not None:
                out.append(f"watchdog: {safety[1]} causes={list(safety[2])}")
            out.append(f"clutch: {clutch[1] if clutch else 'never published'}")
            out.append(f"teleop: {self.p.teleop[0] or 'never published'} ({self.p.teleop[1]})")
        for name in self.spec.services:
            log = self.log_dir / f"{name}.log"
            if log.exists():
                tail = log.read_text(errors="replace").splitlines()[-lines:]
                out.append(f"--- {name}.log (last {len(tail)} lines)")
                out.extend(tail)
        return "\n".join(out)

    # -- faults: each returns the injection time on the probe's clock ---------------------------
    def kill(self, name: str) -> int:
        """SIGKILL service ``name``."""
        pid = self.site.pid(name)
        t = now_ns()
        os.kill(pid, signal.SIGKILL)
        self.site.procs[name].wait()
        return t

    def freeze(self, name: str) -> int:
        """SIGSTOP service ``name`` (a hang: its liveliness token stays until the link lease)."""
        t = now_ns()
        os.kill(self.site.pid(name), signal.SIGSTOP)
        return t

    def thaw(self, name: str) -> int:
        """SIGCONT service ``name``."""
        t = now_ns()
        os.kill(self.site.pid(name), signal.SIGCONT)
        return t

    def restart(self, name: str) -> int:
        """Start ``name`` again after a kill."""
        t = now_ns()
        self.site.restart(name)
        return t

    def cut(self) -> int:
        """Cut the console ↔ slave-site link (bytes stop, sockets stay open)."""
        assert self.impairer is not None
        t = now_ns()
        self.impairer.cut()
        return t

    def delay(self, ms: float) -> int:
        """Add ``ms`` one-way delay to the console ↔ slave-site link."""
        assert self.impairer is not None
        t = now_ns()
        self.impairer.set_delay(ms)
        return t

    def estop(self, action: str, arm: str = "*", source: str = "console") -> int:
        """Send an e-stop (``action="estop"``) or its reset as ``source`` (a node of that service
        id, opened once; the operator console by default: only it may reset, shared/authority.py)."""
        out = self._estop_outs.get(source)
        if out is None:
            node = Node(self.spec.client_bus("operator"), self.spec.site, source)
            self._extra_nodes.append(node)
            out = self._estop_outs[source] = node.outlet(node.keys.estop)
            time.sleep(0.3)  # let the new publisher be matched before the first put
        t = now_ns()
        out.put(EStop(out.header(), arm, action, "bench"))
        return t

    def restore(self) -> int:
        """Back to a clean link."""
        assert self.impairer is not None
        t = now_ns()
        self.impairer.restore()
        return t
