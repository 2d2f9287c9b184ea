"""Patient keep-out for every slave-side motion, through the running services (issue #20, acceptance 2).

The test is the operator console (and an idle master with the clutch released) of a running site —
router, watchdog, slave_control on MuJoCo, mapping. From ever-changing random postures it sends
500 random PTP targets — ``play`` of a one-point program (a joint PTP to a random pose; the
programs are in the site's teach store, as if taught) and ``begin_posture_adjust method=ptp`` (the
J4/J5 PTP that aims the forceps at the trocar) — and 100 random jog sequences (2–4 jogs each in the
frames base / world / work / forceps / joint, random axis, direction and duration, then ``stop``);
after some accepted posture adjustments (``TROCAR_SHARE``) the forceps is inserted into trocar
mode, jogged there (translations through the trocar IK, the roll, and some jogs trocar mode
refuses) and removed.

What a user would notice, judged by the test itself with the patient read from the site's MJCF
(the scene's ``patient_torso`` box, its ``trocar`` site and the ``trocar_cannula`` radius),
independently of the slave's own check (``shared/kinematics/keepout.py``, the site's larger
``patient_box_*``):

* the forceps as the slave actually moved it — every ``measured_js`` sample at its full rate,
  interpolated in joint space between samples, forward kinematics by MuJoCo (the ``wrist_center``
  and ``tip`` sites) — never enters the torso except through the trocar cannula;
* no accepted PTP has a planned path (settled measured start → target, at ≤ 3 mrad steps) that crosses the
  torso outside the trocar;
* every refusal and every stop names its reason, a keep-out refusal says where.

Speeds are raised for the test (PTP at 0.8 of the joint limits, jogs at 40 mm/s and 40°/s) so
every accepted motion runs to completion (or until the slave or a watchdog hold stops it) within
the test; faster motions are the harder case for the keep-out (more lag and overshoot of the
simulated arm behind its command). Under load the watchdog holds now and then; a hold stops a
motion, which is counted and the test goes on (the arm stays where the hold left it).
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import os
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
import pytest
from helpers import MasterHand, operator_command
from telesurg.shared import robots
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import (
    CommandReply,
    JointState,
    OperatingState,
    SafetyEvent,
)
from telesurg.shared.robots.mh3f.trocar import posture_adjust
from telesurg.tools.bench.harness import Pipeline

# (long: every accepted motion runs; see docs/trocar.md for the time it took)
pytestmark = [
    pytest.mark.process,
    pytest.mark.timeout(1500),
    # 6–25 min of motions and analysis on this 2-core VM (docs/trocar.md): too long for make test
    pytest.mark.skipif(
        not os.environ.get("TELESURG_SLOW"),
        reason="issue #20 acceptance 2, a slow test (6–25 min): TELESURG_SLOW=1 runs it",
    ),
]

N_PTP = 500  # random PTP targets (play + posture adjustment)
N_JOG_SEQUENCES = 100
N_PROGRAMS = 32  # one-point programs with random joint targets (the teach store's maximum)
SEED = 20
TROCAR_SHARE = 0.15  # of the accepted posture adjustments: inserted, jogged in trocar mode, removed
SCENE = Path(robots.get("mh3f").scene)
FRAMES = ("base", "world", "work", "forceps", "joint")
CARTESIAN = ("x", "y", "z", "rx", "ry", "rz")
JOINTS = ("j1", "j2", "j3", "j4", "j5", "j6")
# random program targets: joints (rad) in this range, the forceps above the floor
Q_LO = np.array([-0.6, -0.3, -0.2, -1.2, -1.6, -1.0])
Q_HI = np.array([0.6, 0.6, 0.9, 1.2, 0.4, 1.0])


class Patient:
    """The patient as the site's MJCF models it, and the forceps shaft by MuJoCo's kinematics."""

    def __init__(self) -> None:
        self.model = mujoco.MjModel.from_xml_path(str(SCENE))
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        torso = self.data.geom("patient_torso")
        assert np.allclose(torso.xmat, np.eye(3).ravel()), "the torso box is axis-aligned in the scene"
        half = self.model.geom("patient_torso").size
        self.lo, self.hi = torso.xpos - half, torso.xpos + half
        self.trocar = self.data.site("trocar").xpos.copy()
        self.cannula_r = float(self.model.geom("trocar_cannula").size[0])
        self.qadr = [int(self.model.joint(j).qposadr[0]) for j in JOINTS]
        self.sites = [self.model.site(n).id for n in ("wrist_center", "tip")]

    def shaft(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Wrist centre and tip (m, base frame) at joints ``q`` (n, 6), by MuJoCo."""
        m, d, qadr, sites = self.model, self.data, self.qadr, self.sites
        out = np.empty((len(q), 2, 3))
        for i, qi in enumerate(q):
            d.qpos[qadr] = qi
            mujoco.mj_kinematics(m, d)
            out[i] = d.site_xpos[sites]
        return out[:, 0], out[:, 1]

    def penetration(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per pose: how deep (m) the shaft is in the torso outside the trocar (0: not at all),
        and its distance (m) from the torso where it is outside it (0 where it touches)."""
        q = np.atleast_2d(q)
        pen, gap = np.zeros(len(q)), np.zeros(len(q))
        s = np.linspace(0.0, 1.0, 296)  # ~2 mm steps along the 590 mm wrist centre → tip
        for a in range(0, len(q), 2000):
            w, t = self.shaft(q[a : a + 2000])
            d = t - w
            length = np.linalg.norm(d, axis=1)
            u = d / length[:, None]
            c = self.trocar - w
            through = np.linalg.norm(np.cross(c, u), axis=1) <= self.cannula_r  # in the cannula
            s_c = np.einsum("ij,ij->i", c, u) / length  # the trocar along the shaft
            p = w[:, None, :] + s[None, :, None] * d[:, None, :]
            inside = np.min(np.minimum(p - self.lo, self.hi - p), axis=2)  # > 0 inside, per point
            # beyond the trocar the shaft is in the patient through it: allowed
            inside[through[:, None] & (s[None, :] > s_c[:, None] - 1e-9) & (s_c[:, None] > 0)] = -np.inf
            pen[a : a + 2000] = np.maximum(inside.max(axis=1), 0.0)
            out = np.linalg.norm(np.maximum(np.maximum(self.lo - p, p - self.hi), 0.0), axis=2)
            out[inside == -np.inf] = np.inf
            gap[a : a + 2000] = out.min(axis=1)
        return pen, gap

    def path_penetration(self, q_from: np.ndarray, q_to: np.ndarray) -> float:
        """Deepest penetration (m) along the straight joint path, at ≤ 3 mrad steps."""
        n = max(1, math.ceil(float(np.max(np.abs(q_to - q_from))) / 0.003))
        qs = q_from + (q_to - q_from) * np.linspace(0.0, 1.0, n + 1)[:, None]
        return float(self.penetration(qs)[0].max())


def random_programs(patient: Patient, rng: np.random.Generator) -> dict[str, list[dict[str, object]]]:
    """One-point programs at random joints, the forceps above the floor (tip and wrist ≥ 100 mm)."""
    programs: dict[str, list[dict[str, object]]] = {}
    while len(programs) < N_PROGRAMS:
        q = rng.uniform(Q_LO, Q_HI)
        w, t = patient.shaft(q[None, :])
        if min(w[0, 2], t[0, 2]) < 0.1:
            continue
        tip = [float(v) for v in t[0]]
        programs[f"r{len(programs):02d}"] = [{"q": [float(v) for v in q], "tip": tip, "mode": "non_trocar"}]
    return programs


@dataclass
class Bus:
    """What the console hears: measured joints at full rate, state, slave events."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    js: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)  # (seq, position)
    js_at: dict[int, tuple[float, str]] = field(default_factory=dict)  # seq → (arrival, control mode)
    sent: list[tuple[float, str]] = field(default_factory=list)  # (time, command) accepted
    rcm_trocar_max_mm: float = 0.0  # the slave's RCM error in trocar mode, largest reported
    mode: str = ""
    lease: bool = False
    events: list[tuple[float, str, str]] = field(default_factory=list)

    def on_js(self, m: JointState, key: str) -> None:
        with self.lock:
            self.js.append((m.header.seq, m.position))
            self.js_at[m.header.seq] = (time.monotonic(), self.mode)
            self._speed = max((abs(v) for v in m.velocity), default=0.0)
            self._stamp_ns = m.header.stamp_ns

    def on_state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.mode, self.lease = m.control_mode, m.lease_ok
            if m.control_mode == "trocar":
                self.rcm_trocar_max_mm = max(self.rcm_trocar_max_mm, m.rcm_error_mm)

    def on_event(self, m: SafetyEvent, key: str) -> None:
        with self.lock:
            self.events.append((time.monotonic(), m.kind, m.text))

    def q(self) -> np.ndarray:
        with self.lock:
            return np.array(self.js[-1][1])

    def speed(self) -> float:
        """Fastest joint (rad/s) in the last sample."""
        with self.lock:
            return self._speed

    _speed: float = 0.0
    _stamp_ns: int = 0

    def age_ms(self) -> float:
        """Age of the last sample (its stamp against this host's clock), ms."""
        with self.lock:
            return (time.time_ns() - self._stamp_ns) / 1e6

    def events_since(self, t: float, kinds: tuple[str, ...]) -> list[tuple[str, str]]:
        with self.lock:
            return [(k, text) for ts, k, text in self.events if ts >= t and k in kinds]


@dataclass
class Tally:
    """Every command sent and how it ended."""

    ptp: Counter[str] = field(default_factory=Counter)  # "play accepted", "posture refused", ...
    refusals: Counter[str] = field(default_factory=Counter)  # by reason class
    stops: Counter[str] = field(default_factory=Counter)  # stopped by the slave, by reason class
    jogs: Counter[str] = field(default_factory=Counter)
    sequences: int = 0
    bad_accepts: list[str] = field(default_factory=list)  # accepted PTPs whose planned path crosses
    unnamed: list[str] = field(default_factory=list)  # refusals / stops without a reason
    keepout_refused_torso: int = 0  # keep-out refusals whose path the test sees crossing the torso too
    keepout_refused_margin: int = 0  # ... only the site's larger box (the margin around the torso)
    planned_gap_mm: list[float] = field(default_factory=list)


def reason_class(text: str) -> str:
    t = text.lower()
    for key, words in (
        ("patient keep-out", ("keep-out",)),
        ("RCM guard", ("rcm error",)),
        ("watchdog hold", ("hold:",)),
        ("joint limit", ("joint limit", "at its limit")),
        ("reach / IK", ("reach", "singular", "ik ", "no solution", "not converge", "posture_adjust")),
        ("watchdog hold (lease)", ("lease",)),
        ("inside the trocar", ("inside the trocar",)),
        ("mode", ("refused in", "motion mode", "select")),
    ):
        if any(w in t for w in words):
            return key
    return "other: " + text[:60]


@dataclass
class Site:
    pipe: Pipeline
    node: Node
    bus: Bus
    patient: Patient
    rng: np.random.Generator
    targets: dict[str, np.ndarray]  # program name → its one point's joints


@pytest.fixture
def site(tmp_path: Path) -> Iterator[Site]:
    patient = Patient()
    rng = np.random.default_rng(SEED)
    programs = random_programs(patient, rng)
    store = tmp_path / "teach.json"
    store.write_text(
        json.dumps({"version": 1, "arm": "arm1", "trocars": {}, "current_trocar": "", "programs": programs})
    )
    overrides = {
        "slave_control": [
            f"robot.state_file={json.dumps(str(store))}",
            "robot.ptp_speed_fraction=0.8",
            "robot.playback_dwell_s=0.02",
            "robot.jog_speed_mm_s=40.0",  # (trocar-mode jogs are paced: trocar_arm.TrocarMotions.paced)
            "robot.jog_joint_speed_deg_s=40.0",
        ]
    }
    with (
        Pipeline(
            tmp_path / "logs", mirror=False, impair=False, master=False, probe=False, overrides=overrides
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as master_node,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as node,
    ):
        bus = Bus()
        k = node.keys
        node.subscribe(k.slave("arm1", "measured_js"), JointState, bus.on_js)
        node.subscribe(k.slave("arm1", "operating_state"), OperatingState, bus.on_state)
        node.subscribe(k.events("slave_control"), SafetyEvent, bus.on_event)
        master = MasterHand(master_node)
        master.start()
        try:
            targets = {name: np.array(pts[0]["q"], dtype=float) for name, pts in programs.items()}
            yield Site(p, node, bus, patient, rng, targets)
        finally:
            master.stop.set()
            master.join(2)
    for f in sorted((tmp_path / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-1500:]}")


def test_random_ptp_and_jog_never_cross_the_patient_outside_the_trocar(site: Site) -> None:
    pipe, node, bus, patient, rng = site.pipe, site.node, site.bus, site.patient, site.rng
    key = node.keys.command("arm1")
    tally = Tally()
    programs = sorted(site.targets)
    assert pipe.wait(lambda: bus.lease and bus.js, 60), "no lease / no measured_js"
    assert bus.mode == "non_trocar"
    t_start = time.monotonic()
    load_start = round(os.getloadavg()[0], 1)

    def send(name: str, *args: str) -> CommandReply:
        assert pipe.wait(lambda: bus.lease, 60), "no lease for a minute"
        r: CommandReply = operator_command(node, key, "arm1", name, *args)  # confirmed
        if r.accepted:
            with bus.lock:
                bus.sent.append((time.monotonic(), f"{name} {' '.join(args)}"))
        if not r.accepted and (not r.reason.strip() or r.reason.strip().endswith("refused")):
            tally.unnamed.append(f"{name} {args}: {r.reason!r}")
        return r

    def run_until(t: float, done: str, timeout: float = 20.0) -> None:
        """Wait for the motion to end (``done``, or stopped by the slave / a hold); note the stop."""
        kinds = (done, "motion_stopped", "hold")
        pipe.wait(lambda: bus.events_since(t, kinds), timeout)
        for kind, text in bus.events_since(t, ("motion_stopped", "hold")):
            why = text.split("stopped:", 1)[-1].strip()
            if not why:
                tally.unnamed.append(f"{kind}: {text!r}")
            tally.stops[f"{done.split('_')[0]}: {reason_class(text)}"] += 1

    def until_mode(command: str, mode: str, timeout: float = 90.0) -> bool:
        """Command until the arm is in ``mode``: a hold of this busy host stops the motion, and the
        operator commands it again once the lease is back (as long as ``timeout`` s)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            t = time.monotonic()
            send(command)
            kinds = ("motion_stopped", "hold")
            if pipe.wait(lambda: bus.mode == mode or bool(bus.events_since(t, kinds)), 10):  # noqa: B023
                if bus.mode == mode:
                    return True
                time.sleep(0.1)
        return bus.mode == mode

    def ptp(kind: str, q_target: np.ndarray | None, *args: str) -> bool:
        """One PTP target, judged at acceptance against the test's own planned path (True: accepted)."""
        settled = pipe.wait(lambda: bus.speed() < 0.05, 0.5)  # settled: the measured joints are the command
        q0, age, speed = bus.q(), bus.age_ms(), bus.speed()
        if kind == "posture":  # its target from the same sample as its start (J4/J5 aimed from here)
            try:
                q_target = posture_adjust(q0, patient.trocar)
            except Exception:
                q_target = None
        planned = patient.path_penetration(q0, q_target) if q_target is not None else 0.0
        t = time.monotonic()
        r = send(*args)
        tally.ptp[f"{kind} {'accepted' if r.accepted else 'refused'}"] += 1
        if r.accepted:
            if planned > 0.0:
                tally.bad_accepts.append(
                    f"{args}: {r.reason} (planned path {planned * 1e3:.1f} mm deep; from the sample "
                    f"{age:.0f} ms old, {speed:.3f} rad/s, {'settled' if settled else 'not settled: 0.5 s'}; "
                    f"q0 {np.round(q0, 4).tolist()}, the test's target {np.round(q_target, 4).tolist()})"
                )
            run_until(t, "playback_done" if kind == "play" else "ptp_done")
            return True
        cls = reason_class(r.reason)
        tally.refusals[f"{kind}: {cls}"] += 1
        if cls == "patient keep-out":
            assert " mm" in r.reason, f"a keep-out refusal names where: {r.reason}"
            if planned > 0.0:
                tally.keepout_refused_torso += 1
            else:
                tally.keepout_refused_margin += 1
        return False

    def jog_sequence(where: str = "non_trocar") -> None:
        tally.sequences += 1
        tally.jogs[f"sequences in {where} mode"] += 1
        send("set_motion_mode", "mode=jog")
        for _ in range(int(rng.integers(2, 5))):
            frame = str(rng.choice(FRAMES))
            axes = JOINTS if frame == "joint" else CARTESIAN
            if where == "trocar":  # mostly what trocar mode allows (translations, the roll), some not
                axes = ("j6", "j2") if frame == "joint" else ("x", "y", "z", "x", "y", "z", "rx", "ry")
            axis = str(rng.choice(axes))
            direction = int(rng.choice((1, -1)))
            t = time.monotonic()
            r = send("jog", f"frame={frame}", f"axis={axis}", f"direction={direction}")
            tally.jogs["accepted" if r.accepted else "refused"] += 1
            if not r.accepted:
                tally.refusals[f"jog: {reason_class(r.reason)}"] += 1
                continue
            pipe.wait(
                functools.partial(bus.events_since, t, ("motion_stopped", "hold")), rng.uniform(0.15, 0.5)
            )
            send("stop")
            for kind, text in bus.events_since(t, ("motion_stopped", "hold")):
                if not text.split("stopped:", 1)[-1].strip():
                    tally.unnamed.append(f"{kind}: {text!r}")
                tally.stops[f"jog: {reason_class(text)}"] += 1

    def trocar_jog_sequence() -> bool:
        """After an accepted posture PTP: insert into trocar mode, a jog sequence there, remove."""
        if not pipe.wait(lambda: send("finish_posture_adjust").accepted or time.sleep(0.3), 3):  # type: ignore[func-returns-value]
            send("abort", "reason=not aligned")  # (a hold stopped the PTP short of the target)
            return True
        if not until_mode("insert", "trocar"):
            send("abort", "reason=not inserted")
            return until_mode("remove", "non_trocar") if bus.mode != "non_trocar" else True
        jog_sequence("trocar")
        return until_mode("remove", "non_trocar")

    n_ptp, moved, playback = 0, True, False
    stuck = ""
    while (n_ptp < N_PTP or tally.sequences < N_JOG_SEQUENCES) and not stuck:
        if n_ptp < N_PTP:  # to a random posture: play a random one-point program (a joint PTP)
            if not playback:
                playback = send("set_motion_mode", "mode=playback").accepted
            prog = str(rng.choice(programs))
            moved = ptp("play", site.targets[prog], "play", f"program={prog}") or moved
            n_ptp += 1
        if rng.random() < N_JOG_SEQUENCES / N_PTP * 2 or n_ptp >= N_PTP:
            jog_sequence()
            moved, playback = True, False
        if n_ptp < N_PTP and moved:  # the posture adjustment PTP from here (J4/J5 aim at the trocar)
            # (its target is predicted from the settled start: from a sample taken before the arm
            # settled, J1-J3 were up to 28 mrad off and the test judged a path the slave never planned)
            adjusted = ptp("posture", None, "begin_posture_adjust", "method=ptp")
            n_ptp += 1
            if adjusted and rng.random() < TROCAR_SHARE:
                if not trocar_jog_sequence():  # (it ends in non_trocar mode by itself)
                    stuck = f"not out of {bus.mode} mode after the trocar-mode jogs (remove, 90 s)"
            elif adjusted:
                send("abort", "reason=next trial")
            moved = False  # (from the same posture the same PTP again: play first)
            playback = playback and not adjusted
        if n_ptp % 50 == 0:
            print(
                f"{time.monotonic() - t_start:.0f} s: {n_ptp} PTP, {tally.sequences} jog sequences",
                flush=True,
            )
    seconds = time.monotonic() - t_start

    with bus.lock:
        samples = sorted(bus.js)
    seqs = np.array([s for s, _ in samples])
    qs = np.array([q for _, q in samples])
    gaps = int(np.sum(np.diff(seqs) - 1))
    # joint-space interpolation between consecutive samples (4 ms apart), ≤ 2 mrad; across a
    # sequence gap (samples lost on the way) only the samples themselves: the path between is
    # unknown, and a straight joint-space line across a long gap is not the arm's path
    steps = [qs[:1]]
    for (sa, a), (sb, b) in itertools.pairwise(zip(seqs, qs, strict=True)):
        if sb - sa != 1:
            steps.append(b[None, :])
            continue
        n = max(1, math.ceil(float(np.max(np.abs(b - a))) / 0.002))
        steps.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    path = np.concatenate(steps)
    pen, gap = patient.penetration(path)
    deepest = patient.shaft(path[int(np.argmax(pen))][None, :])
    w, t = deepest[0][0], deepest[1][0]  # how far the deepest pose's axis passes from the trocar
    u = (t - w) / np.linalg.norm(t - w)
    deepest_axis_mm = float(np.linalg.norm(np.cross(patient.trocar - w, u))) * 1e3
    # where the measured forceps was in the patient outside the trocar: when, in which mode, after what
    pen_samples = patient.penetration(qs)[0]
    for i in np.argsort(pen_samples)[::-1][:5]:
        if pen_samples[i] <= 0.0:
            break
        at, mode = bus.js_at.get(int(seqs[i]), (0.0, "?"))
        before = [c for ts, c in bus.sent if ts <= at][-3:]
        print(
            f"in the patient {pen_samples[i] * 1e3:.2f} mm at {at - t_start:.1f} s in {mode} mode, "
            f"seq {seqs[i]}, after {before}"
        )
    figures = {
        "seconds": round(seconds, 1),
        "load_average_1min_start_end": [load_start, round(os.getloadavg()[0], 1)],
        "rcm_error_trocar_mode_max_mm": round(bus.rcm_trocar_max_mm, 3),
        "measured_samples_in_the_patient_outside_the_trocar": int(np.sum(pen_samples > 0.0)),
        "ptp": dict(tally.ptp),
        "ptp_refusals_by_reason": {k: v for k, v in tally.refusals.items() if not k.startswith("jog")},
        "keepout_refusals_path_through_torso": tally.keepout_refused_torso,
        "keepout_refusals_only_site_box_margin": tally.keepout_refused_margin,
        "jog_sequences": tally.sequences,
        "jogs": dict(tally.jogs),
        "jog_refusals_by_reason": {k: v for k, v in tally.refusals.items() if k.startswith("jog")},
        "stops_by_reason": dict(tally.stops),
        "measured_js_samples": len(samples),
        "measured_js_seq_gaps": gaps,
        "poses_checked": len(path),
        "max_penetration_mm": round(float(pen.max()) * 1e3, 3),
        "deepest_pose_wrist_tip_mm": [[round(v * 1e3) for v in x[0]] for x in deepest],
        "deepest_pose_axis_from_trocar_mm": round(deepest_axis_mm, 2),
        "poses_in_the_patient_outside_the_trocar": int(np.sum(pen > 0.0)),
        "closest_approach_outside_trocar_mm": round(float(gap.min()) * 1e3, 2),
        "poses_within_10_mm": int(np.sum(gap < 0.01)),
        "accepted_ptp_planned_through_patient": len(tally.bad_accepts),
        "unnamed_refusals_or_stops": len(tally.unnamed),
    }
    print(json.dumps(figures, indent=1))
    for line in tally.bad_accepts[:10] + tally.unnamed[:10]:
        print(line)
    assert not stuck, stuck
    assert tally.sequences >= N_JOG_SEQUENCES and n_ptp >= N_PTP
    assert not tally.bad_accepts, f"{len(tally.bad_accepts)} accepted PTPs planned through the patient"
    assert not tally.unnamed, f"refusals / stops without a reason: {tally.unnamed[:5]}"
    assert pen.max() == 0.0, f"the forceps entered the patient outside the trocar: {pen.max() * 1e3:.2f} mm"
    assert tally.keepout_refused_torso > 0, "no random PTP was refused for the keep-out: the test did not try"
