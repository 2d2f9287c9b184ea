"""Live VIP reallocation through the running services: Jang 2014, Fig. 9 (issue #20, acceptance 4).

Router, watchdog, slave_control (MuJoCo, the two VIP arms), mapping (``mode = "vip"``) and
master_capture run as processes on loopback (``deploy/vip``). The scripted master moves back and
forth along its x axis between two plateaus (0 and −120 mm, 12 s per cycle); this test is the
operator console: it holds the console clutch (``console/m1/clutch``) over one outward stroke at a
time and sends the operator commands (confirmed, as the console).

The paper's case, on arm 1: its VIP is set to the paper's VIP (the Fig. 6 VIP, ``set_vip``); the
target is the initial wrist moved 60 mm toward the feet (``FIG9_TARGET_OFFSET_M``).

1. **Before.** A 120 mm master stroke at scale 0.5 asks the wrist to go the 60 mm to the target:
   the mapping's VIP IK leaves Table I (q2 past 50°) and holds; the MuJoCo wrist stops > 15 mm
   short. The elbow jog is refused while the arm follows the master, and, at the stall, along −x
   (q2 would pass its limit: the reply names it).
2. **Step 2, live.** ``elbow_jog axis=midrange`` on the slave: the elbow swings on the forearm
   sphere toward mid-range joints, off the VIP line, while the MuJoCo wrist stays put;
   ``reallocate_vip`` is refused while it moves.
3. **Steps 3-6, live.** ``reallocate_vip`` on the mapping: the new VIP is ``select_vip`` of the
   joints the slave measures (the line through the moved elbow).
4. **After.** The operator sets the motion scale so one more stroke covers what is left and
   engages: the MuJoCo wrist reaches the target (within 1 mm), with no IK hold on the way.
"""

from __future__ import annotations

import contextlib
import itertools
import re
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from helpers import operator_command
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.kinematics.elbow import limit_margin, off_line
from telesurg.shared.messages import (
    CartesianPose,
    CommandReply,
    JointState,
    MasterButtons,
    SafetyEvent,
    TeleopState,
)
from telesurg.shared.robots.vip import kinematics as vip
from telesurg.tools.bench.harness import Pipeline
from telesurg.tools.experiment.jang import FIG9_TARGET_OFFSET_M, paper_vip

pytestmark = pytest.mark.process
DEPLOY = Path(__file__).resolve().parents[1] / "deploy" / "vip"
G = vip.VIP_ARM1
STROKE_M = 0.120  # m: the master's stroke (plateau 0 → plateau −STROKE_M along its x)
#: the master path: plateau 0 (1.5 s), cosine ramp out (4 s), plateau −120 mm (2.5 s), ramp back
#: (4 s); short plateaus: on this shared host a watchdog hold may end any engagement, the shorter
#: it has to last the better
PATH = [(0.0, 0.0), (1.5, 0.0), (5.5, -STROKE_M), (8.0, -STROKE_M), (12.0, 0.0)]
TARGET_TOL_MM = 1.0


def _write_path(path: Path) -> None:
    rows = ["t,x,y,z"]
    for (t0, x0), (t1, x1) in itertools.pairwise(PATH):
        for t in np.arange(t0, t1, 0.05):
            s = 0.5 - 0.5 * np.cos(np.pi * (t - t0) / (t1 - t0))
            rows.append(f"{t:.3f},{x0 + (x1 - x0) * s:.6f},0,0")
    rows.append(f"{PATH[-1][0]:.3f},{PATH[-1][1]:.6f},0,0")
    path.write_text("\n".join(rows) + "\n")


