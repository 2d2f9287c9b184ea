"""Always a way out (issue #20, acceptance 3): every documented stuck state of trocar mode, left by
the documented command, through the running services.

The states (docs/trocar.md, "Ways out"):

1. **Reach stall**: a jog in trocar mode toward the arm stops where the wrist centre leaves the arm's
   reach ("beyond the reach"). ``remove`` gets out: where the straight retraction would leave the
   reach too, the forceps pivots about the trocar while it retracts (``remove_pivot`` event).
2. **Watchdog hold during the removal**: the mapping hangs (SIGSTOP), the watchdog holds, the
   removal stops in ``transitional/remove``. When the hold is released, ``remove`` again.
3. **E-stop in trocar mode**: after the e-stop is reset, ``remove``.
4. **RCM-error hold in trocar mode**: an external force (``push``) deflects the arm during
   master–slave, the watchdog holds for the RCM error, the slave's command froze where the arm was
   measured, off the trocar — the hold never clears by itself. ``remove`` (once, while held) gets
   out: it starts when the watchdog allows motion and retracts straight along the forceps axis
   while the RCM error does not grow (the slave's guard).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import MasterHand, operator_command
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import (
    CartesianPose,
    CommandReply,
    MasterButtons,
    OperatingState,
    SafetyEvent,
    SafetyState,
)
from telesurg.tools.bench.harness import Pipeline
from telesurg.tools.experiment.jinno import STARTS

pytestmark = pytest.mark.process


class Console:
    def __init__(self, pipe: Pipeline, node: Node) -> None:
        self.pipe, self.node = pipe, node
        self.key = node.keys.command("arm1")
        self.lock = threading.Lock()
        self.mode, self.lease, self.safety, self.depth = "", False, "", 0.0
        self.events: list[tuple[float, str, str]] = []
        node.subscribe(node.keys.slave("arm1", "operating_state"), OperatingState, self._state)
        node.subscribe(node.keys.safety("arm1", "state"), SafetyState, self._safety)
        node.subscribe(node.keys.events("slave_control"), SafetyEvent, self._event)

    def _state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.mode, self.lease = m.control_mode, m.lease_ok

    def _safety(self, m: SafetyState, key: str) -> None:
        with self.lock:
            self.safety = m.state

    def _event(self, m: SafetyEvent, key: str) -> None:
        with self.lock:
            self.events.append((time.monotonic(), m.kind, m.text))

    def send(self, name: str, *args: str) -> CommandReply:
        r: CommandReply = operator_command(self.node, self.key, "arm1", name, *args)  # confirmed
        print(f"{name} {' '.join(args)} -> {'accepted' if r.accepted else 'REFUSED'}: {r.reason}")
        return r

    def get(self, attr: str) -> object:
        with self.lock:
            return getattr(self, attr)

    def events_since(self, t: float, kind: str) -> list[str]:
        with self.lock:
            return [text for ts, k, text in self.events if ts >= t and k == kind]

    def until(self, command: str, mode: str, timeout: float = 30) -> bool:
        """Command until the arm is in ``mode`` (a hold of this busy host stops a motion)."""
        for _ in range(4):
            assert self.pipe.wait(lambda: self.get("lease"), 30), "no lease"
            self.send(command)
            if self.pipe.wait(lambda: self.get("mode") == mode, timeout):
                return True
        return False

    def into_trocar_mode(self) -> None:
        for _ in range(4):
            assert self.pipe.wait(lambda: self.get("lease"), 30), "no lease"
            assert self.send("begin_posture_adjust", "method=ptp").accepted
            if self.pipe.wait(lambda: self.send("finish_posture_adjust").accepted or time.sleep(0.5), 20):  # type: ignore[func-returns-value]
                break
            self.send("abort", "reason=held during the PTP")
        else:
            pytest.fail("posture adjustment never finished")
        assert self.until("insert", "trocar", 20), "never reached trocar mode"


def idle_master(node: Node, stop: threading.Event) -> None:
    """A master at rest with the clutch released (nobody engages master–slave in this test)."""
    pose = node.outlet(node.keys.master("m1", "measured_cp"))
    buttons = node.outlet(node.keys.master("m1", "buttons"))
    while not stop.wait(0.004):
        buttons.put(MasterButtons(buttons.header(), False, True))
        pose.put(CartesianPose(pose.header(), "master", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))


@pytest.fixture
def console(tmp_path: Path) -> Iterator[Console]:
    overrides = {"slave_control": [f"q_home={list(STARTS['start_a'])}", "robot.jog_speed_mm_s=40.0"]}
    with (
        Pipeline(
            tmp_path / "logs", mirror=False, impair=False, master=True, probe=False, overrides=overrides
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as node,
    ):
        yield Console(p, node)
    for f in sorted((tmp_path / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-2000:]}")


def test_every_stuck_state_has_its_way_out(console: Console) -> None:
    c, pipe = console, console.pipe
    # 1. reach stall: jog toward the arm in trocar mode until the jog stops at the reach limit
    c.into_trocar_mode()
    assert c.send("set_motion_mode", "mode=jog").accepted
    t = time.monotonic()
    for _ in range(4):  # (re-commanded after a load hold, like an operator)
        assert pipe.wait(lambda: c.get("lease"), 30)
        c.send("jog", "frame=base", "axis=x", "direction=-1")
        if pipe.wait(lambda: any("reach" in e for e in c.events_since(t, "motion_stopped")), 15):
            break
    stalls = [e for e in c.events_since(t, "motion_stopped") if "reach" in e]
    print("stall:", stalls[:1])
    assert stalls, "the jog never reached the reach limit"
    t = time.monotonic()
    assert c.until("remove", "non_trocar"), "remove did not get out of the reach stall"
    print("pivot:", c.events_since(t, "remove_pivot"))

    # 2. a watchdog hold stops the removal; released, `remove` again
    c.into_trocar_mode()
    assert pipe.wait(lambda: c.get("lease"), 30)
    assert c.send("remove").accepted
    time.sleep(0.3)
    pipe.freeze("mapping")
    time.sleep(0.5)
    pipe.thaw("mapping")
    held = c.get("mode")
    print("after the hold:", held, c.get("safety"))
    assert c.until("remove", "non_trocar"), "remove did not resume after the hold"

    # 3. e-stop in trocar mode; reset; `remove`
    c.into_trocar_mode()
    pipe.estop("estop")
    assert pipe.wait(lambda: c.get("safety") == "ESTOP", 5)
    refused = c.send("remove")
    assert not refused.accepted and "reset" in refused.reason  # the refusal names the way out
    pipe.estop("reset")
    assert c.until("remove", "non_trocar"), "remove did not get out after the e-stop reset"


# -- 4. the RCM-error hold in trocar mode -------------------------------------------------------
#
# In trocar-mode master–slave an external force (the simulated hand, ``push`` at the tip: a
# collision, an assistant leaning on the forceps) deflects the arm off the trocar; the watchdog
# holds for the RCM error, and the slave, as on every hold out of following, freezes its command
# where the arm was measured — off the trocar. When the force is gone the arm stays there: the RCM
# error stays above the watchdog's limit, so the watchdog never grants a lease again. The way out
# (docs/trocar.md, "Ways out"): ``remove``.

PUSH_N = 60.0  # N at the tip, sideways (the forceps points down into the patient)
PUSH_S = 0.4  # s
WALL_OK_N = 40.0  # N: the tip-force limit here, above the body wall's push on an arm off the trocar


class RcmConsole(Console):
    """The console, with the RCM error, the follow flag and the watchdog's causes as they come."""

    def __init__(self, pipe: Pipeline, node: Node, master: MasterHand) -> None:
        super().__init__(pipe, node)
        self.master = master
        self.following, self.rcm = False, 0.0
        self.trace: list[tuple[float, str, float, bool]] = []  # (t, mode, RCM mm, lease)
        self.causes: tuple[str, ...] = ()
        node.subscribe(node.keys.slave("arm1", "operating_state"), OperatingState, self._rcm_state)
        node.subscribe(node.keys.safety("arm1", "state"), SafetyState, self._causes)

    def _rcm_state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.following, self.rcm = m.follow, m.rcm_error_mm
            self.trace.append((time.monotonic(), m.control_mode, m.rcm_error_mm, m.lease_ok))

    def _causes(self, m: SafetyState, key: str) -> None:
        with self.lock:
            self.causes = m.causes

    def rcm_held(self) -> bool:
        with self.lock:
            return any("RCM error" in c for c in self.causes)


