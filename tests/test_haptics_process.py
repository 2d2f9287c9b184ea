"""Touching the tissue through the running services: the surgeon's master presses the MH3F's
forceps into the scene's tissue; slave_control publishes the contact force (``measured_cf``), the
watchdog's ``tip_force`` rule answers a force above the tissue limit with DEGRADED, then HOLD, with
the cause. The test is the master (a 250 Hz pose and the clutch); router, watchdog, slave_control
on MuJoCo and the mapping are the real services."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from helpers import GoalMaster as Master
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import CartesianPose, CartesianWrench, OperatingState, SafetyState
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process

LIMIT_N = 2.0  # N: the site's tissue limit for this test (below the 4 N default: a short press)


class Seen:
    def __init__(self, node: Node) -> None:
        self.lock = threading.Lock()
        self.tip = np.zeros(3)
        self.force: list[tuple[float, float]] = []  # (monotonic s, fz N)
        self.states: list[tuple[str, tuple[str, ...]]] = []
        self.follow = self.lease = False
        k = node.keys
        node.subscribe(k.slave("arm1", "measured_cp"), CartesianPose, self._tip)
        node.subscribe(k.slave("arm1", "measured_cf"), CartesianWrench, self._cf, sources=["slave_control"])
        node.subscribe(k.slave("arm1", "operating_state"), OperatingState, self._state)
        node.subscribe(k.safety("arm1", "state"), SafetyState, self._safety)

    def _tip(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            self.tip = np.array(m.position)

    def _cf(self, m: CartesianWrench, key: str) -> None:
        with self.lock:
            self.force.append((time.monotonic(), m.force[2]))

    def _state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.follow, self.lease = m.follow, m.lease_ok

    def _safety(self, m: SafetyState, key: str) -> None:
        with self.lock:
            if not self.states or self.states[-1][0] != m.state:
                self.states.append((m.state, m.causes))


@pytest.fixture
def site(tmp_path: Path) -> Iterator[tuple[Pipeline, Master, Seen]]:
    with (
        Pipeline(
            tmp_path / "logs",
            mirror=False,
            impair=False,
            master=False,
            probe=False,
            overrides={"watchdog": [f"rules.tip_force.limit_n={LIMIT_N}"]},
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as node,
    ):
        seen = Seen(node)
        m = Master(node)
        m.start()
        try:
            yield p, m, seen
        finally:
            m.stop.set()
            m.join(2)
    for f in sorted((tmp_path / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-1500:]}")


def test_pressing_the_tissue_gives_a_contact_force_then_degraded_then_hold(
    site: tuple[Pipeline, Master, Seen],
) -> None:
    pipe, master, seen = site
    assert pipe.wait(lambda: seen.lease and len(seen.force) > 10, 30), "no lease, or no measured_cf"
    with seen.lock:
        n0, t0 = len(seen.force), time.monotonic()
    time.sleep(1.0)
    with seen.lock:
        rate = (len(seen.force) - n0) / (time.monotonic() - t0)
        free = max(abs(f) for _, f in seen.force)
    print(f"measured_cf: {rate:.0f} messages/s in free space, |fz| ≤ {free:.4f} N")
    assert free < 1e-6  # nothing touches the instrument in free space

    def engage() -> None:
        for _ in range(5):  # (a load hold may refuse one)
            master.clutch = False
            time.sleep(0.3)
            master.clutch = True
            if pipe.wait(lambda: seen.follow, 5):
                return
        raise AssertionError("no engage")

    def tissue_hold() -> bool:
        with seen.lock:
            return any(s == "HOLD" and any("tip force" in c for c in cs) for s, cs in seen.states)

    engage()
    z0 = float(seen.tip[2])
    # press down (master −z, slave at scale 0.5) until the watchdog holds for the tissue force,
    # at most 160 mm of master travel; a hold for another cause (load) is engaged again
    for _ in range(80):
        if tissue_hold():
            break
        if not seen.follow:
            print("a hold for another cause interrupted the press: engage again")
            engage()
        master.goal = master.goal + np.array([0.0, 0.0, -0.002])
        time.sleep(0.06)
    time.sleep(0.3)
    with seen.lock:
        states, force, tip = list(seen.states), list(seen.force), seen.tip.copy()
    print(
        f"tip z {z0 * 1e3:.1f} → {tip[2] * 1e3:.1f} mm; largest fz {max(f for _, f in force):.2f} N; {states}"
    )
    assert max(f for _, f in force) > LIMIT_N  # the tissue pushed back, upward
    tissue = [(s, c) for s, c in states if any("tip force above the tissue limit" in x for x in c)]
    names = [s for s, _ in tissue]
    assert "DEGRADED" in names and "HOLD" in names and names.index("DEGRADED") < names.index("HOLD"), states
