"""The mapping's teleop state as the operator sees it, against a running local pipeline (router,
watchdog, slave_control with MuJoCo, mapping, a scripted master whose pedal is pressed 0.5–3.5 s
of every 4 s).

Issue #16, acceptance 6: a console started after an engage shows the mapping engaged within
0.5 s of its session opening. Then the state follows a watchdog hold (an e-stop: HOLDING), the
reset and the pedal's release (IDLE) and the re-press (ENABLED), in the console's panel, and a
stalled master (HOLDING until a release and a new press).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from telesurg.services.console import ArmState, ConsoleConfig, ConsoleModel
from telesurg.services.console.app import arm_text
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import TeleopState
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process

#: s to wait for an engage: the scripted pedal presses every 4 s, but on a loaded machine the
#: watchdog may hold (stale streams) or degrade (latency) the arm through a press or two.
ENGAGE_S = 30.0
#: s for the bus to show the effect of an e-stop (loopback zenoh, watchdog confirmation).
SHOWN_S = 5.0
#: The acceptance figure: s from the console's session opening to showing the truth.
LATE_JOIN_S = 0.5


class Truth:
    """Every teleop state the mapping publishes for arm1, in order (the test's own session)."""

    def __init__(self, node: Node) -> None:
        self.lock = threading.Lock()
        self.states: list[tuple[float, TeleopState]] = []  # (monotonic s, message)
        node.subscribe(node.keys.mapping("arm1", "teleop_state"), TeleopState, self._on, sources=["mapping"])

    def _on(self, m: TeleopState, key: str) -> None:
        with self.lock:
            self.states.append((time.monotonic(), m))

    def last(self) -> TeleopState | None:
        with self.lock:
            return self.states[-1][1] if self.states else None

    def changes_since(self, t: float) -> list[str]:
        """The states published after ``t``, repeats dropped."""
        with self.lock:
            seq = [m.state for ts, m in self.states if ts >= t]
        return [s for i, s in enumerate(seq) if i == 0 or s != seq[i - 1]]

    def left_enabled_between(self, t0: float, t1: float) -> bool:
        with self.lock:
            return any(m.state != "ENABLED" for ts, m in self.states if t0 <= ts <= t1)


def wait(pred: Callable[[], bool], timeout: float, step: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return pred()


def shown(model: ConsoleModel) -> tuple[ArmState, str]:
    """arm1's state in the console and its panel text, as the TUI draws it."""
    arms, clutch, _ = model.snapshot()
    a = next(x for x in arms if x.arm == "arm1")
    return a, arm_text(a, clutch[a.master], model.cfg, time.monotonic()).plain


def test_a_console_started_after_the_engage_shows_it_and_follows_holds(tmp_path: Path) -> None:
    with Pipeline(tmp_path / "logs", mirror=False, impair=False, probe=False) as pipe:
        truth = Truth(pipe.node)
        cfg = ConsoleConfig(site=pipe.spec.site, bus=BusConfig(connect=[pipe.spec.endpoint]))
        late_ms: list[float] = []
        for _attempt in range(5):
            # an engage that began just now: the pedal stays down for ~3 s more
            assert wait(
                lambda: (
                    (m := truth.last()) is not None
                    and m.state == "ENABLED"
                    and time.time() - m.since_ns / 1e9 < 0.5
                ),
                ENGAGE_S,
            ), truth.last()
            t_open = time.monotonic()
            node = Node(cfg.bus, cfg.site, cfg.service)
            t_session = time.monotonic()
            model = ConsoleModel(cfg, node)
            engaged = wait(lambda m=model: shown(m)[0].engaged, LATE_JOIN_S - (time.monotonic() - t_session))
            t_shown = time.monotonic()
            if engaged or not truth.left_enabled_between(t_open, t_shown):
                break
            # the truth changed within the window (a hold on this busy host): not a late-join
            # failure; try again on the next engage with a fresh console
            model.close()
            node.close()
        try:
            a, text = shown(model)
            assert engaged, f"not shown engaged within {LATE_JOIN_S} s of the session: {text}"
            late_ms.append((t_shown - t_session) * 1e3)
            assert "mapping engaged" in text and "teleop   ENABLED" in text, text
            assert a.teleop is not None and a.teleop.master == "m1" and a.teleop.scale == 0.5
            print(f"late-joining console showed ENABLED {late_ms[0]:.0f} ms after its session opened")

            # A watchdog hold (the operator's e-stop) → HOLDING with the slave's reason.
            t_stop = time.monotonic()
            assert model.estop("*").result(timeout=SHOWN_S + 5), "e-stop not confirmed"
            assert wait(lambda: "teleop   HOLDING" in shown(model)[1], SHOWN_S), shown(model)[1]
            a, text = shown(model)
            assert not a.engaged and "mapping disengaged" in text, text
            assert a.teleop is not None and a.teleop.reason.startswith("slave holding"), a.teleop
            assert "HOLDING" in truth.changes_since(t_stop), truth.changes_since(t_stop)
            # still holding while latched, through a whole pedal cycle (release and press)
            time.sleep(4.5)
            seen = truth.changes_since(t_stop)  # (from the hold on: states published before the
            assert "ENABLED" not in seen[seen.index("HOLDING") :], seen  # e-stop may arrive after t_stop)
            assert not shown(model)[0].engaged

            # Reset: the pedal's release (IDLE, or DISABLED while the slave may not move yet) and
            # the next press (ENGAGING → ENABLED) engage again; the console shows it.
            t_reset = time.monotonic()
            assert model.estop("*", "reset").result(timeout=SHOWN_S + 5), "reset not confirmed"
            assert wait(lambda: shown(model)[0].engaged, ENGAGE_S), shown(model)[1]
            # (the test's own subscriber may get the mapping's state a little after the console's)
            assert wait(lambda: "ENABLED" in truth.changes_since(t_reset), SHOWN_S), truth.changes_since(
                t_reset
            )
            seen = truth.changes_since(t_reset)
            before = seen[: seen.index("ENABLED")]
            assert "ENGAGING" in before and ("IDLE" in before or "DISABLED" in before), seen
            # and the operator's release, at the end of the pedal's press, is IDLE "clutch released"
            t_on = time.monotonic()
            assert wait(lambda: "teleop   IDLE" in shown(model)[1], ENGAGE_S), shown(model)[1]
            a, text = shown(model)
            assert a.teleop is not None and a.teleop.previous == "ENABLED", a.teleop
            assert a.teleop.reason == "clutch released" and "mapping disengaged" in text, text
            assert truth.changes_since(t_on)[:2] == ["ENABLED", "IDLE"], truth.changes_since(t_on)

            # A stall of the master (SIGSTOP 0.4 s) while engaged: the watchdog holds the slave
            # (stale master) or the mapping sees its input stale first; either way HOLDING, and
            # only a release and a new press engage again.
            # (engaged as the mapping says now, not only as the console last showed it: a hold on
            # this busy host may have begun a new pedal cycle the console has not shown yet)
            assert wait(
                lambda: shown(model)[0].engaged and (m := truth.last()) is not None and m.state == "ENABLED",
                ENGAGE_S,
            ), (shown(model)[1], truth.last())
            t_freeze = time.monotonic()
            pipe.freeze("master_capture")
            time.sleep(0.4)
            pipe.thaw("master_capture")
            assert wait(lambda: "HOLDING" in truth.changes_since(t_freeze), SHOWN_S), truth.changes_since(
                t_freeze
            )
            with truth.lock:
                held = next(m for ts, m in truth.states if ts >= t_freeze and m.state == "HOLDING")
            assert held.reason.startswith(("master stream stale", "slave holding")), held

            def engaged_again() -> bool:
                seen = truth.changes_since(t_freeze)
                return "ENABLED" in seen[seen.index("HOLDING") :]

            assert wait(engaged_again, ENGAGE_S), truth.changes_since(t_freeze)
            seen = truth.changes_since(t_freeze)
            held_at = seen.index("HOLDING")
            again = seen.index("ENABLED", held_at)
            assert {"IDLE", "DISABLED"} & set(seen[held_at:again]), seen
            assert wait(lambda: shown(model)[0].engaged, SHOWN_S), shown(model)[1]
        finally:
            model.close()
            node.close()