@pytest.fixture
def rcm_console(tmp_path: Path) -> Iterator[RcmConsole]:
    # (the tip-force rule off its way: the arm frozen off the trocar rests against the body wall,
    # whose push reads as a tip force — 6.7 N on one CI run, above the 4 N limit — and that hold
    # would outlast the RCM one; the force-hold way out is not what this test is about)
    overrides = {
        "slave_control": [f"q_home={list(STARTS['start_a'])}", "robot.jog_speed_mm_s=40.0"],
        "watchdog": [f"rules.tip_force.limit_n={WALL_OK_N}"],
    }
    with (
        Pipeline(
            tmp_path / "logs", mirror=False, impair=False, master=False, probe=False, overrides=overrides
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as master_node,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as node,
    ):
        master = MasterHand(master_node)
        master.start()
        try:
            yield RcmConsole(p, node, master)
        finally:
            master.stop.set()
            master.join(2)
    for f in sorted((tmp_path / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-2000:]}")


def test_rcm_error_hold_in_trocar_mode_has_its_way_out(rcm_console: RcmConsole) -> None:
    c, pipe, master = rcm_console, rcm_console.pipe, rcm_console.master
    c.into_trocar_mode()
    for _ in range(4):  # engage master–slave (again after a load hold, like an operator)
        assert c.send("set_motion_mode", "mode=master_slave").accepted
        master.clutch = False
        time.sleep(0.3)
        master.clutch = True
        if pipe.wait(lambda: c.get("following"), 5):
            break
    else:
        pytest.fail("the slave never followed in trocar mode")
    t_push = time.monotonic()
    assert c.send("push", f"fy={PUSH_N}", f"seconds={PUSH_S}", "at=tip").accepted
    assert pipe.wait(c.rcm_held, 5), "the push never made the watchdog hold for the RCM error"
    master.clutch = False  # the operator lets go of the pedal
    time.sleep(PUSH_S + 2.0)  # the force is gone; the arm settles where its command is
    with c.lock:
        after = [(t, mode, rcm, lease) for t, mode, rcm, lease in c.trace if t >= t_push + PUSH_S + 1.0]
    rcm_after = [rcm for _, _, rcm, _ in after]
    print(
        f"after the push: mode {c.get('mode')}, RCM error {min(rcm_after):.2f}–{max(rcm_after):.2f} mm "
        f"over {len(after)} states, lease in {sum(1 for a in after if a[3])}; watchdog {c.get('safety')}: "
        f"{c.get('causes')}"
    )
    # the stuck state: with the force gone the arm rests off the trocar and the watchdog keeps holding
    assert c.rcm_held() and not c.get("lease"), f"not held for the RCM error: {c.get('causes')}"
    assert all(mode == "trocar" and rcm > 2.0 and not lease for _, mode, rcm, lease in after), after[-3:]
    assert any("way out: remove" in cause for cause in c.get("causes")), c.get("causes")  # type: ignore[attr-defined]
    # the documented way out: `remove` — accepted while held, it starts when the watchdog allows
    # motion (transitional/remove: the RCM no longer judged by the watchdog, by the slave's guard instead)
    t_out = time.monotonic()
    r = c.send("remove")
    assert r.accepted, r.reason
    sent = 1
    while not pipe.wait(lambda: c.get("mode") == "non_trocar", 20) and sent < 4:
        print("held again during the removal (this busy host): remove again")  # the documented way
        assert pipe.wait(lambda: c.get("lease"), 30), "no lease in transitional/remove"
        assert c.send("remove").accepted
        sent += 1
    with c.lock:
        out = [rcm for t, mode, rcm, _ in c.trace if t >= t_out and mode == "transitional"]
    print(
        f"removal: {time.monotonic() - t_out:.1f} s, remove sent {sent}×, RCM error from "
        f"{out[0]:.2f} mm, max {max(out):.2f} mm, at the exit {out[-1]:.2f} mm; "
        f"events: {c.events_since(t_out, 'remove_pending')} {c.events_since(t_out, 'motion_stopped')}"
    )
    assert c.get("mode") == "non_trocar", f"remove did not get out of the RCM hold: {c.get('causes')}"
    stopped = c.events_since(t_out, "hold") + c.events_since(t_out, "motion_stopped")
    assert sent == 1 or stopped, "a second remove was needed though nothing stopped the first"
    assert max(out) <= out[0] + 1.0, "the removal carried the forceps further off the trocar"
