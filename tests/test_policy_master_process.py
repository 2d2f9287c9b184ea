"""A policy drives a live site through the ``policy`` master device, supervised by an operator.

One real site (router, watchdog, slave_control on MuJoCo, mapping, master_capture with
``device = "policy"`` and ``clutch = "console"``): the scripted policy ``tests/policies/reach.py``
moves the master tip at 20 mm/s; the test is the operator's console, holding its clutch
(``console/m1/clutch``, identity ``console``). In turn:

1. the operator holds the clutch: the slave follows the policy;
2. the operator releases it: the slave stops following at once and stands still, though the policy
   goes on (control is the operator's again);
3. the policy pauses (returns None): nothing is published and the arm holds within the watchdog's
   master deadline;
4. an e-stop stops the arm that the policy drives.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
from telesurg.shared.bus import Node
from telesurg.shared.messages import CartesianPose, MasterButtons
from telesurg.tools.bench.harness import Pipeline, now_ns

REACH = Path(__file__).with_name("policies") / "reach.py"
DEADLINE_MS = 80.0  # the watchdog's master_deadline_ms (default)


class Console:
    """The operator console's clutch key: held (published at 20 Hz) or released."""

    def __init__(self, p: Pipeline) -> None:
        self.node = Node(p.spec.client_bus("operator"), p.spec.site, "console")
        self.out = self.node.outlet(self.node.keys.console_clutch("m1"))
        self.held = False
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.wait(0.05):
            self.out.put(MasterButtons(self.out.header(), self.held, True))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        self.node.close()


@pytest.mark.process
@pytest.mark.timeout(240)
def test_a_policy_drives_the_site_and_the_operator_the_estop_and_the_deadline_stop_it(tmp_path: Path) -> None:
    pause = tmp_path / "pause"
    options = [
        'device="policy"',
        f'device_options.policy="{REACH}:make"',
        'device_options.clutch="console"',
        "device_options.options.speed_mm_s=20.0",
        f'device_options.options.pause_file="{pause}"',
    ]
    with Pipeline(tmp_path / "logs", mirror=False, impair=False, overrides={"master_capture": options}) as p:
        masters: list[int] = []  # receive ns of the master's pose samples
        p.node.subscribe(
            p.node.keys.master("m1", "measured_cp"),
            CartesianPose,
            lambda m, k: masters.append(now_ns()),
            sources=["master_capture"],
        )
        console = Console(p)
        try:
            assert p.wait(lambda: len(masters) > 100, 30), "the policy master never published"
            assert not p.p.following()  # nobody holds the clutch: the policy alone does not engage

            # 1. the operator holds the clutch once the console says the arm is ready (a press
            # before it, while the site still starts, is refused and needs a new one): the slave
            # follows the policy
            assert p.wait_ready(30), "the mapping never became ready to engage\n" + p.diagnose()
            console.held = True
            assert p.wait_following(15), "the slave never followed the policy\n" + p.diagnose()
            t1 = now_ns()
            time.sleep(1.5)
            moved = p.p.motion_after(t1, 1.5)
            print(f"following the policy: the tip moved {moved:.1f} mm in 1.5 s")
            assert moved > 5.0  # 20 mm/s at the mapping's scale 0.5: ~15 mm

            # 2. the operator releases it: the slave stops following and stands still
            console.held = False
            t2 = now_ns()
            assert p.wait(lambda: not p.p.following(), 1.0), "the slave went on following after the release"
            t_stop = p.p.first_op_after(t2, lambda r: not r[1])
            assert t_stop is not None
            n_before = len(masters)
            time.sleep(1.0)
            still = p.p.motion_after(t_stop[0] + 200_000_000, 0.8)
            print(
                f"released: follow off after {(t_stop[0] - t2) / 1e6:.0f} ms; "
                f"then the tip moved {still:.2f} mm"
            )
            assert still < 0.5
            assert len(masters) - n_before > 300  # the policy goes on; the slave no longer takes it

            # 3. the policy pauses: nothing is published, the arm holds within the master deadline
            assert p.wait_ready(10), "the mapping was not ready again after the release\n" + p.diagnose()
            console.held = True
            assert p.wait_following(10), "the slave did not follow again after a new press\n" + p.diagnose()
            time.sleep(0.5)
            pause.touch()
            assert p.wait(lambda: masters and now_ns() - masters[-1] > 500_000_000, 5)
            last = masters[-1]
            hold = p.p.first_op_after(last, lambda r: not r[1])
            with p.p.lock:  # the watchdog's first HOLD that names the master's stream
                safety = next(
                    (
                        r[0]
                        for r in p.p.safety
                        if r[0] >= last and r[1] == "HOLD" and "master" in " ".join(r[2])
                    ),
                    None,
                )
            assert hold is not None and safety is not None, "the arm never held after the policy paused"
            hold_ms, safety_ms = (hold[0] - last) / 1e6, (safety - last) / 1e6
            print(
                f"policy paused: watchdog HOLD {safety_ms:.0f} ms, slave stopped following {hold_ms:.0f} ms "
                f"after the last master sample (deadline {DEADLINE_MS:g} ms)"
            )
            assert safety_ms < DEADLINE_MS + 60  # the deadline plus the watchdog's check and delivery
            assert p.p.motion_after(hold[0] + 100_000_000, 0.3) < 0.5

            # 4. the policy acts again; a new press engages; an e-stop stops the arm
            pause.unlink()
            console.held = False
            time.sleep(0.3)
            console.held = True
            assert p.wait_following(15), "the slave did not follow again after the policy resumed"
            time.sleep(0.5)
            t4 = p.estop("estop")
            assert p.wait(lambda: p.p.first_op_after(t4, lambda r: not r[1]) is not None, 2)
            stopped = p.p.first_op_after(t4, lambda r: not r[1])
            assert stopped is not None
            time.sleep(0.8)
            after = p.p.motion_after(stopped[0] + 100_000_000, 0.5)
            print(
                f"e-stop: follow off after {(stopped[0] - t4) / 1e6:.0f} ms, "
                f"then the tip moved {after:.2f} mm"
            )
            assert after < 0.5 and not p.p.following()
            tips = p.p.tips()
            assert np.isfinite(tips[:, 1:]).all()
        finally:
            console.close()
