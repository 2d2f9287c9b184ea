"""The operator console (``telesurg console``) headless, driven by textual's pilot against a
running local pipeline (router, watchdog, slave_control with MuJoCo, mapping, a scripted master
whose pedal is pressed 0.5–3.5 s of every 4 s).

Issue #7, acceptance 2: engage, clutch, a mode command refused with its reason, e-stop, reset.
Every assertion is on what the operator sees — the text the widgets draw — except the clutch
message on the bus and the slave's own operating state, which are what the console must cause.
"""

from __future__ import annotations

import asyncio
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from telesurg.services.console import ConsoleConfig, ConsoleModel, console_clutch_key
from telesurg.services.console.app import ArmPanel, ConsoleApp
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import MasterButtons, OperatingState
from telesurg.tools.bench.harness import Pipeline
from textual.geometry import Region
from textual.pilot import Pilot
from textual.widget import Widget

pytestmark = pytest.mark.process

#: s to wait for an engage: the scripted pedal presses every 4 s, but on a loaded machine the
#: watchdog may hold (stale streams) or degrade (latency) the arm through a press or two.
ENGAGE_S = 30.0
#: s for the UI and the bus to show the effect of a key (10 Hz redraw, loopback zenoh).
SHOWN_S = 5.0


def seen(widget: Widget) -> str:
    """The text ``widget`` draws on the terminal, border included (the lines, joined)."""
    w, h = widget.outer_size
    return "\n".join(strip.text for strip in widget.render_lines(Region(0, 0, w, h)))


def dialog_text(app: ConsoleApp) -> str:
    """The question of a pop-up dialog, as drawn ("" if none)."""
    return "\n".join(seen(w) for w in app.screen.query("#question"))


def screen_text(app: ConsoleApp) -> str:
    """Panels, log and pop-up notifications, as drawn."""
    parts = [seen(p) for p in app.query(ArmPanel)] + [seen(app.query_one("#log"))]
    return "\n".join([*parts, toasts(app)])


def toasts(app: ConsoleApp) -> str:
    """The pop-up notifications on screen, as drawn."""
    return "\n".join(seen(t) for t in app.screen.query("Toast"))


