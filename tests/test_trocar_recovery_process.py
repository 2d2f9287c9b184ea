"""Always a way out (issue #20, acceptance 3): every documented stuck state of trocar mode, left by
the documented command, through the running services.

The states (docs/trocar.md, "Ways out"):

1. **Reach stall**: a jog in trocar mode toward the arm stops where the wrist centre leaves the arm's
   reach ("beyond the reach"). ``remove`` gets out: where the straight retraction would leave the
   reach too, the forceps pivots about the trocar while it retracts (``remove_pivot`` event).
2. **Watchdog hold during the removal**: the mapping hangs (SIGSTOP), the watchdog holds, the
   removal stops in ``transitional/remove``. When the hold is released, ``remove`` again.
3. **E-stop in trocar mode**: after the e-stop is reset, ``remove``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import operator_command
from telesurg.services.bench.harness import Pipeline
from telesurg.services.experiment.jinno import STARTS
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import (
    CartesianPose,
    CommandReply,
    MasterButtons,
    OperatingState,
    SafetyEvent,
    SafetyState,
)

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
    overrides = {"slave_control": [f"q_home={list(STARTS['start_a'])}", "jog_speed_mm_s=40.0"]}
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
