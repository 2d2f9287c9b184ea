"""The console's terminal UI (textual) over a :class:`~telesurg.services.console.ConsoleModel`.

Layout: a status line (site, live services), one panel per arm (slave, clutch, the mapping's
teleop state, safety, jog, last reply, events), the log (events, command replies,
refusals), the command line and the key footer. The panels redraw from a model snapshot at
10 Hz; nothing here touches zenoh directly.

Keys (``?`` lists them in the app):

=========  ==========================================================================
``c``      console clutch of the selected arm's master: press / release (toggle)
``g``      engage: a fresh clutch press (release + press if it was pressed)
``d``      disengage: release the console clutch
``e``      E-STOP every arm (``*``); ``E`` the selected arm only; ``F1`` e-stops every
           arm from anywhere, even while typing a command
``r``      reset the e-stop of every arm (asks ``y``/``n``); ``R`` the selected arm
``t``      teach_trocar      ``p`` begin_posture_adjust method=ptp
``f``      finish_posture_adjust      ``i`` insert      ``o`` remove (out)
``s``      stop      ``a`` abort      ``m`` set_motion_mode mode=master_slave
``x y z``  jog axis      ``v`` next jog frame      ``j`` jog +      ``J`` jog −
``k``      teach_point program=<program>      ``l`` play program=<program>
``+ -``    scale_up / scale_down (sent to the mapping)
``1``–``9``  select the arm
``:``      command line: ``[@ARM] [mapping] NAME [key=value …]``, or ``estop [ARM|*]``,
           ``reset [ARM|*]``, ``clutch on|off``, ``engage``, ``disengage``; Esc leaves it
``ctrl+q`` quit (the console clutch is released first)
=========  ==========================================================================
"""

from __future__ import annotations

import time
from typing import ClassVar

from rich.text import Text
from telesurg.services.console.model import (
    JOG_AXES,
    JOG_FRAMES,
    ArmState,
    ConsoleConfig,
    ConsoleModel,
    Notice,
)
from textual import on
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.notifications import SeverityLevel
from textual.screen import ModalScreen
from textual.widgets import Button, Footer, Input, Label, RichLog, Static

SAFETY_STYLE = {
    "OK": "bold green",
    "DEGRADED": "bold yellow",
    "HOLD": "bold yellow",
    "ESTOP": "bold white on red",
}
TELEOP_STYLE = {
    "ENABLED": "bold green",
    "ENGAGING": "cyan",
    "IDLE": "",
    "HOLDING": "yellow",
    "DISABLED": "dim",
}
OP_STYLE = {"ENABLED": "bold green", "PAUSED": "yellow", "DISABLED": "dim", "FAULT": "bold white on red"}
SEVERITY: dict[str, SeverityLevel] = {"info": "information", "warning": "warning", "error": "error"}
LOG_STYLE = {"info": "", "warning": "yellow", "error": "bold red"}
CARTESIAN_AXES = ("x", "y", "z", "rx", "ry", "rz")


def _clock(stamp: float) -> str:
    return time.strftime("%H:%M:%S", time.localtime(stamp))