class Site:
    """What the console sees of the running site, and its clutch."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.lock = threading.Lock()
        self.master_x: list[tuple[float, float]] = []  # (receive time, m)
        self.wrist: list[tuple[float, np.ndarray]] = []  # arm1's wrist: FK of measured_js
        self.q: list[tuple[float, np.ndarray]] = []  # arm1 measured_js
        self.events: list[tuple[float, str, str, str]] = []
        self.teleop: list[tuple[float, TeleopState]] = []
        self.clutch = False
        k = node.keys
        node.subscribe(k.master("m1", "measured_cp"), CartesianPose, self._on_master)
        node.subscribe(k.slave("arm1", "measured_js"), JointState, self._on_js)
        node.subscribe(k.events(), SafetyEvent, self._on_event)
        node.subscribe(k.mapping("arm1", "teleop_state"), TeleopState, self._on_teleop)
        self._clutch_out = node.outlet(k.console_clutch("m1"))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._press, daemon=True)
        self._thread.start()

    def _on_master(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            self.master_x.append((time.monotonic(), m.position[0]))

    def _on_js(self, m: JointState, key: str) -> None:
        q = np.array(m.position)
        w = vip.fk(q, G).wrist  # the slave's measured_cp is this FK of its measured joints
        with self.lock:
            self.q.append((time.monotonic(), q))
            self.wrist.append((time.monotonic(), w))

    def _on_event(self, m: SafetyEvent, key: str) -> None:
        with self.lock:
            self.events.append((time.monotonic(), m.arm, m.kind, m.text))

    def _on_teleop(self, m: TeleopState, key: str) -> None:
        with self.lock:
            self.teleop.append((time.monotonic(), m))

    def _press(self) -> None:
        """The console's clutch key, sent at 50 Hz (master_capture ORs it while fresh)."""
        while not self._stop.wait(0.02):
            out = self._clutch_out
            out.put(MasterButtons(out.header(), self.clutch, True))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)

    # -- what the operator looks at
    def now_wrist(self) -> np.ndarray:
        with self.lock:
            return self.wrist[-1][1].copy()

    def now_q(self) -> np.ndarray:
        with self.lock:
            return self.q[-1][1].copy()

    def now_x(self) -> float:
        with self.lock:
            return self.master_x[-1][1] if self.master_x else float("nan")

    def state(self) -> TeleopState | None:
        with self.lock:
            return self.teleop[-1][1] if self.teleop else None

    def events_since(self, t: float, kind: str, arm: str = "arm1") -> list[str]:
        with self.lock:
            return [x for tt, a, k, x in self.events if tt >= t and k == kind and a == arm]

    def command(self, key: str, name: str, *args: str) -> CommandReply:
        r = operator_command(self.node, key, "arm1", name, *args)
        print(f"{name} {' '.join(args)} -> {'accepted' if r.accepted else 'REFUSED'}: {r.reason}")
        return r


