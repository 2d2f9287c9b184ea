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

import dataclasses
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from telesurg.services.master_capture.devices.policy import PolicyObservation
from telesurg.shared import tasks as tasks_mod
from telesurg.shared.kinematics.transforms import matrix_from_quat
from telesurg.shared.tasks import Goal, TaskSpec, Vec3

LIFT_M = 0.008  # m: a target is approached from this high above it


def min_jerk(s: float) -> float:
    """Minimum-jerk position profile, 0 → 1 over normalised time ``s`` in [0, 1]."""
    s = min(max(s, 0.0), 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s)


def via_points(task: TaskSpec, step_m: float, press_m: float = 0.0, detour_m: float = 0.0) -> list[Goal]:
    """The goals the operator aims at in turn: each target between points ``LIFT_M`` above it (it
    lifts the tip off the tissue before it moves on), or the wire every ``step_m``.

    ``press_m``: it aims each touch this far below the target (into the tissue: a press too
    hard); ``detour_m``: it aims the wire's middle via point this far to the side (out of the
    tube). Both are errors on purpose, for the tests that provoke them."""
    if task.kind == "transfer":  # (its hands plan their own: TransferHand)
        return list(task.goals)
    if task.kind == "targets":
        out = []
        for g in task.goals:
            x, y, z = g.position
            above = Goal((x, y, z + LIFT_M), g.radius_m)
            out += [above, Goal((x, y, z - press_m), g.radius_m + press_m, g.dwell_s), above]
        return out[:-1]
    wire = np.array(task.path)
    seg = np.linalg.norm(np.diff(wire, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])

    def at(s: float) -> np.ndarray:  # the wire's point s m along it
        return np.array([np.interp(s, cum, wire[:, i]) for i in range(3)])

    out = []
    along = np.arange(0.0, cum[-1], step_m)[1:]
    for s in along:
        p = at(s)
        if detour_m and s == along[len(along) // 2]:
            side = np.cross(at(s + 1e-3) - p, (0.0, 0.0, 1.0))
            p = p + detour_m * side / np.linalg.norm(side)
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
        press_mm: float = 0.0,
        detour_mm: float = 0.0,
    ) -> None:
        self.task, self.scale, self.dt = task, scale, 1.0 / rate_hz
        self.rng = np.random.default_rng(seed)
        self.reaction_s, self.fa, self.fb = reaction_s, fitts_a_s, fitts_b_s
        self.noise, self.undershoot, self.tremor = endpoint_noise, undershoot, tremor_mm / 1e3
        self.settle, self.max_wait = settle_mm_s / 1e3, max_wait_s
        self.goals = via_points(task, path_step_mm / 1e3, press_mm / 1e3, detour_mm / 1e3)
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


def _vec(p: np.ndarray) -> Vec3:
    return (float(p[0]), float(p[1]), float(p[2]))


@dataclass(frozen=True)
class Step:
    """One step of a hand's program (:class:`TransferHand`).

    ``move``: bring the jaws' centre to ``to(hand, obs)`` (within ``radius_m``, held ``dwell_s``);
    ``grip``: set the master's grip to ``value`` and wait until ``until(hand, obs)`` (at most
    ``timeout_s``, then on to step ``retry``); ``wait``: wait until ``until``.
    """

    kind: str
    to: Callable[[TransferHand, PolicyObservation], np.ndarray] | None = None
    radius_m: float = 0.003
    dwell_s: float = 0.0
    value: float = 0.0
    until: Callable[[TransferHand, PolicyObservation], bool] | None = None
    timeout_s: float = math.inf
    retry: int = -1  # step to go to on a timeout (-1: the next)
    live: bool = False  # move: its goal follows the object (re-aimed at each sub-movement)
    min_s: float = 0.0  # grip / wait: at least this long (and its lag) before it goes on


