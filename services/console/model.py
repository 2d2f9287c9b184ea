"""The console's model: its config, the per-arm state it shows and what it sends (no UI).

The terminal UI (:mod:`telesurg.services.console.app`) and the tests drive a :class:`ConsoleModel`;
see :mod:`telesurg.services.console` for what the console shows and does.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

from telesurg.services.console.webconfig import WebConfig
from telesurg.shared.authority import CONFIRM_ARG
from telesurg.shared.bus import BusConfig, Node, only
from telesurg.shared.errors import ConfigError, MessageError
from telesurg.shared.keys import Keys, check_id
from telesurg.shared.messages import (
    Command,
    CommandReply,
    EStop,
    MasterButtons,
    OperatingState,
    SafetyEvent,
    SafetyState,
    Sequencer,
    TeleopState,
    TrialState,
)

log = logging.getLogger(__name__)


@dataclass
class ConsoleConfig:
    """console config."""

    site: str = "local"  # key prefix telesurg/<site>
    # instance id (liveliness, header src of the clutch, commands and e-stops); the slave site's
    # master_capture accepts the console clutch only from this id
    service: str = "console"
    # "master:arm" pairs as in the mapping, or a bare arm id (driven by master m1)
    arms: list[str] = field(default_factory=lambda: ["m1:arm1"])
    clutch_hz: float = 20.0  # Hz: the console clutch is re-sent this often (and on every change)
    command_timeout_s: float = 3.0  # s: wait for a command reply, then report "no reply"
    estop_confirm_s: float = 2.0  # s: re-send an e-stop / reset until the watchdog confirms it
    stale_s: float = 1.0  # s: a stream silent for longer is shown as stale
    events_per_arm: int = 6  # last events shown in each arm's panel
    jog_frame: str = "base"  # initial jog frame (base, world, work, forceps, joint)
    program: str = "p1"  # program name used by the teach_point and play keys
    # only these publishers are believed ("" = anyone): the genuine services of the site
    slave_source: str = "slave_control"
    watchdog_source: str = "watchdog"
    master_source: str = "master_capture"
    mapping_source: str = "mapping"
    study_source: str = "study"  # the study's trial (study/trial: task, clock, score) from telesurg study
    web: WebConfig = field(default_factory=WebConfig)  # the web console (telesurg console --web)
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session

    def validate(self) -> None:
        """Raise ConfigError naming the problem."""
        check_id("site", self.site)
        check_id("service", self.service)
        if not self.arms:
            raise ConfigError("console needs at least one arm (--arm ARM or --arm MASTER:ARM)")
        for spec in self.arms:
            parse_arm(spec)
        if not 1.0 <= self.clutch_hz <= 200.0:
            raise ConfigError(f"clutch_hz={self.clutch_hz} outside [1, 200]")
        if not 0.1 <= self.command_timeout_s <= 60.0:
            raise ConfigError(f"command_timeout_s={self.command_timeout_s} outside [0.1, 60]")
        if not 0.1 <= self.estop_confirm_s <= 60.0:
            raise ConfigError(f"estop_confirm_s={self.estop_confirm_s} outside [0.1, 60]")
        if self.jog_frame not in JOG_FRAMES:
            raise ConfigError(f"jog_frame {self.jog_frame!r} invalid; valid: {', '.join(JOG_FRAMES)}")
        check_id("program", self.program)
        self.web.validate()


JOG_FRAMES = ("base", "world", "work", "forceps", "joint")
JOG_AXES = {"joint": ("j1", "j2", "j3", "j4", "j5", "j6")}  # other frames: x y z rx ry rz


def parse_arm(spec: str) -> tuple[str, str]:
    """``"m1:arm1"`` → ``("m1", "arm1")``; a bare ``"arm1"`` is driven by master ``m1``."""
    master, sep, arm = spec.partition(":")
    if not sep:
        master, arm = "m1", spec
    return check_id("master", master), check_id("arm", arm)


def console_clutch_key(keys: Keys, master: str) -> str:
    """``telesurg/<site>/console/<master>/clutch``: the console's clutch for one master."""
    return keys.console_clutch(master)