def wait_for(what: str, cond: Callable[[], bool], timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def on_plateau(s: Site, x: float) -> bool:
    return abs(s.now_x() - x) < 1e-6


def stroke(s: Site, during: Callable[[], None] | None = None) -> bool:
    """One outward stroke with the clutch held: pressed at the start of the master's 0 plateau,
    released on the −120 mm plateau once the wrist has settled; ``during`` runs on that plateau
    if the mapping follows then. Returns whether it followed from the start to the plateau. On
    this busy host the watchdog may refuse the engage or hold in the middle (latency, stale
    streams): the callers judge what the wrist did and stroke again."""
    wait_for("the master leaving its 0 plateau", lambda: not on_plateau(s, 0.0), 40.0)
    wait_for("the master back on its 0 plateau", lambda: on_plateau(s, 0.0), 40.0)
    t_press = time.monotonic()
    s.clutch = True
    with contextlib.suppress(AssertionError):  # judged below
        wait_for(
            "the mapping engaged",
            lambda: (st := s.state()) is not None and st.state in ("ENABLED", "HOLDING"),
            2.5,
        )
    st = s.state()
    if st is None or st.state != "ENABLED":
        print(f"engage not usable ({st.state if st else None}: {st.reason if st else ''}): next cycle")
        s.clutch = False
        time.sleep(0.5)
        return False
    wait_for("the master on its −120 mm plateau", lambda: on_plateau(s, -STROKE_M), 20.0)
    time.sleep(1.0)  # the 1 kHz interpolation and the servos settle on the last setpoint
    with s.lock:
        kept = all(m.state == "ENABLED" for t, m in s.teleop if t > t_press + 0.5)
    if during is not None and (now := s.state()) is not None and now.state == "ENABLED":
        during()  # (the mapping follows now, even if a hold cut the stroke short before)
    s.clutch = False
    wait_for("the clutch released", lambda: (st := s.state()) is not None and st.state != "ENABLED", 10.0)
    time.sleep(0.5)
    if not kept:
        print("the engagement ended before the plateau (a hold on this busy host)")
    return kept


@pytest.fixture  # (per test: a rerun after a failure gets a fresh site)
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Pipeline, Site]]:
    tmp = tmp_path_factory.mktemp("vip_realloc")
    csv = tmp / "stroke.csv"
    _write_path(csv)
    overrides = {
        "master_capture": [
            'scripted.trajectory="csv"',
            f'scripted.csv_path="{csv}"',
            "scripted.clutch=[]",  # the console's clutch only (this test)
            "scripted.clutch_repeat_s=0.0",
        ],
    }
    with (
        Pipeline(
            tmp / "logs", mirror=False, impair=False, probe=False, overrides=overrides, config_dir=DEPLOY
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as node,
    ):
        s = Site(node)
        try:
            wait_for("the slave's joints", lambda: bool(s.q) and bool(s.wrist), 30.0)
            yield p, s
        finally:
            s.close()
    for f in sorted((tmp / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-3000:]}")


def test_fig9_elbow_jog_and_live_reallocation_reach_the_target(site: tuple[Pipeline, Site]) -> None:
    _, s = site
    k = s.node.keys
    mapping_key, slave_key = k.mapping_command("arm1"), k.command("arm1")
    w0 = vip.fk(G.home_q, G).wrist
    target = w0 + np.array(FIG9_TARGET_OFFSET_M)
    V_paper = paper_vip(G)

    # the paper's (Fig. 6) VIP on arm 1, before any engage
    r = s.command(
        mapping_key, "set_vip", *(f"{c}={v * 1e3:.4f}" for c, v in zip("xyz", V_paper, strict=True))
    )
    assert r.accepted, r.reason

    # 1. before: the stroke asks for the target; the VIP IK leaves Table I and the wrist stalls
    # (strokes again while a hold on this busy host cut one short: each asks for 60 mm more)
    t1 = time.monotonic()
    refusal: list[CommandReply] = []

    def jog_while_following() -> None:
        if not refusal:  # mm=0.1: harmless should a hold end the following just before it
            r = s.command(slave_key, "elbow_jog", "axis=z", "mm=0.1")
            if not r.accepted:
                refusal.append(r)

    for _ in range(8):
        stroke(s, jog_while_following)
        if refusal and any("IK" in h for h in s.events_since(t1, "clamped")):
            break
    assert refusal and "release the clutch" in refusal[0].reason
    P = s.now_wrist()
    short_mm = float(np.linalg.norm(target - P)) * 1e3
    holds = s.events_since(t1, "clamped")
    print(f"before: the wrist stalled {short_mm:.1f} mm short of the target; mapping: {holds[:1]}")
    assert short_mm > 15.0
    assert any("q2" in h and "Table I" in h for h in holds), holds
    q_stall = s.now_q()
    assert off_line(vip.fk(q_stall, G).elbow, vip.fk(q_stall, G).wrist, V_paper) < 0.5e-3  # on the line

    # a jog that takes q2 past its limit: refused at once, or (when the stall left q2 more than a
    # first step from its limit) stopped where q2 reaches it; either way the operator is told q2
    t_limit = time.monotonic()
    r = s.command(slave_key, "elbow_jog", "axis=x", "direction=-1")
    if r.accepted:
        wait_for(
            "the jog stopped",
            lambda: bool(s.events_since(t_limit, "motion_stopped") + s.events_since(t_limit, "hold")),
            10.0,
        )
        stops = s.events_since(t_limit, "motion_stopped")
        print(f"stopped: {stops}")
        assert stops and "q2" in stops[0]
        time.sleep(0.5)
        q_stall = s.now_q()
    else:
        assert "q2" in r.reason

    # 2. Step 2: the elbow toward mid-range joints, the wrist held (sent again if a watchdog hold
    # on this busy host stopped it: the search goes on from where the elbow is)
    t2 = time.monotonic()
    checked_busy = False
    for _ in range(10):
        t_jog = time.monotonic()
        r = s.command(slave_key, "elbow_jog", "axis=midrange")
        if not r.accepted and "as mid-range as this wrist allows" in r.reason:
            break
        if not r.accepted:  # no lease at this moment
            time.sleep(1.0)
            continue
        if not checked_busy:
            # the mapping knows the slave moves from the slave's operating state (20 Hz and on
            # change): give it a moment to hear of the jog the slave just accepted (sent at once,
            # the request overtook it on a busy host: accepted, the jog not yet known there)
            time.sleep(0.5)
            busy = s.command(mapping_key, "reallocate_vip")
            ended = s.events_since(t_jog, "elbow_jog_done") + s.events_since(t_jog, "hold")
            assert (not busy.accepted and "moving" in busy.reason) or (busy.accepted and ended), busy.reason
            checked_busy = True
        wait_for(
            "the elbow jog's end",
            lambda t=t_jog: bool(s.events_since(t, "elbow_jog_done") + s.events_since(t, "hold")),
            60.0,
        )
        if s.events_since(t_jog, "elbow_jog_done"):
            break
        time.sleep(1.0)
    time.sleep(0.5)
    done = s.events_since(t2, "elbow_jog_done")
    stopped = s.events_since(t2, "motion_stopped")
    assert not stopped, stopped
    with s.lock:
        during = np.array([w for t, w in s.wrist if t >= t2])
    drift_mm = float(np.max(np.linalg.norm(during - P, axis=1))) * 1e3
    q_moved = s.now_q()
    E_moved = vip.fk(q_moved, G).elbow
    off_mm = off_line(E_moved, P, V_paper) * 1e3
    m_before, m_after = (limit_margin(q, G.lower, G.upper) for q in (q_stall, q_moved))
    print(
        f"elbow jog: {done}; MuJoCo wrist within {drift_mm:.3f} mm of where it stalled; elbow "
        f"{off_mm:.1f} mm off the paper's VIP line; smallest joint margin {m_before:.3f} → {m_after:.3f}"
    )
    assert drift_mm < 0.5
    assert off_mm > 5.0
    assert m_after > m_before + 0.1

    # 3. Steps 3-6: the VIP from the joints the slave measures
    r = s.command(mapping_key, "reallocate_vip")
    assert r.accepted, r.reason
    assert re.search(r"elbow was [0-9.]+ mm off the previous VIP line", r.reason)
    V_new = np.array([float(v) for v in re.findall(r"-?[0-9]+\.[0-9]", r.reason.split(")")[0])]) / 1e3
    V_expected = vip.select_vip(s.now_q(), 0.05, G)
    print(f"VIP {np.round(V_paper * 1e3, 1)} → {np.round(V_new * 1e3, 1)} mm")
    assert np.linalg.norm(V_new - V_expected) < 0.3e-3

    # 4. after: one more stroke covers what is left, at the scale the operator sets for it
    for _attempt in range(6):
        P2 = s.now_wrist()
        left = float(P2[0] - target[0])
        if abs(left) * 1e3 < TARGET_TOL_MM:
            break
        assert left > 0.0, f"the wrist went past the target ({left * 1e3:.1f} mm)"
        r = s.command(mapping_key, "set_scale", f"value={min(left / STROKE_M, 2.0):.5f}")
        assert r.accepted, r.reason
        t4 = time.monotonic()
        stroke(s)
        holds = [h for h in s.events_since(t4, "clamped") if "back inside" not in h]
        assert not holds, holds  # no IK hold on the way: the new VIP reaches the target
    W_end = s.now_wrist()
    err_mm = float(np.linalg.norm(W_end - target)) * 1e3
    q_end = s.now_q()
    print(
        f"after: MuJoCo wrist {err_mm:.3f} mm from the target; joints "
        f"{np.round(np.degrees(q_end[[0, 1, 3, 4]]), 1)} deg, q3 {q_end[2]:.4f} m; "
        f"smallest margin {limit_margin(q_end, G.lower, G.upper):.3f}"
    )
    assert err_mm < TARGET_TOL_MM
    assert vip.within_limits(q_end, G, 1e-6)
