"""The synthetic operator: a human-like planner that performs a task as the ``policy`` master.

It sees what a surgeon sees — the slave's tip, as the bus brings it (so late by the link's delay)
— and moves the master hand (``services/master_capture/devices/policy.py``):

* a **reaction time** (``reaction_s`` ± 20 %) before each new movement;
* **minimum-jerk sub-movements** (Flash & Hogan 1985) toward the next goal, their duration from
  Fitts' law (``fitts_a_s + fitts_b_s · log2(D / W + 1)``), aimed with signal-dependent endpoint
  noise (``endpoint_noise`` · distance, Harris & Wolpert 1998) and a slight undershoot;
* **move and wait** (Ferrell 1965): after a sub-movement it waits until it sees the tip stop —
  at least its own estimate of the lag (learned from when its moves begin to show) — then
  corrects from what it sees; so a longer delay makes it slower, as it does a person;
* a small hand **tremor** (``tremor_mm``, per step);
* a **dwell** at targets: it holds still while it sees the tip inside;
* a **new press** when it sees the slave stop following (the watchdog held it), or not start
  (pressed before the arm was set up): it lifts its foot off the pedal (the policy pauses one
  step: the device releases it) and presses again.

For a path task it plans the same way along via points every ``path_step_mm`` of the wire (each
sub-movement aimed from where it sees the tip, so back toward the wire), going on to the next as
soon as it sees the tip near the one it aimed at.

Loaded by name through master_capture's config (the study harness sets it)::

    device = "policy"
    device_options.policy = "telesurg.tools.study.operator:make"
    device_options.options = {task = "mh3f-targets", scale = 0.5, seed = 3}
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import numpy as np
from telesurg.services.master_capture.devices.policy import PolicyObservation
from telesurg.shared import tasks as tasks_mod
from telesurg.shared.tasks import Goal, TaskSpec

LIFT_M = 0.008  # m: a target is approached from this high above it


def min_jerk(s: float) -> float:
    """Minimum-jerk position profile, 0 → 1 over normalised time ``s`` in [0, 1]."""
    s = min(max(s, 0.0), 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s)


def via_points(task: TaskSpec, step_m: float) -> list[Goal]:
    """The goals the operator aims at in turn: each target between points ``LIFT_M`` above it (it
    lifts the tip off the tissue before it moves on), or the wire every ``step_m``."""
    if task.kind == "targets":
        out = []
        for g in task.goals:
            x, y, z = g.position
            above = Goal((x, y, z + LIFT_M), g.radius_m)
            out += [above, g, above]
        return out[:-1]
    wire = np.array(task.path)
    seg = np.linalg.norm(np.diff(wire, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    out = []
    for s in np.arange(0.0, cum[-1], step_m)[1:]:
        p = np.array([np.interp(s, cum, wire[:, i]) for i in range(3)])
        out.append(Goal((float(p[0]), float(p[1]), float(p[2])), task.tube_radius_m * 0.5))
    w0 = (float(wire[0, 0]), float(wire[0, 1]), float(wire[0, 2]))
    out.insert(0, Goal(w0, task.tube_radius_m * 0.4))
    out.append(Goal(task.goals[-1].position, task.goals[-1].radius_m * 0.5, 0.0))
    return out


class Operator:
    """The planner (see the module doc); ``__call__`` is the policy."""

    def __init__(
        self,
        task: TaskSpec,
        scale: float,
        rate_hz: float,
        seed: int = 0,
        reaction_s: float = 0.25,
        fitts_a_s: float = 0.25,
        fitts_b_s: float = 0.15,
        endpoint_noise: float = 0.06,
        undershoot: float = 0.95,
        tremor_mm: float = 0.03,
        path_step_mm: float = 12.0,
        settle_mm_s: float = 8.0,
        max_wait_s: float = 3.0,
        repress_s: float = 3.0,
    ) -> None:
        self.task, self.scale, self.dt = task, scale, 1.0 / rate_hz
        self.rng = np.random.default_rng(seed)
        self.reaction_s, self.fa, self.fb = reaction_s, fitts_a_s, fitts_b_s
        self.noise, self.undershoot, self.tremor = endpoint_noise, undershoot, tremor_mm / 1e3
        self.settle, self.max_wait = settle_mm_s / 1e3, max_wait_s
        self.goals = via_points(task, path_step_mm / 1e3)
        self.i = 0  # the goal aimed at
        self.phase = "wait"  # wait (engage) · react · move · settle · dwell · done
        self.until = 0.0  # react: when it may move
        self.move: tuple[float, float, np.ndarray, np.ndarray] | None = None  # t0, T, start, delta (slave m)
        self.sent = 0.0  # the fraction of the move already output
        self.seen = deque[tuple[float, np.ndarray]](maxlen=64)  # (t, observed tip)
        self.lag = 0.0  # s: its estimate of the time from a command to seeing it
        self.move_shown = False
        self.dwell_since: float | None = None
        # s: not following this long (since it last followed, or since it started) → a new press
        self.repress_s = repress_s
        self.followed_until: float | None = None  # when it last saw the slave follow (or started)

    # -- what it sees ---------------------------------------------------------------------------
    def _speed(self, now: float, window: float = 0.15) -> float:
        pts = [(t, p) for t, p in self.seen if t >= now - window]
        if len(pts) < 2 or pts[-1][0] - pts[0][0] < window * 0.6:
            return math.inf
        return float(np.linalg.norm(pts[-1][1] - pts[0][1]) / (pts[-1][0] - pts[0][0]))

    def _plan(self, t: float, tip: np.ndarray) -> None:
        goal = self.goals[self.i]
        d = np.asarray(goal.position) - tip
        dist = float(np.linalg.norm(d))
        width = 2.0 * goal.radius_m
        duration = self.fa + self.fb * math.log2(dist / width + 1.0)
        aim = d * self.undershoot + self.rng.normal(0.0, self.noise * dist / math.sqrt(3), 3)
        self.move = (t, duration, tip.copy(), aim)
        self.sent = 0.0
        self.move_shown = False
        self.phase = "move"

    @staticmethod
    def _shows(tip: np.ndarray, start: np.ndarray, delta: np.ndarray) -> bool:
        """The tip seen moving along a sub-movement (its first 30 %, or 1 mm of it)."""
        n = float(np.linalg.norm(delta))
        if n < 2e-3:
            return False
        return float(np.dot(tip - start, delta / n)) >= min(1e-3, 0.3 * n)

    def _inside(self, tip: np.ndarray, goal: Goal, margin: float = 1.0) -> bool:
        return float(np.linalg.norm(np.asarray(goal.position) - tip)) <= goal.radius_m * margin

    def _next_goal(self, t: float) -> None:
        self.i += 1
        self.dwell_since = None
        if self.i >= len(self.goals):
            self.phase = "done"
            return
        if self.goals[self.i - 1].dwell_s == 0.0:  # from a via point: one intent, no new reaction
            self.phase, self.until = "react", t
        else:
            self.phase, self.until = "react", t + self.reaction_s * self.rng.uniform(0.8, 1.2)

    # -- the policy -----------------------------------------------------------------------------
    def _see_move(self, t: float, tip: np.ndarray) -> None:
        """Note when its current sub-movement first shows: the lag it lives with (a running mean)."""
        if self.move is None or self.move_shown:
            return
        t0, T, start, delta = self.move
        if self._shows(tip, start, delta):
            self.move_shown = True
            seen = max(0.0, t - t0 - 0.15 * T)  # (the min-jerk start is slow: 1 mm shows late)
            self.lag = 0.7 * self.lag + 0.3 * seen if self.lag else seen

    def __call__(self, obs: PolicyObservation) -> np.ndarray | None:
        t, tip = obs.t, np.asarray(obs.tip, dtype=float)
        self.seen.append((t, tip))
        out = np.zeros(3)
        if self.followed_until is None:
            self.followed_until = t
        if not obs.following:  # not engaged (yet, or the watchdog held): hands still, start over
            if self.phase not in ("wait", "done"):
                self.phase = "wait"
            # (a press before the arm was ready — a trocar task's set-up — is answered by none:
            # the slave waits for a new press, as after a hold)
            if t - self.followed_until >= self.repress_s + 2 * self.lag:
                # held and not following again: lift the foot off the pedal (the device releases it
                # while the policy does not act) and press anew (``repress_s`` of the device later)
                self.followed_until = t
                return None
            return out
        self.followed_until = t
        self._see_move(t, tip)
        if self.phase == "wait":
            self.phase, self.until = "react", t + self.reaction_s * self.rng.uniform(0.8, 1.2)
        if self.phase == "react" and t >= self.until:
            if self._inside(tip, self.goals[self.i], 0.6) and self.goals[self.i].dwell_s > 0:
                self.phase, self.dwell_since = "dwell", t
            else:
                self._plan(t, tip)
        if self.phase == "move":
            assert self.move is not None
            t0, T, _start, delta = self.move
            s = min_jerk((t - t0 + self.dt) / T)
            out = (s - self.sent) * delta / self.scale
            self.sent = s
            if s >= 1.0:
                self.phase, self.until = "settle", t0 + T
        elif self.phase == "settle":
            self._settle(t, tip)
        elif self.phase == "dwell":
            goal = self.goals[self.i]
            if not self._inside(tip, goal, 0.9):
                self.phase, self.until = "react", t + self.reaction_s
            elif self.dwell_since is not None and t - self.dwell_since >= goal.dwell_s + 0.1 + self.lag:
                self._next_goal(t)
        if self.phase != "done":
            out = out + self.rng.normal(0.0, self.tremor / self.scale, 3) * math.sqrt(self.dt * 50)
        return out

    def _settle(self, t: float, tip: np.ndarray) -> None:
        """After a sub-movement: on along the wire, or wait to see the tip stop, then judge."""
        waited, goal = t - self.until, self.goals[self.i]
        flowing = goal.dwell_s == 0.0 and self.i < len(self.goals) - 1  # a via point, passed through
        if flowing and self.move_shown and self._inside(tip, goal, 1.5) and waited >= 0.5 * self.lag:
            self._next_goal(t)  # along the wire: on to the next via point once it sees the tip near
            return
        # it waits to see its move (a tiny one may never show: then its lag) and the tip stop
        seen = self.move_shown or waited >= self.lag
        stopped = self._speed(t) < self.settle and waited >= self.lag
        if not (seen and stopped) and waited <= self.max_wait:
            return
        if self._inside(tip, goal, 0.6 if goal.dwell_s > 0 else 1.0):
            if goal.dwell_s > 0:
                self.phase, self.dwell_since = "dwell", t
            else:
                self._next_goal(t)
        else:  # a corrective sub-movement after a reaction
            self.phase, self.until = "react", t + self.reaction_s * self.rng.uniform(0.6, 1.0)


def make(
    task: str, scale: float = 0.5, rate_hz: float = 50.0, seed: int = 0, **knobs: float
) -> Callable[[PolicyObservation], np.ndarray | None]:
    """The operator performing the registered task ``task`` at motion scale ``scale`` (the
    mapping's: slave / master), asked at ``rate_hz`` (the policy device's); ``knobs``: the
    :class:`Operator`'s human-like parameters."""
    return Operator(tasks_mod.get(task), scale, rate_hz, seed, **knobs)