async def until(pilot: Pilot[None], pred: Callable[[], bool], timeout: float) -> bool:
    """Let the app run until ``pred()`` holds (True) or ``timeout`` s pass (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        await pilot.pause(0.1)
    return pred()


class Tap:
    """What the console causes on the bus: its clutch messages (as master_capture would receive
    them) and the slave's operating state (follow or not, at 20 Hz and on every change)."""

    def __init__(self, node: Node, master: str, arm: str) -> None:
        self.lock = threading.Lock()
        self.clutch: list[MasterButtons] = []
        self.follow: list[tuple[float, bool]] = []  # (monotonic s, follow)
        k = node.keys
        node.subscribe(console_clutch_key(k, master), MasterButtons, self._on_clutch, sources=["console"])
        node.subscribe(
            k.slave(arm, "operating_state"), OperatingState, self._on_op, sources=["slave_control"]
        )

    def _on_clutch(self, m: MasterButtons, key: str) -> None:
        with self.lock:
            self.clutch.append(m)

    def _on_op(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.follow.append((time.monotonic(), m.follow))

    def last_clutch(self) -> MasterButtons | None:
        with self.lock:
            return self.clutch[-1] if self.clutch else None

    def clutch_edges(self, since: int) -> list[bool]:
        """The clutch values after message ``since``, repeats dropped."""
        with self.lock:
            vals = [m.clutch for m in self.clutch[since:]]
        return [v for i, v in enumerate(vals) if i == 0 or v != vals[i - 1]]

    def followed_since(self, t: float) -> bool:
        with self.lock:
            return any(f for ts, f in self.follow if ts >= t)

    def last_follow(self) -> bool | None:
        with self.lock:
            return self.follow[-1][1] if self.follow else None


async def drive(app: ConsoleApp, tap: Tap) -> None:
    async with app.run_test(size=(140, 50), notifications=True) as pilot:
        panel = app.query_one("#arm-arm1", ArmPanel)

        def panel_text() -> str:
            return seen(panel)

        # Engage: the scripted pedal presses; the panel shows the lease, the slave following and
        # the mapping's teleop state.
        def engaged() -> bool:
            text = panel_text()
            want = ("ENABLED", "FOLLOWING", "lease ok", "mapping engaged", "teleop   ENABLED")
            return all(s in text for s in want)

        assert await until(pilot, engaged, ENGAGE_S + 10.0), panel_text()  # + start-up
        shown = re.compile(r"safety +(OK|DEGRADED) · scale ×[01]\.\d\d · latency p50 \d+\.\d ms  p99 ")
        assert await until(pilot, lambda: bool(shown.search(panel_text())), SHOWN_S), panel_text()

        # A motion-starting command asks the operator first (the server's confirm required,
        # shared/authority.py); "n" sends nothing, "y" sends it with the server's token.
        await pilot.press("i")
        asked = "confirm required: insert on arm1"
        assert await until(pilot, lambda: asked in dialog_text(app), SHOWN_S), screen_text(app)
        await pilot.press("n")
        assert await until(pilot, lambda: "insert: not confirmed, not sent" in screen_text(app), SHOWN_S)
        await pilot.press("i")
        assert await until(pilot, lambda: asked in dialog_text(app), SHOWN_S), screen_text(app)
        await pilot.press("y")
        # A mode command refused with its reason: insert before any posture adjustment.
        assert await until(pilot, lambda: "insert: REFUSED" in screen_text(app), SHOWN_S), screen_text(app)
        text = screen_text(app)
        assert "insert refused in non_trocar" in text, text  # the slave's reason, as sent
        assert await until(pilot, lambda: "insert: REFUSED" in toasts(app), SHOWN_S), "no pop-up"
        # the same through the command line
        await pilot.press("colon", *"remove", "enter")
        assert await until(pilot, lambda: "confirm required: remove" in dialog_text(app), SHOWN_S)
        await pilot.press("y")
        assert await until(pilot, lambda: "remove: REFUSED — remove refused" in screen_text(app), SHOWN_S)

        # E-stop latches: the panel shows ESTOP / FAULT and the slave stops following.
        assert await until(pilot, lambda: "FOLLOWING" in panel_text(), ENGAGE_S), panel_text()
        await pilot.press("e")
        assert await until(pilot, lambda: "safety   ESTOP" in panel_text(), SHOWN_S), panel_text()
        assert await until(
            pilot, lambda: "FAULT" in panel_text() and "FOLLOWING" not in panel_text(), SHOWN_S
        )
        assert await until(pilot, lambda: "estop of * confirmed" in screen_text(app), SHOWN_S)
        # the tap is another session: a state from before the e-stop may still reach it after the
        # panel showed the hold (it would count as following after the e-stop)
        assert await until(pilot, lambda: tap.last_follow() is False, SHOWN_S), "the tap saw no hold"
        t_latched = time.monotonic()
        await pilot.pause(4.5)  # a whole pedal cycle: the scripted master presses again
        assert not tap.followed_since(t_latched), "the slave followed after the e-stop"
        assert "safety   ESTOP" in panel_text() and "FOLLOWING" not in panel_text(), panel_text()

        # Reset (after a confirmation) clears it; the next pedal press engages again.
        await pilot.press("r")
        assert await until(pilot, lambda: "Reset the e-stop" in dialog_text(app), SHOWN_S)
        await pilot.press("n")  # cancelled: still latched
        await pilot.pause(0.5)
        assert "safety   ESTOP" in panel_text()
        await pilot.press("r")
        assert await until(pilot, lambda: "Reset the e-stop" in dialog_text(app), SHOWN_S)
        await pilot.press("y")
        assert await until(pilot, lambda: "safety   ESTOP" not in panel_text(), SHOWN_S), panel_text()
        assert await until(pilot, lambda: "FOLLOWING" in panel_text(), ENGAGE_S), panel_text()

        # The clutch key: the console publishes its clutch for master m1, as "console".
        assert "console clutch released" in panel_text()
        assert (m := tap.last_clutch()) is not None and not m.clutch
        await pilot.press("c")
        assert await until(pilot, lambda: "console clutch PRESSED" in panel_text(), SHOWN_S), panel_text()
        assert await until(pilot, lambda: (m := tap.last_clutch()) is not None and m.clutch, SHOWN_S)
        await pilot.press("c")
        assert await until(pilot, lambda: (m := tap.last_clutch()) is not None and not m.clutch, SHOWN_S)
        # (the panel redraws every 0.1 s; the message is published at once, so it may come first)
        assert await until(pilot, lambda: "console clutch released" in panel_text(), SHOWN_S), panel_text()
        # engage (g) is a fresh press, also when the clutch is pressed already; d releases it
        await pilot.press("g")
        assert await until(pilot, lambda: "console clutch PRESSED" in panel_text(), SHOWN_S), panel_text()
        # (the press must be on the bus before counting, else its edge would pass for the next one)
        assert await until(pilot, lambda: (m := tap.last_clutch()) is not None and m.clutch, SHOWN_S)
        n = len(tap.clutch)
        await pilot.press("g")
        assert await until(pilot, lambda: tap.clutch_edges(n)[-2:] == [False, True], SHOWN_S), (
            tap.clutch_edges(n)
        )
        await pilot.press("d")
        assert await until(pilot, lambda: "console clutch released" in panel_text(), SHOWN_S), panel_text()
        assert await until(pilot, lambda: (m := tap.last_clutch()) is not None and not m.clutch, SHOWN_S)


def test_console_against_pipeline(tmp_path: Path) -> None:
    # (no probe: pilot key presses wait for this process to go idle, and the probe's 1 kHz of
    # subscriptions would keep it busy)
    with Pipeline(tmp_path / "logs", mirror=False, impair=False, probe=False) as pipe:
        tap = Tap(pipe.node, "m1", "arm1")
        cfg = ConsoleConfig(site=pipe.spec.site, bus=BusConfig(connect=[pipe.spec.endpoint]))
        with Node(cfg.bus, cfg.site, cfg.service) as node:
            model = ConsoleModel(cfg, node)
            try:
                asyncio.run(drive(ConsoleApp(model), tap))
            finally:
                model.close()