@dataclass(frozen=True)
class Notice:
    """One line for the console's log panel; ``toast`` ones also pop up."""

    stamp: float  # wall clock, s since the epoch
    severity: str  # info | warning | error
    text: str
    toast: bool = False


@dataclass(frozen=True)
class PendingConfirm:
    """A motion-starting command the server asked the operator to confirm (shared/authority.py)."""

    arm: str
    key: str
    cmd: Command  # as first sent (without the token)
    line: str
    target: str
    token: str
    question: str  # the server's ``confirm required: …`` summary


@dataclass
class ArmState:
    """What the console knows about one arm (guarded by the model's lock)."""

    arm: str
    master: str
    op: OperatingState | None = None
    op_rx: float = 0.0  # monotonic s of the last operating_state
    safety: SafetyState | None = None
    safety_rx: float = 0.0
    pedal: MasterButtons | None = None  # the master's buttons as master_capture publishes them
    pedal_rx: float = 0.0
    teleop: TeleopState | None = None  # the mapping's teleop state of the pair driving this arm
    teleop_rx: float = 0.0
    engaged_by_events: bool = False  # from the mapping's engage / disengage events
    engage_note: str = ""  # the last of those events' text
    events: deque[tuple[float, str, str, str]] = field(default_factory=lambda: deque(maxlen=50))
    jog_frame: str = "base"
    jog_axis: str = "x"
    last_reply: str = ""  # the last command reply for this arm, as shown

    @property
    def engaged(self) -> bool:
        """The mapping says the slave follows: its teleop state is ENABLED (before any teleop
        state arrived, e.g. from an older mapping: its last engage / disengage event)."""
        if self.teleop is not None:
            return self.teleop.state == "ENABLED"
        return self.engaged_by_events


