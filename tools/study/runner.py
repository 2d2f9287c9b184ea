"""Run a study: each trial on a real site, recorded, scored from its recording, appended.

A trial is one :class:`~telesurg.tools.bench.harness.Pipeline` — router, watchdog, slave_control
(MuJoCo), mapping, master_capture with the ``policy`` device driven by the synthetic operator
(:mod:`telesurg.tools.study.operator`) — whose console side reaches the site through the
:class:`~telesurg.tools.bench.impair.LinkImpairer` that adds the condition's delay and jitter each
way. The whole bus is recorded (:class:`~telesurg.services.record.Recorder`, MCAP) from before the
operator engages until the task is done (or its time limit), then scored from that file
(:func:`streams_from_mcap`, :func:`telesurg.shared.tasks.score`).

The study directory holds ``plan.json`` (the protocol's digest and the participant's schedule),
``results.jsonl`` (one line per finished trial, appended and flushed when the trial is scored),
``trials/NNN.mcap`` and ``trials/NNN/`` (the services' logs). A study run again resumes after its
last finished trial; a trial cut short (Ctrl-C, a service that died) leaves no line and is run
again.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.services.record import Recorder, iter_decoded, open_mcap
from telesurg.shared import tasks
from telesurg.shared.errors import SiteStartError
from telesurg.shared.keys import Keys
from telesurg.shared.messages import (
    CartesianPose,
    CartesianWrench,
    MasterButtons,
    OperatingState,
    SafetyState,
    SceneState,
    TrialState,
)
from telesurg.tools.study.protocol import Protocol, Trial, schedule

log = logging.getLogger(__name__)

OPERATOR = "telesurg.tools.study.operator:make"
POLICY_HZ = 50.0  # Hz: the synthetic operator is asked this often
ENGAGE_TIMEOUT_S = 90.0  # s: a site whose slave never follows by then fails the trial (a loaded host)
AFTER_DONE_S = 0.5  # s recorded after the task is done
#: a trial ends at its task's time limit of time following (the watchdog's holds on a loaded host
#: do not count), and at this many times the limit whatever happened
WALL_LIMIT = 4.0
#: the watchdog's freshness deadlines (its defaults, ms) that the protocol's host_margin_ms lengthens
WATCHDOG_DEADLINES = {
    "lease_valid_ms": 250.0,
    "master_deadline_ms": 80.0,
    "buttons_deadline_ms": 200.0,
    "servo_deadline_ms": 80.0,
    "slave_deadline_ms": 100.0,
    "slave_state_deadline_ms": 250.0,
}


class StudyError(Exception):
    """The study cannot go on (the message says why and what to do)."""


class TrialFailed(StudyError):
    """One trial could not be run to its end (a service died, the slave never followed)."""


@dataclass(frozen=True)
class Where:
    """A study's files."""

    out: Path

    @property
    def plan(self) -> Path:
        return self.out / "plan.json"

    @property
    def results(self) -> Path:
        return self.out / "results.jsonl"

    def mcap(self, index: int) -> Path:
        return self.out / "trials" / f"{index:03d}.mcap"

    def logs(self, index: int) -> Path:
        return self.out / "trials" / f"{index:03d}"


def finished(path: Path) -> dict[int, dict[str, Any]]:
    """The trials already in ``results.jsonl`` (index → row); a torn last line is ignored."""
    out: dict[int, dict[str, Any]] = {}
    if not path.exists():
        return out
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue  # (a line torn by a crash mid-write: that trial is run again)
        if isinstance(row, dict) and isinstance(row.get("trial"), int):
            out[row["trial"]] = row
    return out


