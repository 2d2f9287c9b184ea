"""Master–slave in trocar mode through the running services (Jinno 2014, issue #4 acceptance 2).

The test is the console and the master: it sends the operator commands (posture adjustment,
insert, master–slave, remove) and publishes the master pose and clutch pedal itself (as
``master_capture``), so it decides when the clutch is pressed. The RCM error is the slave's, from
MuJoCo's tip pose: it must stay < 1 mm throughout trocar mode, master–slave motion included.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from helpers import MasterHand, operator_command
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import CartesianPose, CommandReply, OperatingState
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process


class Master(MasterHand):
    """A 250 Hz master drawing a 10 mm circle, with a clutch the test presses."""

    def __init__(self, node: Node) -> None:
        super().__init__(node)
        self.node, self.t0 = node, time.monotonic()

    def position(self, now: float) -> tuple[float, float, float]:
        a = 2 * math.pi * (now - self.t0) / 3.0
        return (0.01 * math.cos(a), 0.01 * math.sin(a), 0.0)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Pipeline, Node, Master, Node]]:
    logs = tmp_path_factory.mktemp("trocar_ms") / "logs"
    overrides = {"slave_control": ["q_home=[0.0, -0.2, 0.6, 0.0, -0.3, 0.0]", "robot.jog_speed_mm_s=40.0"]}
    with (
        Pipeline(logs, mirror=False, impair=False, master=False, probe=False, overrides=overrides) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as node,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as console,  # the operator
    ):
        m = Master(node)
        m.start()
        try:
            yield p, node, m, console
        finally:
            m.stop.set()
            m.join(2)
    for f in sorted(logs.glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-2500:]}")


def test_master_slave_about_the_trocar(site: tuple[Pipeline, Node, Master, Node]) -> None:
    pipe, node, master, console = site
    states: list[tuple[float, str, float, bool, bool]] = []
    tips: list[tuple[float, float, float, float]] = []
    lock = threading.Lock()

    def on_state(m: OperatingState, key: str) -> None:
        with lock:
            states.append((time.monotonic(), m.control_mode, m.rcm_error_mm, m.follow, m.lease_ok))

    def on_tip(m: CartesianPose, key: str) -> None:
        with lock:
            tips.append((time.monotonic(), *m.position))

    k = node.keys
    node.subscribe(k.slave("arm1", "operating_state"), OperatingState, on_state)
    node.subscribe(k.slave("arm1", "measured_cp"), CartesianPose, on_tip)
    cmd_key = k.command("arm1")

    def send(name: str, *args: str) -> CommandReply:
        r = operator_command(console, cmd_key, "arm1", name, *args)
        print(f"{name} {' '.join(args)} -> {'accepted' if r.accepted else 'REFUSED'}: {r.reason}")
        return r

    def last() -> tuple[float, str, float, bool, bool]:
        with lock:
            return states[-1] if states else (0.0, "", 0.0, False, False)

    assert pipe.wait(lambda: last()[4], 30), "no lease"
    assert send("begin_posture_adjust", "method=ptp").accepted
    deadline = time.monotonic() + 20  # the PTP takes ~1.5 s; ask every 0.5 s
    while not send("finish_posture_adjust").accepted:
        assert time.monotonic() < deadline, "posture adjustment never finished"
        time.sleep(0.5)
    assert send("insert").accepted
    assert pipe.wait(lambda: last()[1] == "trocar", 20), "never reached trocar mode"
    assert send("set_motion_mode", "mode=master_slave").accepted

    time.sleep(0.2)
    master.clutch = True  # the operator presses the pedal: engage
    assert pipe.wait(lambda: last()[3], 5), "the slave never followed in trocar mode"
    t_follow = time.monotonic()
    time.sleep(4.0)  # more than one 3 s master circle
    t_release = time.monotonic()
    master.clutch = False
    assert pipe.wait(lambda: not last()[3], 2)
    assert send("remove").accepted
    assert pipe.wait(lambda: last()[1] == "non_trocar", 20), "never came back out"

    with lock:
        in_trocar = [rcm for _, mode, rcm, _, _ in states if mode == "trocar"]
        following = [s for s in states if t_follow <= s[0] <= t_release]
        path = np.array([p[1:] for p in tips if t_follow + 0.5 <= p[0] <= t_release])
    travel_mm = float(np.ptp(path, axis=0).max() * 1e3)
    print(
        f"trocar mode: RCM error max {max(in_trocar):.3f} mm over {len(in_trocar)} states; "
        f"master–slave tip travel {travel_mm:.1f} mm"
    )
    assert all(s[1] == "trocar" for s in following)
    # The slave follows the whole window, unless the watchdog held it (a scheduling stall of this
    # busy 2-core host: the safe response, not a tracking failure); the RCM is checked regardless.
    share = sum(1 for s in following if s[3]) / max(1, len(following))
    assert len(following) >= 20 and share >= 0.8, f"followed {share:.0%} of the master–slave window"
    assert travel_mm > 5.0  # 10 mm master circle × scale 0.5 → a 10 mm circle at the tip
    assert max(in_trocar) < 1.0