def arm_text(a: ArmState, console_clutch: bool, cfg: ConsoleConfig, now: float) -> Text:
    """What one arm's panel shows (``now``: monotonic s)."""
    t = Text()

    def row(label: str) -> None:
        t.append(f"\n{label:<8} " if t.plain else f"{label:<8} ", style="bold")

    row("slave")
    op = a.op
    if op is None:
        t.append("no operating state yet", style="dim")
    else:
        age = now - a.op_rx
        t.append(op.state, style=OP_STYLE.get(op.state, ""))
        t.append(f" · mode {op.control_mode} · ")
        if op.follow:
            t.append("FOLLOWING", style="bold green")
        else:
            t.append("holding" + (f": {op.reason}" if op.reason else ""), style="yellow")
        t.append(" · ")
        t.append("lease ok" if op.lease_ok else "no lease", style="green" if op.lease_ok else "red")
        t.append(f" · holds {op.holds}")
        if op.control_mode in ("transitional", "trocar"):  # meaningful once through the trocar
            t.append(f" · rcm error {op.rcm_error_mm:.2f} mm")
        if age > cfg.stale_s:
            t.append(f" · STALE {age:.1f} s", style="bold red")
    row("clutch")
    if a.pedal is None or now - a.pedal_rx > cfg.stale_s:
        t.append(f"pedal {a.master}: no data", style="dim")
    else:
        t.append(f"pedal {a.master} " + ("pressed" if a.pedal.clutch else "released"))
        if not a.pedal.operator_present:
            t.append(" (operator absent)", style="yellow")
    t.append(" · console clutch ")
    t.append("PRESSED" if console_clutch else "released", style="bold cyan" if console_clutch else "")
    t.append(" · mapping ")
    tp = a.teleop
    if tp is not None and now - a.teleop_rx > cfg.stale_s:
        t.append("unknown (teleop state stale)", style="bold red")
    else:
        t.append("engaged" if a.engaged else "disengaged", style="green" if a.engaged else "")
    row("teleop")
    if tp is None:
        t.append("no teleop state from the mapping yet", style="dim")
    else:
        t.append(tp.state, style=TELEOP_STYLE.get(tp.state, ""))
        since = tp.since_ns / 1e9
        t.append(f" since {_clock(since)} ({max(time.time() - since, 0.0):.1f} s)")
        if tp.previous != tp.state:
            t.append(f" · was {tp.previous}", style="dim")
        t.append(f" · scale {tp.scale:.2f} × safety {tp.safety_scale:.2f} · {tp.mode}")
        if tp.reason:
            t.append(f"\n         {tp.reason}", style=TELEOP_STYLE.get(tp.state, ""))
        if now - a.teleop_rx > cfg.stale_s:
            t.append(f" · STALE {now - a.teleop_rx:.1f} s", style="bold red")
    row("safety")
    s = a.safety
    if s is None:
        t.append("no watchdog state yet", style="dim")
    else:
        t.append(s.state, style=SAFETY_STYLE.get(s.state, ""))
        t.append(f" · scale ×{s.scale:.2f} · latency ")
        if s.latency_samples:
            t.append(f"p50 {s.latency_p50_ms:.1f} ms  p99 {s.latency_p99_ms:.1f} ms")
            t.append(f" ({s.latency_samples} samples)", style="dim")
            t.append(f" · master clock {s.clock_offset_ms:+.1f} ms", style="dim")
        else:
            t.append("unknown", style="dim")
        if now - a.safety_rx > cfg.stale_s:
            t.append(f" · STALE {now - a.safety_rx:.1f} s", style="bold red")
        if s.causes:
            row("causes")
            t.append("; ".join(s.causes), style=SAFETY_STYLE.get(s.state, ""))
    row("jog")
    t.append(f"{a.jog_frame} {a.jog_axis}", style="bold")
    t.append("  (x/y/z axis · v frame · j + · J − · s stop)", style="dim")
    if a.last_reply:
        row("reply")
        t.append(a.last_reply, style="red" if "REFUSED" in a.last_reply else "")
    row("events")
    shown = list(a.events)[-cfg.events_per_arm :]
    if not shown:
        t.append("none yet", style="dim")
    for stamp, source, kind, text in shown:
        t.append(f"\n  {_clock(stamp)} {source} {kind}: {text}")
    return t


class ArmPanel(Static):
    """One arm's panel."""

    DEFAULT_CSS = """
    ArmPanel { border: round $secondary; padding: 0 1; height: auto; }
    ArmPanel.selected { border: double $accent; }
    """


class ConfirmScreen(ModalScreen[bool]):
    """A yes/no question; ``y`` / ``n`` / Esc."""

    DEFAULT_CSS = """
    ConfirmScreen { align: center middle; }
    ConfirmScreen > Vertical { width: 64; height: auto; border: thick $warning; padding: 1 2;
                               background: $surface; }
    ConfirmScreen Horizontal { height: auto; margin-top: 1; }
    ConfirmScreen Button { margin-right: 2; }
    """
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("y", "answer(True)", "yes"),
        Binding("n,escape", "answer(False)", "no"),
    ]

    def __init__(self, question: str) -> None:
        super().__init__()
        self.question = question

    def compose(self) -> ComposeResult:
        with Vertical():
            yield Label(self.question, id="question")
            with Horizontal():
                yield Button("Yes (y)", id="yes", variant="warning")
                yield Button("No (n)", id="no")

    def action_answer(self, yes: bool) -> None:
        self.dismiss(yes)

    @on(Button.Pressed)
    def _pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "yes")