def prepare(protocol: Protocol, participant: str, out: Path) -> tuple[list[Trial], dict[int, dict[str, Any]]]:
    """The schedule and the trials already done; writes ``plan.json`` on a new study.

    Raises:
        StudyError: ``out`` holds a study of another protocol or participant.
    """
    where = Where(out)
    trials = schedule(protocol, participant)
    plan = {
        "protocol": protocol.name,
        "digest": protocol.digest(),
        "participant": participant,
        "trials": [
            {"trial": t.index, "task": t.task, "condition": t.condition.name, "repetition": t.repetition,
             "practice": t.practice, "code": t.code}
            for t in trials
        ],
    }  # fmt: skip
    if where.plan.exists():
        old = json.loads(where.plan.read_text())
        if (old.get("digest"), old.get("participant")) != (plan["digest"], participant):
            raise StudyError(
                f"{out} holds study {old.get('protocol')!r} (protocol {old.get('digest')}, participant "
                f"{old.get('participant')!r}), not this one ({plan['digest']}, {participant!r}): "
                "choose another --out, or --restart to discard it"
            )
    else:
        out.mkdir(parents=True, exist_ok=True)
        where.plan.write_text(json.dumps(plan, indent=1) + "\n")
    return trials, finished(where.results)


def overrides(
    trial: Trial, margin_ms: float = 0.0, knobs: dict[str, Any] | None = None
) -> dict[str, list[str]]:
    """The site's settings for one trial: the operator as the master, the condition's scale, the
    watchdog's latency limits above the condition's delay (the study measures the delay, not the
    watchdog's answer to it), and ``margin_ms`` (the protocol's ``host_margin_ms``) added to every
    freshness deadline of the watchdog and the mapping; ``knobs``: the synthetic operator's
    (:mod:`telesurg.tools.study.operator`, e.g. ``drop_after_lift`` for a test that provokes a drop)."""
    c = trial.condition
    # (the latency the watchdog sees is the round trip plus the host's own; on a loaded host the
    # latter alone can pass the defaults, 100 / 250 ms)
    rtt = 2.0 * (c.delay_ms + c.jitter_ms)
    budget = max(100.0, rtt + 100.0) + margin_ms
    opts = {"task": trial.task, "scale": c.scale, "rate_hz": POLICY_HZ, "seed": trial.seed, **(knobs or {})}
    master = [
        'device="policy"',
        f'device_options.policy="{OPERATOR}"',
        'device_options.clutch="policy"',
        f"device_options.rate_hz={POLICY_HZ}",
        "device_options.max_step_mm=20.0",
        "device_options.press_at_s=0.5",
        # ms: what it sees may be this old before it stops acting (a loaded host delays it too)
        "device_options.stale_ms=1000.0",
    ] + [f"device_options.options.{k}={json.dumps(v)}" for k, v in opts.items()]
    task = tasks.get(trial.task)
    if len(task.arms) > 1:  # each arm its own master (m1, m2 …): the first here, the others in hands()
        master += [f"device_options.slave={json.dumps(task.arms[0])}", "device_options.options.role=0"]
    # (the slave's own setpoint deadline too: a stall of the master stream on a loaded host
    # otherwise stops the slave first, while the mapping's longer deadline keeps it engaged)
    slave = [f"setpoint_timeout_ms={100.0 + margin_ms}"] if margin_ms else []
    if task.scene:
        slave.append(f"scene={json.dumps(task.scene)}")
    if task.q_start:
        slave.append(f"q_home={list(task.q_start)}")
    if task.setup == "trocar":  # the insertion jog at the speed Jinno's experiment uses
        slave.append("robot.jog_speed_mm_s=40.0")
    out = {
        "slave_control": slave,
        "master_capture": master,
        "mapping": [
            f"scale={c.scale}",
            f"master_timeout_ms={100.0 + margin_ms}",
            f"slave_timeout_ms={100.0 + margin_ms}",
        ],
        "watchdog": [f"latency_budget_ms={budget}", f"latency_limit_ms={budget + 150.0}"]
        + [f"{k}={v + margin_ms}" for k, v in WATCHDOG_DEADLINES.items()],
    }
    if task.mapping:
        out["mapping"].append(f"mode={json.dumps(task.mapping)}")
    out["mapping"] += task.mapping_set
    if len(task.arms) > 1:
        pairs = [f"m{i + 1}:{arm}" for i, arm in enumerate(task.arms)]
        names = masters(task)
        for table in ("mapping", "watchdog"):
            out[table] += [f"pairs={json.dumps(pairs)}", f"master_source={json.dumps(','.join(names))}"]
        required = [names[0], "mapping", "slave_control", *names[1:]]
        out["watchdog"].append(f"required_services={json.dumps(required)}")
    return out