class TransferHand(Operator):
    """One hand of the synthetic operator in a transfer task (a peg transfer: ``task.arms[role]``).

    It plans with the :class:`Operator`'s human-like sub-movements, but aims the jaws' centre (the
    controlled point plus ``task.grasp_offset`` turned by the tip's orientation, as a surgeon aims
    the jaws they see), squeezes and opens the master's grip, and waits on what it sees in the
    scene — the object's position and which jaws hold it:

    * the first hand (``role`` 0): above the object, down onto it, close; once it sees the object
      held, lift and carry it to the hand-over; wait until the other jaws hold it, open, withdraw;
      an object it sees lying free (a drop) is picked up again;
    * the other hand (``role`` 1): wait until it sees the object held at the hand-over, come to it
      along its instrument, close; once the first hand let go, carry it to above the target, lower,
      open wide, back out along its instrument.

    Knobs: ``approach_mm`` (how far back along its instrument it comes in from a grasp, and how far
    above the target it carries), ``lift_mm`` (the first hand's lift), ``release_mm`` (the
    object's clearance above the target when it opens), ``drop_after_lift`` (the first hand opens
    once it has lifted the object: a drop, for the tests that provoke one).
    """

    def __init__(
        self,
        task: TaskSpec,
        scale: float,
        rate_hz: float,
        seed: int = 0,
        role: int = 0,
        approach_mm: float = 12.0,
        lift_mm: float = 15.0,
        release_mm: float = 2.0,
        drop_after_lift: bool = False,
        **knobs: float,
    ) -> None:
        super().__init__(task, scale, rate_hz, seed, **knobs)
        self.role, self.arm = role, task.arms[role]
        self.giver = task.arms[0]
        self.offset = np.array(task.grasp_offset, dtype=float)
        self.approach, self.lift, self.release = approach_mm / 1e3, lift_mm / 1e3, release_mm / 1e3
        self.grip = 0.0
        self.k = 0
        self.step_t0: float | None = None
        self.mark = np.zeros(3)  # the jaws where the step began
        self.free_since: float | None = None  # the object seen lying free since (a drop)
        self.off_since: float | None = None  # the other jaws seen off the object since
        self.steps = self._giver(drop_after_lift) if role == 0 else self._taker()

    # -- what it sees -----------------------------------------------------------------------------
    def jaws(self, obs: PolicyObservation) -> np.ndarray:
        """Where it sees the jaws' centre."""
        out: np.ndarray = np.asarray(obs.tip, dtype=float) + matrix_from_quat(obs.tip_quat) @ self.offset
        return out

    def obj(self, obs: PolicyObservation) -> np.ndarray | None:
        p = obs.objects.get(self.task.obj)
        return None if p is None else np.array(p, dtype=float)

    def holds(self, obs: PolicyObservation, arm: str) -> bool:
        return arm in obs.held_by.get(self.task.obj, ())

    def let_go(self, obs: PolicyObservation, arm: str, seconds: float) -> bool:
        """It has seen ``arm``'s jaws off the object for ``seconds``."""
        if self.holds(obs, arm):
            self.off_since = None
            return False
        self.off_since = obs.t if self.off_since is None else self.off_since
        return obs.t - self.off_since >= seconds

    def tool(self, obs: PolicyObservation) -> np.ndarray:
        """The way its instrument points now (unit, base frame)."""
        out: np.ndarray = matrix_from_quat(obs.tip_quat) @ np.array(self.task.tool_axis, dtype=float)
        return out

    def at_obj(self, back: float = 0.0) -> Callable[[TransferHand, PolicyObservation], np.ndarray]:
        """Its grasp point on the object (``task.obj_grasps``), ``back`` m behind it along its
        instrument (the way it comes in)."""
        grasp = np.array(self.task.obj_grasps[self.role] if self.task.obj_grasps else (0.0, 0.0, 0.0))

        def to(h: TransferHand, obs: PolicyObservation) -> np.ndarray:
            o = h.obj(obs)
            base = o + grasp if o is not None else h.jaws(obs)
            out: np.ndarray = base - back * h.tool(obs)
            return out

        return to

    def from_mark(self, up: float) -> Callable[[TransferHand, PolicyObservation], np.ndarray]:
        """``up`` m above where the jaws were when the step began."""
        return lambda h, obs: h.mark + np.array([0.0, 0.0, up])

    def back_from_mark(self, back: float) -> Callable[[TransferHand, PolicyObservation], np.ndarray]:
        """``back`` m behind where the jaws were when the step began, along its instrument."""
        return lambda h, obs: h.mark - back * h.tool(obs)

    @staticmethod
    def fixed(p: Vec3, up: float = 0.0) -> Callable[[TransferHand, PolicyObservation], np.ndarray]:
        """``up`` m above the point ``p``."""
        return lambda h, obs: np.array(p, dtype=float) + np.array([0.0, 0.0, up])

    # -- the programs ---------------------------------------------------------------------------
    def _giver(self, drop_after_lift: bool) -> list[Step]:
        me, other = self.arm, self.task.arms[-1]
        grasp = self.task.obj_grasps[0] if self.task.obj_grasps else (0.0, 0.0, 0.0)
        over = _vec(np.add(self.task.goals[1].position, grasp))
        steps = [
            Step("move", self.at_obj(self.approach), 0.003, live=True),
            Step("move", self.at_obj(0.0), 0.0015, 0.2, live=True),
            Step("grip", value=1.0, until=lambda h, o: h.holds(o, me), timeout_s=2.0, retry=0),
            Step("move", self.from_mark(self.lift), 0.004),
        ]
        if drop_after_lift:
            steps.append(Step("grip", value=0.0, until=lambda h, o: not h.holds(o, me), timeout_s=1.0))
        steps += [
            Step("move", self.fixed(over), 0.003, 0.2),
            # (it lets go once it has seen the other jaws hold a moment: a firm grasp)
            Step("wait", until=lambda h, o: h.holds(o, other), timeout_s=30.0, min_s=0.3),
            # (it lets the jaws open wide before it draws them back along its instrument: jaws
            # still half closed drag the peg out of the other's grasp, or knock it over)
            Step("grip", value=0.0, until=lambda h, o: not h.holds(o, me), timeout_s=2.0, min_s=0.4),
            Step("move", self.back_from_mark(self.approach), 0.005),  # (back out along its instrument)
        ]
        return steps

    def _taker(self) -> list[Step]:
        me, giver = self.arm, self.giver
        over = np.array(self.task.goals[1].position)
        grasp = self.task.obj_grasps[1] if self.task.obj_grasps else (0.0, 0.0, 0.0)
        place = _vec(np.add(self.task.goals[2].position, grasp))

        def offered(h: TransferHand, o: PolicyObservation) -> bool:
            p = h.obj(o)
            return p is not None and h.holds(o, giver) and float(np.linalg.norm(p - over)) < 0.008

        return [
            Step("wait", until=offered),
            Step("move", self.at_obj(self.approach), 0.003, live=True),
            Step("move", self.at_obj(0.0), 0.0015, 0.2, live=True),
            Step("grip", value=1.0, until=lambda h, o: h.holds(o, me), timeout_s=2.0, retry=1),
            # (it waits to see the first hand's jaws open and draw back before it carries)
            Step("wait", until=lambda h, o: h.let_go(o, giver, 1.0), timeout_s=30.0),
            # (straight on to above the target: down and away from the first hand's jaws)
            Step("move", self.fixed(place, self.approach), 0.003),
            Step("move", self.fixed(place, self.release), 0.002, 0.2),
            # (as the first hand: jaws open wide before they draw back off the peg)
            Step("grip", value=0.0, until=lambda h, o: not h.holds(o, me), timeout_s=2.0, min_s=0.4),
            Step("move", self.back_from_mark(self.approach), 0.005),
        ]

    # -- the policy -----------------------------------------------------------------------------
    def _begin(self, k: int, t: float, obs: PolicyObservation) -> None:
        self.k, self.step_t0 = k, t
        self.mark = self.jaws(obs)
        self.i = 0
        if k < len(self.steps) and self.steps[k].kind == "move":
            st = self.steps[k]
            assert st.to is not None
            self.goals = [Goal(_vec(st.to(self, obs)), st.radius_m, st.dwell_s)]
            self.phase, self.until = "react", t + self.reaction_s * self.rng.uniform(0.6, 1.0)
        else:  # (still: a hold's new press re-aims it here)
            self.goals, self.phase = [Goal(_vec(self.mark), 0.003)], "done"

    def _dropped(self, t: float, obs: PolicyObservation) -> bool:
        """It sees the object lying free (no jaws on it) for a while, after its grasp: a drop."""
        if self.role != 0 or self.k < 3 or self.grip > 0.5:
            self.free_since = None
            return False
        if obs.held_by.get(self.task.obj):
            self.free_since = None
            return False
        self.free_since = t if self.free_since is None else self.free_since
        return t - self.free_since > 0.5 + self.lag

    def __call__(self, obs: PolicyObservation) -> np.ndarray | None:
        t = obs.t
        if self.step_t0 is None:
            self._begin(0, t, obs)
        seen = dataclasses.replace(obs, tip=self.jaws(obs))
        if self.k >= len(self.steps):  # done: hands still (the pose held, the pedal pressed)
            out = super().__call__(seen)
            return None if out is None else np.append(np.zeros(3), self.grip)
        if obs.following and self._dropped(t, obs) and self.obj(obs) is not None:
            self.steps = self._giver(False)  # (a provoked drop happens once)
            self._begin(0, t, obs)  # pick it up again where it lies
        st = self.steps[self.k]
        if st.kind == "move":
            if st.live and st.to is not None and self.phase == "react":
                self.goals = [Goal(_vec(st.to(self, obs)), st.radius_m, st.dwell_s)]
            out = super().__call__(seen)
            if out is None:
                return None
            if self.phase == "done":
                self._begin(self.k + 1, t, obs)
            return np.append(out, self.grip)
        # grip / wait: the hand still (its tremor), the grip set, watching
        out = super().__call__(seen)
        if out is None:
            return None
        if st.kind == "grip":
            self.grip = st.value
        assert self.step_t0 is not None
        waited = t - self.step_t0
        done = st.until is not None and st.until(self, obs)
        if obs.following and done and waited >= max(self.lag, st.min_s):
            self._begin(self.k + 1, t, obs)
        elif waited > st.timeout_s + self.lag:
            if st.kind == "grip" and st.value > 0.5:
                self.grip = 0.0  # a grasp that did not take: open, and try again
            self._begin(st.retry if st.retry >= 0 else self.k + 1, t, obs)
        return np.append(out, self.grip)


def make(
    task: str, scale: float = 0.5, rate_hz: float = 50.0, seed: int = 0, **knobs: float
) -> Callable[[PolicyObservation], np.ndarray | None]:
    """The operator performing the registered task ``task`` at motion scale ``scale`` (the
    mapping's: slave / master), asked at ``rate_hz`` (the policy device's); ``knobs``: the
    :class:`Operator`'s human-like parameters (a transfer: :class:`TransferHand`'s, its ``role``)."""
    spec = tasks_mod.get(task)
    if spec.kind == "transfer":
        return TransferHand(spec, scale, rate_hz, seed, **knobs)  # type: ignore[arg-type]
    return Operator(spec, scale, rate_hz, seed, **knobs)