class ConsoleApp(App[None]):
    """``telesurg console``."""

    TITLE = "telesurg console"
    ENABLE_COMMAND_PALETTE = False
    CSS = """
    #status { height: 1; background: $panel; padding: 0 1; }
    #arms { height: auto; max-height: 70%; }
    #log { height: 1fr; min-height: 5; border: round $secondary; }
    #command { dock: bottom; margin-bottom: 1; }
    """
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("f1", "estop('*')", "E-STOP all", priority=True),
        Binding("e", "estop('*')", "E-STOP all"),
        Binding("E", "estop('')", "e-stop arm", show=False),
        Binding("r", "reset('*')", "reset"),
        Binding("R", "reset('')", "reset arm", show=False),
        Binding("c", "clutch", "clutch"),
        Binding("g", "engage", "engage"),
        Binding("d", "disengage", "disengage"),
        Binding("t", "send('teach_trocar')", "teach trocar", show=False),
        Binding("p", "send('begin_posture_adjust', 'method=ptp')", "posture (ptp)", show=False),
        Binding("f", "send('finish_posture_adjust')", "finish posture", show=False),
        Binding("i", "send('insert')", "insert", show=False),
        Binding("o", "send('remove')", "remove", show=False),
        Binding("s", "send('stop')", "stop", show=False),
        Binding("a", "send('abort')", "abort", show=False),
        Binding("m", "send('set_motion_mode', 'mode=master_slave')", "master-slave", show=False),
        Binding("k", "program('teach_point')", "teach point", show=False),
        Binding("l", "program('play')", "play", show=False),
        Binding("x", "axis('x')", "jog x", show=False),
        Binding("y", "axis('y')", "jog y", show=False),
        Binding("z", "axis('z')", "jog z", show=False),
        Binding("v", "frame", "jog frame", show=False),
        Binding("j", "jog(1)", "jog +", show=False),
        Binding("J", "jog(-1)", "jog −", show=False),
        Binding("plus", "scale('scale_up')", "scale +", show=False),
        Binding("minus", "scale('scale_down')", "scale −", show=False),
        *(Binding(str(n), f"select({n - 1})", f"arm {n}", show=False) for n in range(1, 10)),
        Binding("colon,slash", "command_line", "command"),
        Binding("escape", "leave_command_line", "leave command line", show=False),
        Binding("question_mark", "help", "keys"),
    ]

    def __init__(self, model: ConsoleModel) -> None:
        super().__init__()
        self.model = model
        self.cfg = model.cfg
        self.arm_ids = list(model.arms)
        self.selected = 0
        self._asking = False  # a confirmation question is on screen
        # the widgets redrawn at 10 Hz, kept here (a query could miss them while the app closes)
        self.panels = {arm: ArmPanel(id=f"arm-{arm}") for arm in self.arm_ids}
        self.status = Static(id="status")
        self.log_view = RichLog(id="log", wrap=True, markup=False, max_lines=2000)

    # -- layout ----------------------------------------------------------------------------------
    def compose(self) -> ComposeResult:
        yield self.status
        with VerticalScroll(id="arms"):
            for i, (arm, panel) in enumerate(self.panels.items()):
                panel.set_class(i == self.selected, "selected")
                panel.border_title = f"{arm} ← {self.model.arms[arm].master}"
                yield panel
        yield self.log_view
        hint = ": command — e.g. jog frame=base axis=y direction=1 (Esc leaves)"
        yield Input(placeholder=hint, id="command")
        yield Footer()

    def on_mount(self) -> None:
        self.log_view.border_title = "log"
        self.refresh_view()
        self.set_interval(0.1, self.refresh_view)

    @property
    def arm(self) -> str:
        """The selected arm."""
        return self.arm_ids[self.selected]

    def refresh_view(self) -> None:
        """Redraw from a model snapshot; move new notices to the log (and toasts); ask the
        operator to confirm a motion-starting command the server asked about."""
        pending = self.model.pending_confirm
        if pending is not None and not self._asking:
            self._asking = True

            def answered(yes: bool | None) -> None:
                self._asking = False
                self.model.confirm(bool(yes))

            self.push_screen(ConfirmScreen(f"[{pending.arm}] {pending.question}"), answered)
        arms, clutch, alive = self.model.snapshot()
        now = time.monotonic()
        for a in arms:
            self.panels[a.arm].update(arm_text(a, clutch[a.master], self.cfg, now))
        status = Text.assemble(
            ("telesurg console", "bold"),
            f" · site {self.cfg.site} · as {self.cfg.service} · arm {self.arm} · alive: ",
            (", ".join(sorted(alive)) or "nothing (no connection to the site?)", "" if alive else "bold red"),
        )
        self.status.update(status)
        self.show_notices(self.model.drain())

    def show_notices(self, notices: list[Notice]) -> None:
        for n in notices:
            line = Text.assemble((_clock(n.stamp) + " ", "dim"), (n.text, LOG_STYLE.get(n.severity, "")))
            self.log_view.write(line, expand=True)  # wrap at the panel's width
            if n.toast:
                self.notify(n.text, severity=SEVERITY.get(n.severity, "information"), timeout=6)

    # -- actions ---------------------------------------------------------------------------------
    def action_estop(self, arm: str) -> None:
        self.model.estop(arm or self.arm, "estop")

    def action_reset(self, arm: str) -> None:
        self._confirm_reset(arm or self.arm)

    def _confirm_reset(self, target: str) -> None:
        def answered(yes: bool | None) -> None:
            if yes:
                self.model.estop(target, "reset", "operator")
            else:
                self.model.note("info", f"reset of {target} cancelled")

        what = "every arm" if target == "*" else f"arm {target}"
        self.push_screen(
            ConfirmScreen(f"Reset the e-stop of {what}?\nThe arm stays still until a new engage."), answered
        )

    def action_clutch(self) -> None:
        m = self.model.arms[self.arm].master
        self.model.set_clutch(m, not self.model.clutch(m))

    def action_engage(self) -> None:
        self.model.engage(self.model.arms[self.arm].master)

    def action_disengage(self) -> None:
        self.model.set_clutch(self.model.arms[self.arm].master, False)

    def action_send(self, name: str, *args: str) -> None:
        self.model.command(self.arm, name, args)

    def action_program(self, name: str) -> None:
        self.model.command(self.arm, name, (f"program={self.cfg.program}",))

    def action_scale(self, name: str) -> None:
        self.model.command(self.arm, name, target="mapping")

    def action_axis(self, axis: str) -> None:
        frame = self.model.arms[self.arm].jog_frame
        if frame == "joint":  # x / y / z pick j1..j3 in the joint frame
            axis = JOG_AXES["joint"][CARTESIAN_AXES.index(axis)]
        self.model.set_jog(self.arm, axis=axis)

    def action_frame(self) -> None:
        frame = self.model.arms[self.arm].jog_frame
        self.model.set_jog(self.arm, frame=JOG_FRAMES[(JOG_FRAMES.index(frame) + 1) % len(JOG_FRAMES)])

    def action_jog(self, direction: int) -> None:
        self.model.jog(self.arm, direction)

    def action_select(self, index: int) -> None:
        if index >= len(self.arm_ids):
            return
        self.panels[self.arm].remove_class("selected")
        self.selected = index
        self.panels[self.arm].add_class("selected")
        self.panels[self.arm].scroll_visible()

    def action_command_line(self) -> None:
        self.query_one("#command", Input).focus()

    def action_leave_command_line(self) -> None:
        self.set_focus(None)

    def action_help(self) -> None:
        if self.screen.query("HelpPanel"):
            self.action_hide_help_panel()
        else:
            self.action_show_help_panel()

    # -- command line ----------------------------------------------------------------------------
    @on(Input.Submitted, "#command")
    def _submitted(self, event: Input.Submitted) -> None:
        event.input.clear()
        self.set_focus(None)
        line = event.value.strip()
        if line:
            self.run_line(line)

    def run_line(self, line: str) -> None:
        """Carry out one command-line entry (see the module docstring)."""
        words = line.split()
        arm = self.arm
        if words[0].startswith("@"):
            arm = words.pop(0)[1:]
            if arm not in self.model.arms:
                self.model.note("error", f"no arm {arm!r} here; valid: {', '.join(self.arm_ids)}", toast=True)
                return
            if not words:
                self.action_select(self.arm_ids.index(arm))
                return
        name, args = words[0], words[1:]
        master = self.model.arms[arm].master
        if name in ("estop", "reset"):
            target = args[0] if args else ("*" if name == "estop" else arm)
            if target != "*" and target not in self.model.arms:
                self.model.note("error", f"{name}: no arm {target!r}; valid: *, {', '.join(self.arm_ids)}")
            elif name == "estop":
                self.model.estop(target, "estop")
            else:
                self._confirm_reset(target)
        elif name == "clutch" and args in (["on"], ["off"]):
            self.model.set_clutch(master, args == ["on"])
        elif name == "engage" and not args:
            self.model.engage(master)
        elif name == "disengage" and not args:
            self.model.set_clutch(master, False)
        elif name == "mapping" and args:
            self.model.command(arm, args[0], args[1:], target="mapping")
        else:
            self.model.command(arm, name, args)


def run_app(model: ConsoleModel) -> None:
    """Run the UI in this terminal until the operator quits."""
    ConsoleApp(model).run()