def masters(task: tasks.TaskSpec) -> list[str]:
    """The master_capture services of a task, one per arm: ``master_capture`` (``m1``) for the
    first, ``master_capture_2`` (``m2``) … for the others."""
    return ["master_capture", *(f"master_capture_{i + 1}" for i in range(1, len(task.arms)))]


def hands(trial: Trial) -> dict[str, list[str]]:
    """The other masters of a task with several arms (``master_capture_2`` … → ``m2`` …): each the
    synthetic operator's other hand on its own arm (settings after the first master's)."""
    task = tasks.get(trial.task)
    return {
        name: [
            f"arm=m{i + 1}",
            f"device_options.slave={json.dumps(arm)}",
            f"device_options.options.role={i}",
            f"device_options.options.seed={trial.seed + 1000 * i}",
        ]
        for i, (name, arm) in enumerate(zip(masters(task), task.arms, strict=True))
        if i > 0
    }


def record_keys(k: Keys, arms: tuple[str, ...] = ("arm1",)) -> list[str]:
    """What a trial records: the masters' streams (a replay's input), each arm's measurements and
    state, the watchdog's and the mapping's states, the scene (of the first arm: every arm's key
    carries the same) and every event — not the 500 Hz setpoints the mapping derives from the
    master, the leases or the heartbeats (a loaded host's CPU)."""
    slave = ("measured_cp", "measured_cf", "measured_js", "operating_state")
    out = [f"{k.prefix}/master/m{i + 1}/**" for i in range(len(arms))]
    for arm in arms:
        out += [*(k.slave(arm, s) for s in slave), k.safety(arm, "state"), k.mapping(arm, "teleop_state")]
    return [*out, k.slave(arms[0], "scene"), f"{k.prefix}/events/**"]


def object_sample(m: SceneState, obj: str, arms: tuple[str, ...]) -> tuple[float, ...] | None:
    """x, y, z (m) and holders (bits, :func:`telesurg.shared.tasks.holders`) of ``obj`` in ``m``."""
    if (seen := m.object(obj)) is None:
        return None
    (x, y, z), names = seen
    return x, y, z, float(tasks.holders(names, arms))


def _rows(rows: list[tuple[float, ...]], cols: int) -> np.ndarray:
    return np.array(rows, dtype=float).reshape(-1, cols)


def streams_from_mcap(path: Path, task: tasks.TaskSpec | None = None) -> tasks.Streams:
    """A trial's :class:`~telesurg.shared.tasks.Streams` from its recording (receive time, s): of
    the task's first arm and master ``m1``, its other arms' tips and forces, its object."""
    arms = task.arms if task is not None else ("arm1",)
    arm, obj = arms[0], task.obj if task is not None else ""
    with open_mcap(path) as reader:
        from telesurg.services.record import recording_site

        k = Keys(recording_site(reader))
        keys = {
            k.slave(arm, "operating_state"): "op",
            k.master("m1", "buttons"): "clutch",
            k.safety(arm, "state"): "safety",
            k.slave(arm, "scene"): "scene",
        }
        for a in arms:
            keys[k.slave(a, "measured_cp")] = f"tip:{a}"
            keys[k.slave(a, "measured_cf")] = f"force:{a}"
        got: dict[str, list[tuple[float, ...]]] = {
            n: [] for n in ("op", "clutch", "safety", "obj", "collide")
        }
        for a in arms:
            got[f"tip:{a}"], got[f"force:{a}"] = [], []
        rcm: list[tuple[float, ...]] = []
        for topic, log_ns, _pub, _payload, msg in iter_decoded(reader, lambda t: t in keys):
            t, what = log_ns / 1e9, keys[topic]
            if what.startswith("tip:") and isinstance(msg, CartesianPose):
                got[what].append((t, *msg.position))
            elif what.startswith("force:") and isinstance(msg, CartesianWrench):
                got[what].append((t, math.hypot(*msg.force)))
            elif what == "scene" and isinstance(msg, SceneState):
                got["collide"].append((t, float(msg.in_collision)))
                if (row := object_sample(msg, obj, arms)) is not None:
                    got["obj"].append((t, *row))
            elif what == "op" and isinstance(msg, OperatingState):
                got["op"].append((t, float(msg.follow)))
                rcm.append((t, msg.rcm_error_mm, float(msg.control_mode == "trocar")))
            elif what == "clutch" and isinstance(msg, MasterButtons):
                got["clutch"].append((t, float(msg.clutch)))
            elif what == "safety" and isinstance(msg, SafetyState):
                got["safety"].append((t, float(msg.state in tasks.HELD_STATES)))
    return tasks.Streams(
        tip=_rows(got[f"tip:{arm}"], 4),
        force=_rows(got[f"force:{arm}"], 2),
        rcm=_rows(rcm, 3),
        follow=_rows(got["op"], 2),
        clutch=_rows(got["clutch"], 2),
        safety=_rows(got["safety"], 2),
        obj=_rows(got["obj"], 5),
        collide=_rows(got["collide"], 2),
        more_tips={a: _rows(got[f"tip:{a}"], 4) for a in arms[1:]},
        more_forces={a: _rows(got[f"force:{a}"], 2) for a in arms[1:]},
    )


