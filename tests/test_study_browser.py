"""A study trial run by a person at the web console's page (issue #44 acceptance 3).

``telesurg study --master web`` runs a blinded one-trial protocol; the test opens the printed
one-time login URL in Chromium (DevTools) and acts as the participant with the mouse master: it
holds the clutch (Space), learns how a drag and the wheel move the tip (as a person does in the
first seconds), then touches each target in turn, reading the tip from the page. What the
participant sees is checked on the page: the task and its instructions, the trial's clock running
while the slave follows, the goals counted, the result at the end — and never the condition (the
page shows only its code: the study is blinded).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import chromium, screenshot
from telesurg.shared import tasks
from test_web_console import (
    centre,
    drag,
    engage,
    js,
    needs_chromium,
    save_shot,
    space,
    teleop,
    text,
    wait_page,
)

pytestmark = pytest.mark.process

CONDITION = "delay 40 ms"
PROTOCOL = f"""\
[study]
name = "at the console"
seed = 9
tasks = ["mh3f-targets"]
repetitions = 1
blinded = true
host_margin_ms = 500

[[condition]]
name = "{CONDITION}"
delay_ms = 40
"""


def tip_mm(cdp: Any, s: str) -> np.ndarray | None:
    v = js(cdp, s, "(window.consoleState && window.consoleState.arms[0].tip_mm) || null")
    return None if v is None else np.array(v, dtype=float)


def settled(cdp: Any, s: str, quiet_mm: float = 0.1, timeout: float = 4.0) -> np.ndarray:
    """The tip the page shows once it stopped moving (0.3 s within ``quiet_mm``)."""
    deadline = time.monotonic() + timeout
    last = tip_mm(cdp, s)
    while time.monotonic() < deadline:
        time.sleep(0.3)
        now = tip_mm(cdp, s)
        if now is not None and last is not None and np.abs(now - last).max() < quiet_mm:
            return now
        last = now
    assert last is not None, "the page never showed the tip"
    return last


def wheel(cdp: Any, s: str, notches: int) -> None:
    """``notches`` wheel notches on the arm view (+: away from the screen, master +z)."""
    x, y = centre(cdp, s, "#view")
    for _ in range(abs(notches)):
        cdp.call(
            "Input.dispatchMouseEvent",
            {"type": "mouseWheel", "x": x, "y": y, "deltaX": 0, "deltaY": -100 if notches > 0 else 100},
            s,
        )
        time.sleep(0.02)


def engaged(cdp: Any, s: str) -> None:
    """Following: else (the loaded host's watchdog held the arm) lift the foot and press again."""
    if teleop(cdp, s) != "ENABLED":
        space(cdp, s, False)
        time.sleep(0.3)
        engage(cdp, s)


class Hand:
    """The participant's hand on the mouse: what a drag pixel and a wheel notch do to the tip
    (learned by trying each, there and back), then reaches aimed from what the page shows."""

    def __init__(self, cdp: Any, s: str) -> None:
        self.cdp, self.s = cdp, s
        cols = []
        tries = (
            (lambda k: drag(cdp, s, 120 * k, 0), 120),
            (lambda k: drag(cdp, s, 0, 120 * k), 120),
            (lambda k: wheel(cdp, s, 4 * k), 4),
        )
        for act, size in tries:
            for _ in range(4):  # a try the slave did not follow (a hold) is tried again
                engaged(cdp, s)
                a = settled(cdp, s)
                act(1)
                b = settled(cdp, s)
                act(-1)  # and back
                if np.linalg.norm(b - a) > 1.0 and teleop(cdp, s) == "ENABLED":
                    break
                print(
                    f"a try that did not move the tip ({np.round(b - a, 2)} mm): "
                    f"{text(cdp, s, '#arm-arm1 .v.teleop')} | {text(cdp, s, '#banner')} | "
                    f"{text(cdp, s, '#master-status')} | {text(cdp, s, '#arm-arm1 .v.slave')} | "
                    f"{text(cdp, s, '#trial')}"
                )
            cols.append((b - a) / size)
        self.m = np.column_stack(cols)  # tip mm per (x px, y px, notch)
        print(f"the hand's map, tip mm per px / notch:\n{np.round(self.m, 4)}")
        assert np.linalg.cond(self.m) < 50, "a drag or the wheel did not move the tip"

    def reach(self, goal_mm: np.ndarray, tol_mm: float, tries: int = 15) -> np.ndarray:
        """Sub-movements toward ``goal_mm`` until the tip is within ``tol_mm``; the last tip."""
        tip = settled(self.cdp, self.s)
        for _ in range(tries):
            err = goal_mm - tip
            if np.linalg.norm(err) < tol_mm:
                break
            engaged(self.cdp, self.s)
            px, py, notches = np.linalg.solve(self.m, err)
            if abs(px) + abs(py) >= 2:
                drag(self.cdp, self.s, float(np.clip(px, -350, 350)), float(np.clip(py, -180, 180)))
            wheel(self.cdp, self.s, int(np.clip(round(notches), -25, 25)))
            tip = settled(self.cdp, self.s)
        return tip


@pytest.mark.timeout(600)
def test_a_person_at_the_console_page_runs_a_blinded_trial_with_the_mouse(tmp_path: Path) -> None:
    needs_chromium()
    proto = tmp_path / "web.toml"
    proto.write_text(PROTOCOL)
    out = tmp_path / "out"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    argv = [
        sys.executable,
        "-m",
        "telesurg.services.cli",
        "study",
        str(proto),
        "--out",
        str(out),
        "--master",
        "web",
    ]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines: queue.Queue[str] = queue.Queue()
    said: list[str] = []
    assert proc.stdout is not None
    reader = threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout], daemon=True)  # type: ignore[union-attr]
    reader.start()
    task = tasks.get("mh3f-targets")
    try:
        url = ""
        deadline = time.monotonic() + 120
        while not url and time.monotonic() < deadline:
            try:
                line = lines.get(timeout=1.0)
            except queue.Empty:
                assert proc.poll() is None, "".join(said)
                continue
            said.append(line)
            if "one-time login" in line:
                url = line.split(": ", 1)[1].strip()
        assert url, f"no console URL printed: {''.join(said)}"
        with chromium(url, tmp_path, nice=0) as (cdp, s):
            # the trial panel: the task, its instructions, the code of the condition, never the condition
            wait_page(cdp, s, "#trial-title", lambda t: "mh3f-targets" in t, 60.0)
            assert text(cdp, s, "#trial-instructions") == task.instructions
            code = text(cdp, s, "#trial-condition")
            assert code.startswith("condition "), code
            wait_page(cdp, s, "#trial-phase", lambda t: "press the clutch" in t, 120.0)
            assert "40 ms" not in text(cdp, s, "body") and "delay" not in text(cdp, s, "#trial")
            wait_page(cdp, s, "#arm-arm1 .v.safety .state", lambda t: t in ("OK", "DEGRADED"), 30.0)
            # the participant: holds the clutch, gets a feel for the mouse, touches each target
            engage(cdp, s)
            clock = [float(text(cdp, s, "#trial-clock").split()[0])]
            hand = Hand(cdp, s)
            for i, goal in enumerate(task.goals):
                g = np.array(goal.position) * 1e3
                goals = f"goals {i + 1}/{len(task.goals)}"
                for _ in range(4):  # held still inside; a hold of the loaded host: reach again
                    hand.reach(g, 0.5 * goal.radius_m * 1e3)
                    with contextlib.suppress(AssertionError):
                        wait_page(cdp, s, "#trial-goals", lambda t, goals=goals: t == goals, 3.0)
                        break
                assert text(cdp, s, "#trial-goals") == goals, text(cdp, s, "#trial")
                if i == 2:  # (docs/study.md's picture: the trial running, the next goal filled)
                    save_shot(screenshot(cdp, s), "study-console.png", tmp_path)
                clock.append(float(text(cdp, s, "#trial-clock").split()[0]))
            result = wait_page(cdp, s, "#trial-result", lambda t: t.startswith("done in"), 10.0)
            space(cdp, s, False)
            print(f"the page: {text(cdp, s, '#trial')}\nclock at each goal: {clock}")
            assert all(b > a for a, b in itertools.pairwise(clock)), clock  # the clock ran
            assert "40 ms" not in text(cdp, s, "body")
        assert proc.wait(timeout=120) == 0, "".join(said)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        reader.join(timeout=5.0)
        proc.stdout.close()
        while not lines.empty():
            said.append(lines.get())
        print("telesurg study said:\n" + "".join(said))
    rows = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["completed"] and rows[0]["goals_reached"] == 4, rows
    r = rows[0]
    print(
        f"scored: done in {r['completion_time_s']:.1f} s, path {r['path_length_mm']:.0f} mm; page: {result}"
    )
    assert rows[0]["condition"] == CONDITION  # (the results know it; the page never showed it)