class ConsoleModel:
    """The console's presence on the bus; thread-safe, UI-free.

    Zenoh callbacks and worker threads only record; :meth:`snapshot` and :meth:`drain` are
    what the UI reads.
    """

    def __init__(self, cfg: ConsoleConfig, node: Node) -> None:
        cfg.validate()
        self.cfg, self.node = cfg, node
        self.lock = threading.Lock()
        pairs = [parse_arm(s) for s in cfg.arms]
        self.arms: dict[str, ArmState] = {
            arm: ArmState(arm, master, jog_frame=cfg.jog_frame) for master, arm in pairs
        }
        self.masters = sorted({m for m, _ in pairs})
        self.alive: set[str] = set()
        self._notices: deque[Notice] = deque(maxlen=1000)
        self._clutch = dict.fromkeys(self.masters, False)
        self._press_at: dict[str, float] = {}  # master → monotonic s of a scheduled press
        self._clutch_lock = threading.Lock()  # one writer per clutch outlet at a time
        self._cmd_lock = threading.Lock()  # the command sequencer
        self._estop_lock = threading.Lock()  # the e-stop outlet (workers put on it)
        self._stop = threading.Event()
        self._wake = threading.Event()  # a console clutch changed: publish now
        self._pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="console-cmd")
        # e-stops get their own workers: they never queue behind commands waiting for replies
        self._estop_pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="console-estop")
        k = node.keys
        self._clutch_out = {m: node.outlet(console_clutch_key(k, m)) for m in self.masters}
        self._estop_out = node.outlet(k.estop)
        self._cmd_seq = Sequencer(cfg.service)  # headers of the commands (sent as queries)
        # the command waiting for the operator's confirmation (the UI asks; confirm() answers)
        self.pending_confirm: PendingConfirm | None = None
        s_src, w_src = only(cfg.slave_source), only(cfg.watchdog_source)
        for a in self.arms.values():
            node.subscribe(k.slave(a.arm, "operating_state"), OperatingState, self._on_op, sources=s_src)
            node.subscribe(k.safety(a.arm, "state"), SafetyState, self._on_safety, sources=w_src)
            # (latest: the mapping answers at once with the current state, then the stream follows)
            node.subscribe(
                k.mapping(a.arm, "teleop_state"),
                TeleopState,
                self._on_teleop,
                sources=only(cfg.mapping_source),
                latest=True,
            )
        for m in self.masters:
            node.subscribe(
                k.master(m, "buttons"), MasterButtons, self._on_pedal, sources=only(cfg.master_source)
            )
        node.subscribe(k.events(), SafetyEvent, self._on_event)
        # the study's current trial, if a study runs (latest: shown at once on a page opened mid-trial)
        self.trial: tuple[TrialState, float] | None = None  # (state, monotonic s received)
        node.subscribe(k.study_trial, TrialState, self._on_trial, sources=only(cfg.study_source), latest=True)
        node.watch_liveliness(k.alive(), self._on_alive)
        self._clutch_thread = threading.Thread(target=self._clutch_loop, daemon=True, name="console-clutch")
        self._clutch_thread.start()

    # -- inputs (zenoh threads: record only) ------------------------------------------------------
    def _on_op(self, m: OperatingState, key: str) -> None:
        arm = key.rsplit("/", 2)[-2]
        with self.lock:
            a = self.arms[arm]
            a.op, a.op_rx = m, time.monotonic()

    def _on_safety(self, m: SafetyState, key: str) -> None:
        with self.lock:
            a = self.arms.get(m.arm)
            if a is not None:
                a.safety, a.safety_rx = m, time.monotonic()

    def _on_teleop(self, m: TeleopState, key: str) -> None:
        with self.lock:
            a = self.arms.get(m.slave)
            if a is not None and key.rsplit("/", 2)[-2] == m.slave:
                a.teleop, a.teleop_rx = m, time.monotonic()

    def _on_pedal(self, m: MasterButtons, key: str) -> None:
        master = key.rsplit("/", 2)[-2]
        now = time.monotonic()
        with self.lock:
            for a in self.arms.values():
                if a.master == master:
                    a.pedal, a.pedal_rx = m, now

    def _on_event(self, m: SafetyEvent, key: str) -> None:
        with self.lock:
            a = self.arms.get(m.arm)
            if a is None and m.arm:
                return  # another arm of the site
            stamp = m.header.stamp_ns / 1e9
            if a is not None:
                a.events.append((stamp, m.header.source, m.kind, m.text))
                if m.kind == "engage":
                    a.engaged_by_events, a.engage_note = True, m.text
                elif m.kind in ("disengage", "engage_refused"):
                    a.engaged_by_events = a.engaged_by_events and m.kind == "engage_refused"
                    a.engage_note = m.text
            where = f"[{m.arm}] " if m.arm else ""
            self._notices.append(
                Notice(stamp, m.severity, f"{where}{m.header.source} {m.kind}: {m.text}", toast=False)
            )

    def _on_trial(self, m: TrialState, key: str) -> None:
        with self.lock:
            self.trial = (m, time.monotonic())

    def _on_alive(self, service: str, alive: bool) -> None:
        with self.lock:
            (self.alive.add if alive else self.alive.discard)(service)

    # -- what the UI reads -----------------------------------------------------------------------
    def snapshot(self) -> tuple[list[ArmState], dict[str, bool], set[str]]:
        """Copies of the arm states, the console clutch per master and the live services."""
        with self.lock:
            arms = [
                dataclasses.replace(a, events=deque(a.events, maxlen=a.events.maxlen))
                for a in self.arms.values()
            ]
            alive = set(self.alive)
        with self._clutch_lock:
            clutch = dict(self._clutch)
        return arms, clutch, alive

    def drain(self) -> list[Notice]:
        """Notices since the last call, oldest first."""
        with self.lock:
            out = list(self._notices)
            self._notices.clear()
        return out

    def note(self, severity: str, text: str, *, toast: bool = False) -> None:
        """Add a line to the log panel (any thread)."""
        with self.lock:
            self._notices.append(Notice(time.time(), severity, text, toast))

    # -- clutch ----------------------------------------------------------------------------------
    # Only the publisher thread puts on the clutch outlets: a put may block on a congested link
    # (control streams use CongestionControl.BLOCK) and must never freeze the UI.
    def clutch(self, master: str) -> bool:
        """The console clutch of ``master`` is pressed."""
        with self._clutch_lock:
            return self._clutch[master]

    def set_clutch(self, master: str, pressed: bool) -> None:
        """Press or release the console clutch of ``master`` (published at once)."""
        with self._clutch_lock:
            self._press_at.pop(master, None)
            changed = self._clutch[master] != pressed
            self._clutch[master] = pressed
        self._wake.set()
        if changed:
            self.note("info", f"console clutch {master} {'pressed' if pressed else 'released'}")

    def engage(self, master: str) -> None:
        """A fresh clutch press (release first if pressed): the mapping engages on a new press."""
        with self._clutch_lock:
            was = self._clutch[master]
            if was:  # released for a few clutch periods, then pressed again by the publisher
                self._clutch[master] = False
                self._press_at[master] = time.monotonic() + 3.0 / self.cfg.clutch_hz
        if was:
            self._wake.set()
        else:
            self.set_clutch(master, True)

    def _clutch_loop(self) -> None:
        """Publish every console clutch on each change and at least every ``1/clutch_hz`` s."""
        period = 1.0 / self.cfg.clutch_hz
        while not self._stop.is_set():
            pressed: list[str] = []
            with self._clutch_lock:
                now = time.monotonic()
                for m, at in list(self._press_at.items()):
                    if now >= at:
                        del self._press_at[m]
                        self._clutch[m] = True
                        pressed.append(m)
                state = dict(self._clutch)
                wait = min([period, *(at - now for at in self._press_at.values())])
            try:
                for m, on in state.items():
                    out = self._clutch_out[m]
                    out.put(MasterButtons(out.header(), on, True))
            except Exception as exc:  # the session is gone: master_capture sees the clutch go stale
                if not self._stop.is_set():
                    log.exception("console clutch publisher stopped")
                    self.note("error", f"console clutch no longer published: {exc}", toast=True)
                return
            for m in pressed:
                self.note("info", f"console clutch {m} pressed (engage)")
            self._wake.wait(max(wait, 0.0))
            self._wake.clear()

    # -- commands --------------------------------------------------------------------------------
    def command(
        self, arm: str, name: str, args: Sequence[str] = (), *, target: str = "slave"
    ) -> Future[bool]:
        """Send an operator command in the background; the reply (or refusal) becomes a notice.

        ``target``: ``slave`` (``slave/<arm>/command``) or ``mapping`` (``mapping/<arm>/command``).
        The future's result is True if the command was accepted.
        """
        k = self.node.keys
        key = k.command(arm) if target == "slave" else k.mapping_command(arm)
        line = " ".join((name, *args))
        try:
            with self._cmd_lock:
                header = self._cmd_seq.next()
            # from_body validates like the receiver will (name pattern, key=value arguments)
            cmd = Command.from_body(header, {"arm": arm, "name": name, "args": list(args)})
        except MessageError as exc:
            self._refused(arm, line, f"not sent: {exc}")
            done: Future[bool] = Future()
            done.set_result(False)
            return done
        self.note("info", f"[{arm}] > {'mapping ' if target == 'mapping' else ''}{line}")
        return self._pool.submit(self._request, arm, key, cmd, line, target)

    def _request(self, arm: str, key: str, cmd: Command, line: str, target: str) -> bool:
        try:
            reply = self.node.request(key, cmd, CommandReply, self.cfg.command_timeout_s)
        except TimeoutError:
            # (zenoh ends the query at once when nothing serves the key, else after the timeout)
            who = "slave_control" if target == "slave" else "the mapping (does it serve commands here?)"
            self._refused(arm, line, f"no reply on {key} from {who}")
            return False
        except MessageError as exc:  # the server (or the router's access control) refused it
            self._refused(arm, line, str(exc))
            return False
        if reply.confirm:  # a motion-starting command: the operator must confirm it
            with self.lock:
                self.pending_confirm = PendingConfirm(
                    arm, key, cmd, line, target, reply.confirm, reply.reason
                )
                self._notices.append(Notice(time.time(), "warning", f"[{arm}] {line}: {reply.reason}"))
            return False
        if reply.accepted:
            text = f"[{arm}] {line}: accepted" + (f" — {reply.reason}" if reply.reason else "")
            with self.lock:
                self.arms[arm].last_reply = text
                self._notices.append(Notice(time.time(), "info", text))
            return True
        self._refused(arm, line, reply.reason or "(no reason given)")
        return False

    def confirm(self, yes: bool) -> Future[bool]:
        """Answer the pending confirmation: send the command again with its token (``yes``), or
        drop it. The future's result is True if the confirmed command was accepted."""
        with self.lock:
            p, self.pending_confirm = self.pending_confirm, None
        if p is None or not yes:
            if p is not None:
                self.note("info", f"[{p.arm}] {p.line}: not confirmed, not sent")
            done: Future[bool] = Future()
            done.set_result(False)
            return done
        with self._cmd_lock:
            header = self._cmd_seq.next()
        cmd = Command(header, p.cmd.arm, p.cmd.name, (*p.cmd.args, f"{CONFIRM_ARG}={p.token}"))
        self.note("info", f"[{p.arm}] > {p.line} (confirmed)")
        return self._pool.submit(self._request, p.arm, p.key, cmd, p.line, p.target)

    def _refused(self, arm: str, line: str, reason: str) -> None:
        text = f"[{arm}] {line}: REFUSED — {reason}"
        with self.lock:
            if arm in self.arms:
                self.arms[arm].last_reply = text
            self._notices.append(Notice(time.time(), "error", text, toast=True))

    def set_jog(self, arm: str, *, frame: str | None = None, axis: str | None = None) -> tuple[str, str]:
        """Choose the jog frame / axis of ``arm`` (the axis resets when the frame changes kind)."""
        with self.lock:
            a = self.arms[arm]
            if frame is not None:
                a.jog_frame = frame
            if axis is not None:
                a.jog_axis = axis
            valid = JOG_AXES.get(a.jog_frame, ("x", "y", "z", "rx", "ry", "rz"))
            if a.jog_axis not in valid:
                a.jog_axis = valid[0]
            return a.jog_frame, a.jog_axis

    def jog(self, arm: str, direction: int) -> Future[bool]:
        """Jog ``arm`` along its chosen frame axis (+1 / -1) until ``stop``."""
        with self.lock:
            frame, axis = self.arms[arm].jog_frame, self.arms[arm].jog_axis
        return self.command(arm, "jog", (f"frame={frame}", f"axis={axis}", f"direction={direction}"))

    # -- e-stop ----------------------------------------------------------------------------------
    def estop(self, arm: str, action: str = "estop", reason: str = "operator") -> Future[bool]:
        """Publish an e-stop (or reset) for ``arm`` or ``*`` until the watchdog confirms it."""
        arms = list(self.arms) if arm == "*" else [arm]
        self.note("warning" if action == "estop" else "info", f"{action} sent to {arm}", toast=True)
        return self._estop_pool.submit(self._estop, arm, arms, action, reason)

    def _estop(self, arm: str, arms: list[str], action: str, reason: str) -> bool:
        t0 = time.monotonic()
        want = action == "estop"

        def confirmed() -> bool:
            with self.lock:
                return all(
                    (s := self.arms[a].safety) is not None
                    and self.arms[a].safety_rx > t0
                    and (s.state == "ESTOP") == want
                    for a in arms
                )

        ok = False
        while time.monotonic() - t0 < self.cfg.estop_confirm_s and not self._stop.is_set():
            with self._estop_lock:
                self._estop_out.put(EStop(self._estop_out.header(), arm, action, reason))
            deadline = time.monotonic() + 0.2
            while time.monotonic() < deadline and not (ok := confirmed()):
                time.sleep(0.02)
            if ok:
                break
        if ok:
            self.note("warning" if want else "info", f"{action} of {arm} confirmed by the watchdog")
        else:
            self.note(
                "error",
                f"{action} of {arm} NOT confirmed by the watchdog within {self.cfg.estop_confirm_s:g} s",
                toast=True,
            )
        return ok

    # -- lifetime --------------------------------------------------------------------------------
    def close(self) -> None:
        """Release every console clutch (published once more), stop the publisher and the workers."""
        self._stop.set()
        self._wake.set()
        self._clutch_thread.join(timeout=2.0)
        if not self._clutch_thread.is_alive():  # (else it is stuck in a put: leave the outlets)
            for m in self.masters:
                out = self._clutch_out[m]
                with contextlib.suppress(Exception):  # the session may be gone
                    out.put(MasterButtons(out.header(), False, True))
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._estop_pool.shutdown(wait=True, cancel_futures=True)