#: The masters a study can use: the synthetic operator (the policy device of master_capture) or a
#: person at the web console's page (mouse and keyboard, phone, gamepad).
MASTERS = ("operator", "web")
#: s the site stays up after a trial with a person at the page: the page shows the result
RESULT_SHOWN_S = 3.0


class Board:
    """The trial as the operator's console shows it (``study/trial``, :class:`TrialState`): the
    task, its instructions, the condition as the operator may see it (its code when blinded), the
    clock and the result."""

    def __init__(self, node: Any, trial: Trial, task: tasks.TaskSpec, shown: str, total: int) -> None:
        self.out = node.outlet(node.keys.study_trial, control=False, latest=True)
        self.trial, self.task, self.shown, self.total = trial, task, shown, total

    def show(self, phase: str, elapsed_s: float = 0.0, reached: int = 0, result: str = "") -> None:
        t = self.task
        self.out.put(
            TrialState(
                self.out.header(), self.trial.index + 1, self.total, t.name, t.instructions,
                self.shown, self.trial.practice, phase, round(elapsed_s, 2), t.time_limit_s, reached,
                len(t.goals), result, tuple(float(v) for g in t.goals for v in g.position),
            )
        )  # fmt: skip


def run_trial(
    trial: Trial,
    where: Where,
    margin_ms: float = 0.0,
    *,
    shown: str = "",
    total: int = 0,
    master: str = "operator",
    on_console: Callable[[str], None] | None = None,
    knobs: dict[str, Any] | None = None,
    time_limit_s: float | None = None,
) -> dict[str, Any]:
    """Run one trial on a fresh site and return its result row (raises TrialFailed).

    ``shown``: the condition as the operator may see it (default: its code), on the console's
    trial panel; ``total``: the trials of the schedule. ``master``: ``operator`` (the synthetic
    operator) or ``web`` (a person at the web console's page: ``on_console`` gets its one-time
    login URL once it is served); ``knobs``: the synthetic operator's (:func:`overrides`);
    ``time_limit_s``: instead of the task's (a shorter trial)."""
    from telesurg.shared.bus import Node
    from telesurg.tools.bench.harness import Pipeline
    from telesurg.tools.bench.netprofile import LinkProfile

    if master not in MASTERS:
        raise StudyError(f"master {master!r} unknown; valid: {', '.join(MASTERS)}")
    task = tasks.get(trial.task)
    if master == "web" and len(task.arms) > 1:
        raise StudyError(f"task {task.name} needs {len(task.arms)} masters: --master web drives one arm")
    logs, mcap = where.logs(trial.index), where.mcap(trial.index)
    shutil.rmtree(logs, ignore_errors=True)
    mcap.unlink(missing_ok=True)
    c = trial.condition
    ov = overrides(trial, margin_ms, knobs)
    web = master == "web"
    if web:  # the page is the master: no master_capture (its policy settings go)
        ov.pop("master_capture")
    link = LinkProfile(delay_ms=c.delay_ms, jitter_ms=c.jitter_ms)  # (set before anything connects)
    from telesurg.services.launcher import deploy_dir

    site_dir = deploy_dir() / task.robot  # (the robot's own site, e.g. deploy/vip; else the MH3F's)
    pipe = Pipeline(
        logs, mirror=False, impair=True, probe=False, overrides=ov, master=not web, console=web, link=link,
        config_dir=site_dir if (site_dir / "site.toml").is_file() else None,
    )  # fmt: skip
    part = mcap.with_name(mcap.name + ".part")
    try:
        p = pipe.__enter__()  # (closes what it started if it fails)
    except SiteStartError as e:  # (a loaded host: a service that did not come up in time)
        raise TrialFailed(f"trial {trial.index}: the site did not start: {e}") from e
    try:
        for name, sets in hands(trial).items():  # (through the impairer, as master_capture)
            p.site.spawn_instance(name, "master_capture", sets)
        study = Node(p.spec.client_bus("operator"), p.spec.site, "study")
        p.keep(study)
        board = Board(study, trial, task, shown or trial.code, total)  # (blinded unless told)
        board.show("setup")
        if web and on_console is not None:
            on_console(p.console_login())
        if task.setup == "trocar":
            from telesurg.tools.experiment.client import ArmClient

            # (as the operator console: only it may command the arm, shared/authority.py)
            with Node(p.spec.client_bus("operator"), p.spec.site, "console") as console:
                insert_through_trocar(ArmClient(console))
        info = {"trial": str(trial.index), "task": trial.task, "condition": c.name}
        watch = Watch(p.node, task)
        with Recorder(part, p.spec.site, info=info) as rec:
            for key in record_keys(p.node.keys, task.arms):
                rec.subscribe(p.node.session, key, p.node.keyring)
            limit = replace(task, time_limit_s=time_limit_s) if time_limit_s else task
            t_go, t_end, why = watch.run(p.site, limit, board)
            time.sleep(AFTER_DONE_S)
        if why:
            board.show("failed", result=why.splitlines()[0])
            raise TrialFailed(f"trial {trial.index}: {why}\n{p.diagnose(6)}")
        if web:
            time.sleep(RESULT_SHOWN_S)
    finally:
        p.close()
    os.replace(part, mcap)
    s = tasks.score(task, streams_from_mcap(mcap, task))
    row = {
        "trial": trial.index,
        "task": trial.task,
        "condition": c.name,
        "code": trial.code,
        "repetition": trial.repetition,
        "practice": trial.practice,
        **{f"cond_{k}": v for k, v in asdict(c).items() if k != "name"},
        "seed": trial.seed,
        "recording": str(mcap.relative_to(where.out)),
        "wall_s": round(t_end - t_go, 3),
        **s.row(),
    }
    return row


#: A slave-side motion of the set-up stopped by a watchdog hold (a loaded host) is commanded again
#: at most this often.
SETUP_ATTEMPTS = 10


def insert_through_trocar(arm: Any) -> None:
    """The MH3F's insert flow before a trocar task's go, as the surgeon's assistant sets the arm up
    (Jinno 2014, Fig. 5; docs/trocar.md): posture adjustment by PTP until aligned with the trocar,
    insert until trocar mode, master–slave. ``arm``: a
    :class:`~telesurg.tools.experiment.client.ArmClient` of the operator console. A hold of the
    watchdog stops a slave-side motion: it is aborted and commanded again.

    Raises:
        TrialFailed: the arm was not in trocar mode master–slave after the attempts.
    """

    def stopped_since(t: float, done: str) -> bool:
        return any(arm.events_of(k, t) for k in (done, "hold", "motion_stopped"))

    for _ in range(SETUP_ATTEMPTS):
        if not arm.wait(arm.lease_ok, 30):
            raise TrialFailed("set-up: the watchdog never allowed motion")
        t = time.monotonic()
        if arm.mode() == "non_trocar":
            arm.must("begin_posture_adjust", "method=ptp")
            arm.wait(lambda t=t: stopped_since(t, "ptp_done"), 30)
            if not arm.events_of("ptp_done", t):
                arm.send("abort", "reason=held during the set-up's PTP")
                continue
            arm.settle()
            if not arm.wait(lambda: arm.send("finish_posture_adjust").accepted, 5):
                arm.send("abort", "reason=not aligned after the PTP")
                continue
        t = time.monotonic()
        if arm.mode() != "trocar":
            arm.send("insert")
            arm.wait(lambda t=t: arm.mode() == "trocar" or stopped_since(t, "hold"), 30)
            if not arm.wait(lambda: arm.mode() == "trocar", 0.5):
                continue  # (held mid-insertion: insert again from where it stopped)
        if arm.send("set_motion_mode", "mode=master_slave").accepted:
            return
    raise TrialFailed(f"set-up: the arm never reached trocar-mode master–slave (mode {arm.mode()!r})")


class Watch:
    """What the harness follows live: the slave's tip (of the task's first arm), whether it follows,
    and a transfer's object (monotonic s)."""

    def __init__(self, node: Any, task: tasks.TaskSpec) -> None:
        self.lock = threading.Lock()
        self.tips: list[tuple[float, float, float, float]] = []
        self.obj: list[tuple[float, ...]] = []
        self.following = False
        self.task = task
        arm, src = task.arms[0], ["slave_control"]
        node.subscribe(node.keys.slave(arm, "measured_cp"), CartesianPose, self._on_tip, sources=src)
        node.subscribe(node.keys.slave(arm, "operating_state"), OperatingState, self._on_op, sources=src)
        if task.obj:
            node.subscribe(node.keys.slave(arm, "scene"), SceneState, self._on_scene, sources=src)

    def _on_tip(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            self.tips.append((time.monotonic(), *m.position))

    def _on_scene(self, m: SceneState, key: str) -> None:
        if (row := object_sample(m, self.task.obj, self.task.arms)) is not None:
            with self.lock:
                self.obj.append((time.monotonic(), *row))

    def _on_op(self, m: OperatingState, key: str) -> None:
        self.following = m.follow  # (a bool: set atomically from the bus thread)

    def run(self, site: Any, task: tasks.TaskSpec, board: Board | None = None) -> tuple[float, float, str]:
        """Wait for the go (the slave follows), then until the task is done or its time limit:
        (go, end, "" or why the trial failed), monotonic s. ``board``: shows the trial's phase,
        clock and, at the end, its result (4 Hz)."""
        deadline = time.monotonic() + ENGAGE_TIMEOUT_S
        shown = 0.0
        while not self.following:
            if (dead := site.dead()) or time.monotonic() > deadline:
                why = f"services exited: {dead}" if dead else "the slave never followed the operator"
                return math.nan, math.nan, why
            if board is not None and time.monotonic() - shown > 0.25:
                board.show("ready")
                shown = time.monotonic()
            time.sleep(0.05)
        go = last = time.monotonic()
        active = 0.0  # s the slave followed since the go: the time limit counts these
        while True:
            time.sleep(0.25)
            now = time.monotonic()
            active += (now - last) if self.following else 0.0
            last = now
            if dead := site.dead():
                return go, now, f"services exited: {dead}"
            with self.lock:
                tips = np.array(self.tips, dtype=float).reshape(-1, 4)
                obj = np.array(self.obj, dtype=float).reshape(-1, 5)
            tips = tips[tips[:, 0] >= go]
            over = active > task.time_limit_s or now - go > WALL_LIMIT * task.time_limit_s
            prog = tasks.evaluate(task, obj[obj[:, 0] >= go] if task.kind == "transfer" else tips)
            if board is not None:
                board.show("done" if prog.done or over else "running", active, len(prog.reached),
                           live_result(prog, tips, go, over))  # fmt: skip
            if prog.done or over:
                return go, now, ""


def live_result(prog: tasks.Progress, tips: np.ndarray, go: float, over: bool) -> str:
    """The trial's result as the console shows it at its end, from the live tip samples ("" while it
    runs); the scored row (from the recording) follows in results.jsonl."""
    if not (prog.done or over):
        return ""
    done_t = prog.done_t if prog.done_t is not None else float(tips[-1, 0]) if len(tips) else go
    inside = tips[tips[:, 0] <= done_t] if len(tips) else tips
    path_mm = tasks.path_length(inside[:, 1:]) * 1e3
    if prog.done:
        return f"done in {done_t - go:.1f} s · tip path {path_mm:.0f} mm"
    return f"not done: time limit · {len(prog.reached)} goals reached · tip path {path_mm:.0f} mm"
