"""Surgical training tasks and their scores: pure functions over a trial's recorded streams.

A task (:class:`TaskSpec`) is what the operator must do with the slave's controlled point, in the
slave's base frame: reach a sequence of goals (a Fitts-style target task: each goal reached when
the tip stays within its radius for its dwell time) or follow a wire (a path task: a polyline and
the tube around it; leaving the tube is an error). A robot's folder declares its tasks
(``shared/robots/<robot>/tasks.py``, :func:`register`); :func:`get` finds one by name.

:func:`evaluate` runs the success rule over the tip samples (the study harness calls it live to
end a trial, and again on the recording); :func:`score` turns a trial's :class:`Streams` (read
from its MCAP recording) into a :class:`TrialScore`. Numpy in, numbers out: no bus, no I/O.

Example::

    task = get("mh3f-targets")
    prog = evaluate(task, tips)          # tips (n, 4): t s, x, y, z m
    s = score(task, streams)             # completion time, path length, errors by kind, …
"""

from __future__ import annotations

import importlib
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import ConfigError

KINDS = ("targets", "path", "transfer")
#: What the harness does before a trial's go (:attr:`TaskSpec.setup`).
SETUPS = ("", "trocar")
#: error kinds a trial counts (an excursion over the limit each, :func:`excursions`; a path exit;
#: ``watchdog_hold`` an entry into HOLD/ESTOP; ``drop`` an object let go anywhere but its target;
#: ``collision`` the instruments of two arms touching)
ERROR_KINDS = ("tissue_force", "path_exit", "rcm_error", "watchdog_hold", "drop", "collision")
#: s: an object free of every arm's jaws this long is let go (a drop, or placed on its target); a
#: grasp's contacts flicker for shorter
LET_GO_S = 0.3
HELD_STATES = ("HOLD", "ESTOP")

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Goal:
    """One point to reach: tip within ``radius_m`` of ``position`` (m, base frame) for ``dwell_s``."""

    position: Vec3
    radius_m: float
    dwell_s: float = 0.0


@dataclass(frozen=True)
class TaskSpec:
    """A task of one robot.

    Attributes:
        name: registered name, ``<robot>-<task>`` (``mh3f-targets``).
        robot: the robot registry name it runs on.
        kind: ``targets`` (reach ``goals`` in order), ``path`` (follow ``path`` in its tube) or
            ``transfer`` (a peg transfer: ``arms[0]`` grasps ``obj`` at ``goals[0]``, hands it over
            to ``arms[-1]`` at ``goals[1]``, which places it on ``goals[2]``).
        instructions: what the operator is told (one or two sentences).
        goals: targets: the sequence; path: the wire's end (the last goal ends the trial).
        path: path: the wire, polyline of points, m, base frame.
        tube_radius_m: path: the ring's radius; the tip farther than this from the wire is out.
        start_tip: m, base frame: where the tip is at the start (the site's home pose).
        force_limit_n: N: tissue force above this is an error (below the watchdog's own limit).
        rcm_limit_mm: mm: RCM error above this (in trocar mode) is an error.
        time_limit_s: s: a trial not done by then ends incomplete.
        scene: the robot's scene for the task, one of its ``scene_*.xml`` ("" = its own scene).
        setup: what the harness does before the go: "" nothing; "trocar" the MH3F's insert flow
            (posture adjustment by PTP, insert to trocar mode, master–slave in trocar mode).
        q_start: rad: the slave's start pose (slave_control's ``q_home``; () = the robot's home).
        arms: the slave arms the task uses (a transfer: the one that grasps first, then the one
            that places); ``start_tip`` is the first's, ``start_tips`` every one's.
        start_tips: m: each arm's controlled point at the start (() = ``start_tip`` alone).
        obj: transfer: the scene's loose object to move (``slave/<arm>/scene``).
        grasp_offset: m: the jaws' centre from the controlled point, in the tip frame (the frame of
            ``measured_cp``'s orientation).
        obj_grasps: m: where each arm grasps the object, from its centre (base frame axes).
        tool_axis: the way the instrument points, in the tip frame (its jaws come along it).
        mapping: the mapping mode the task runs with ("" = the site's; ``position`` for a
            Cartesian master on the PLAS, whose site maps an all-joints master).
        mapping_set: more of the mapping's settings (``--set`` items, e.g. the VIPs).
    """

    name: str
    robot: str
    kind: str
    instructions: str
    goals: tuple[Goal, ...]
    start_tip: Vec3
    path: tuple[Vec3, ...] = ()
    tube_radius_m: float = 0.0
    force_limit_n: float = 2.0
    rcm_limit_mm: float = 2.0
    time_limit_s: float = 90.0
    scene: str = ""
    setup: str = ""
    q_start: tuple[float, ...] = ()
    arms: tuple[str, ...] = ("arm1",)
    start_tips: tuple[Vec3, ...] = ()
    obj: str = ""
    grasp_offset: Vec3 = (0.0, 0.0, 0.0)
    obj_grasps: tuple[Vec3, ...] = ()
    tool_axis: Vec3 = (0.0, 0.0, -1.0)
    mapping: str = ""
    mapping_set: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(f"task {self.name}: kind {self.kind!r} invalid; valid: {', '.join(KINDS)}")
        if self.setup not in SETUPS:
            raise ConfigError(f"task {self.name}: setup {self.setup!r} invalid; valid: {SETUPS}")
        if not self.goals:
            raise ConfigError(f"task {self.name}: no goals")
        if self.kind == "path" and (len(self.path) < 2 or self.tube_radius_m <= 0):
            raise ConfigError(f"task {self.name}: a path task needs >= 2 points and tube_radius_m > 0")
        if self.kind == "transfer" and (len(self.goals) != 3 or len(self.arms) != 2 or not self.obj):
            raise ConfigError(
                f"task {self.name}: a transfer needs 3 goals (grasp, hand-over, place), 2 arms and an obj"
            )
        if self.start_tips and len(self.start_tips) != len(self.arms):
            raise ConfigError(
                f"task {self.name}: start_tips has {len(self.start_tips)} points for {len(self.arms)} arms"
            )

    def ideal_length_m(self) -> float:
        """The shortest tip path that does the task (m): straight lines start → each goal
        (targets); start → the wire's start, then along the wire (path)."""
        if self.kind == "targets":
            pts = np.array([self.start_tip, *(g.position for g in self.goals)])
            return path_length(pts)
        if self.kind == "transfer":  # the first arm: start → grasp → hand-over; the last: → place
            grasp, over, place = (np.array(g.position) for g in self.goals)
            first, last = self.start_tips or (self.start_tip, self.start_tip)
            return path_length(np.array([first, grasp, over])) + path_length(np.array([last, over, place]))
        wire = np.array(self.path)
        return float(np.linalg.norm(wire[0] - np.array(self.start_tip))) + path_length(wire)


_TASKS: dict[str, TaskSpec] = {}


def register(task: TaskSpec) -> None:
    """Make ``task`` known by its name (a robot folder's ``tasks.py`` calls it at import)."""
    _TASKS[task.name] = task


def _load_all() -> None:
    from telesurg.shared.robots import registry

    for robot in registry.names():
        package = f"telesurg.shared.robots.{robot}"
        try:
            importlib.import_module(f"{package}.tasks")
        except ModuleNotFoundError as e:
            # a robot without tasks, or a plugin robot whose folder is elsewhere (its own
            # tasks, if any, register when its plugin imports them)
            if e.name not in (package, f"{package}.tasks"):
                raise


def names() -> tuple[str, ...]:
    """Every registered task's name, sorted."""
    _load_all()
    return tuple(sorted(_TASKS))


def get(name: str) -> TaskSpec:
    """The task ``name``; ConfigError naming the known ones."""
    _load_all()
    if name not in _TASKS:
        raise ConfigError(f"unknown task {name!r}; known: {', '.join(sorted(_TASKS)) or 'none'}")
    return _TASKS[name]


# --------------------------------------------------------------------------- geometry


def path_length(points: npt.ArrayLike) -> float:
    """Length (m) of the polyline through ``points`` (n, 3); 0 for fewer than two."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0


def distance_to_path(points: npt.ArrayLike, path: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m) of each point to the polyline and the arc length (m) of its nearest point.

    Args:
        points: (n, 3) m.
        path: (k, 3) m, k >= 2.
    Returns:
        (n,) distances and (n,) arc lengths along the path.
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    w = np.asarray(path, dtype=float)
    a, b = w[:-1], w[1:]
    ab = b - a
    seg_len = np.linalg.norm(ab, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])[:-1]
    ap = p[:, None, :] - a[None, :, :]
    s = np.clip((ap * ab[None]).sum(-1) / np.maximum(seg_len**2, 1e-18)[None], 0.0, 1.0)
    nearest = a[None] + s[..., None] * ab[None]
    d = np.linalg.norm(p[:, None, :] - nearest, axis=2)
    j = d.argmin(axis=1)
    rows = np.arange(len(p))
    return d[rows, j], cum[j] + s[rows, j] * seg_len[j]


# --------------------------------------------------------------------------- the success rule


@dataclass
class Progress:
    """How far a trial got (times in the tips' clock, s)."""

    reached: list[float] = field(default_factory=list)  # when each goal was reached, in order
    done_t: float | None = None  # when the last goal was reached (the task done)
    entered_t: float | None = None  # path: when the tip first entered the tube at the wire's start
    exits: list[float] = field(default_factory=list)  # path: when the tip left the tube

    @property
    def done(self) -> bool:
        """The task is complete."""
        return self.done_t is not None


def evaluate(task: TaskSpec, tips: npt.ArrayLike) -> Progress:
    """Run the task's success rule over tip samples (n, 4): t s, x, y, z m (time order); a
    transfer's over its object's samples (:func:`evaluate_transfer`).

    Targets: goal i is reached once the tip has stayed within its radius for its dwell (then the
    next goal counts). Path: the trial is on the wire from the first sample within the tube at its
    start; each move out of the tube from then is an exit; done when the tip, having covered 90 %
    of the wire's length, is within the last goal's radius.
    """
    if task.kind == "transfer":
        return evaluate_transfer(task, tips)
    tips = np.asarray(tips, dtype=float).reshape(-1, 4)
    prog = Progress()
    if task.kind == "targets":
        i, since = 0, None
        for t, *p in tips:
            g = task.goals[i]
            inside = math.dist(p, g.position) <= g.radius_m
            if not inside:
                since = None
                continue
            since = t if since is None else since
            if t - since >= g.dwell_s:
                prog.reached.append(float(t))
                i, since = i + 1, None
                if i == len(task.goals):
                    prog.done_t = float(t)
                    break
        return prog
    if len(tips) == 0:
        return prog
    d, s = distance_to_path(tips[:, 1:], task.path)
    wire = np.array(task.path)
    length = path_length(wire)
    end = task.goals[-1]
    start_ok = np.linalg.norm(tips[:, 1:] - wire[0], axis=1) <= task.tube_radius_m
    if not start_ok.any():
        return prog
    k0 = int(np.argmax(start_ok))
    prog.entered_t = float(tips[k0, 0])
    inside = True
    covered = 0.0
    for k in range(k0, len(tips)):
        now_in = d[k] <= task.tube_radius_m
        if inside and not now_in:
            prog.exits.append(float(tips[k, 0]))
        inside = now_in
        if now_in:
            covered = max(covered, float(s[k]))
        if covered >= 0.9 * length and math.dist(tips[k, 1:], end.position) <= end.radius_m:
            prog.done_t = float(tips[k, 0])
            prog.reached.append(prog.done_t)
            break
    return prog


def holders(names: tuple[str, ...], arms: tuple[str, ...]) -> int:
    """The arms holding an object (``SceneState.object``) as bits: bit i set when ``arms[i]`` holds."""
    return sum(1 << i for i, a in enumerate(arms) if a in names)


def evaluate_transfer(task: TaskSpec, obj: npt.ArrayLike) -> Progress:
    """A transfer's success rule over the object's samples (n, 5): t s, x, y, z m, holders (bits,
    :func:`holders`), in time order.

    Goals reached: the grasp (the first arm holds it), the hand-over (the last arm holds it alone,
    after the first held it) and the place (after the hand-over, let go for :data:`LET_GO_S` within
    the place goal's radius, horizontally, and its height within 10 mm) — the task done. Every
    letting go for :data:`LET_GO_S` elsewhere, after a grasp, is a drop (``Progress.exits``)."""
    rows = np.asarray(obj, dtype=float).reshape(-1, 5)
    prog = Progress()
    place = task.goals[-1]
    first, last = 1, 1 << (len(task.arms) - 1)
    held_ever, stage, free_since, dropped = False, 0, None, False
    for t, x, y, z, bits in rows:
        b = int(bits)
        if b:
            free_since, dropped = None, False
            held_ever = True
            if stage == 0 and b & first:
                prog.reached.append(float(t))
                stage = 1
            if stage == 1 and b == last:
                prog.reached.append(float(t))
                stage = 2
            continue
        if not held_ever:
            continue
        free_since = t if free_since is None else free_since
        if t - free_since < LET_GO_S or dropped:
            continue
        px, py, pz = place.position
        on_target = math.hypot(x - px, y - py) <= place.radius_m and abs(z - pz) <= 0.01
        if stage == 2 and on_target:
            prog.reached.append(float(t))
            prog.done_t = float(t)
            break
        prog.exits.append(float(free_since))  # a drop: let go where it does not belong
        dropped = True
    return prog


# --------------------------------------------------------------------------- scores


@dataclass
class Streams:
    """A trial's recorded streams, each in time order on one clock (s).

    Attributes:
        tip: (n, 4) t, x, y, z (m): the slave's measured_cp.
        force: (n, 2) t, |F| (N): measured_cf.
        rcm: (n, 3) t, RCM error (mm), 1 in trocar mode else 0: operating_state.
        follow: (n, 2) t, 1 while the slave follows: operating_state.
        clutch: (n, 2) t, 1 pressed: the master's buttons.
        safety: (n, 2) t, 1 while the watchdog holds (HOLD / ESTOP): its state.
        obj: (n, 5) t, x, y, z (m), holders (bits, :func:`holders`): a transfer's object.
        collide: (n, 2) t, 1 while two arms' instruments touch: the scene.
        more_tips: the other arms' tips (as ``tip``), by arm.
        more_forces: the other arms' forces (as ``force``), by arm.
    """

    tip: np.ndarray
    force: np.ndarray
    rcm: np.ndarray
    follow: np.ndarray
    clutch: np.ndarray
    safety: np.ndarray
    obj: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    collide: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    more_tips: dict[str, np.ndarray] = field(default_factory=dict)
    more_forces: dict[str, np.ndarray] = field(default_factory=dict)

    @staticmethod
    def empty() -> Streams:
        """No samples at all."""
        tip, force, rcm, follow, clutch, safety = (np.zeros((0, c)) for c in (4, 2, 3, 2, 2, 2))
        return Streams(tip, force, rcm, follow, clutch, safety)


@dataclass
class TrialScore:
    """One trial's score (the study's JSON line; docs/study.md defines each)."""

    completed: bool
    completion_time_s: float  # go (the slave first follows) → task done; NaN if not done
    path_length_mm: float  # the tip's path over the trial
    ideal_length_mm: float  # the task's shortest path
    economy: float  # ideal / actual path length (1 = no wasted motion); NaN if not done
    errors: dict[str, int]  # kind → count (ERROR_KINDS)
    peak_force_n: float  # tissue force over the trial
    mean_force_n: float  # mean tissue force while in contact (|F| > 0.05 N); 0 without contact
    contact_time_s: float  # time in contact with the tissue
    rcm_error_max_mm: float  # NaN when the arm was never in trocar mode
    rcm_error_mean_mm: float
    clutch_count: int  # clutch presses from the trial's start
    time_held_s: float  # the watchdog held (HOLD / ESTOP) this long in the trial
    goals_reached: int
    path_exits: list[float]  # path: s after go of each exit; transfer: of each drop
    # each arm's tip path (mm) over the trial; path_length_mm is their sum
    path_lengths_mm: dict[str, float] = field(default_factory=dict)

    def row(self) -> dict[str, Any]:
        """As a JSON-ready dict (NaN → None)."""
        out = asdict(self)
        for k, v in out.items():
            if isinstance(v, float) and not math.isfinite(v):
                out[k] = None
        return out


def _window(a: np.ndarray, t0: float, t1: float) -> np.ndarray:
    return a[(a[:, 0] >= t0) & (a[:, 0] <= t1)] if len(a) else a


def excursions(series: np.ndarray, limit: float, release: float = 0.8, gap_s: float = 0.25) -> int:
    """Excursions of a series (t, value) above ``limit``: one starts when the value passes the
    limit and ends once it has stayed below ``release`` × limit for ``gap_s`` (a contact's chatter
    around the limit is one error, not one per sample)."""
    n, above, low_since = 0, False, None
    for t, v in series:
        if v > limit:
            n += 0 if above else 1
            above, low_since = True, None
        elif above and v < release * limit:
            low_since = t if low_since is None else low_since
            if t - low_since >= gap_s:
                above = False
    return n


def rising(values: np.ndarray) -> int:
    """Number of False → True transitions in a boolean series (a series starting True counts 1)."""
    v = np.asarray(values, dtype=bool)
    if v.size == 0:
        return 0
    return int(v[0]) + int(np.count_nonzero(v[1:] & ~v[:-1]))


def time_true(series: np.ndarray, t0: float, t1: float) -> float:
    """Seconds within [t0, t1] that a step series (t, 0/1) is 1 (each value holds until the next)."""
    if len(series) == 0 or t1 <= t0:
        return 0.0
    t = np.clip(np.append(series[:, 0], t1), t0, t1)
    return float((np.diff(t) * (series[:, 1] > 0.5)).sum())


def start_time(streams: Streams) -> float | None:
    """The go time: the slave's first following state (None if it never followed)."""
    f = streams.follow
    on = np.flatnonzero(f[:, 1] > 0.5) if len(f) else np.zeros(0, dtype=int)
    return float(f[on[0], 0]) if on.size else None


def score(task: TaskSpec, streams: Streams, t_end: float | None = None) -> TrialScore:
    """Score one trial from its streams (see :class:`TrialScore`).

    The trial runs from the go (:func:`start_time`) to the task's completion, else to ``t_end``
    (the harness's stop) or the last tip sample.
    """
    t0 = start_time(streams)
    tip_all = streams.tip
    if t0 is None or len(tip_all) == 0:
        nan = float("nan")
        return TrialScore(
            False, nan, 0.0, task.ideal_length_m() * 1e3, nan, dict.fromkeys(ERROR_KINDS, 0), 0.0, 0.0,
            0.0, nan, nan, 0, 0.0, 0, [],
        )  # fmt: skip
    last = float(tip_all[-1, 0]) if t_end is None else t_end
    samples = streams.obj if task.kind == "transfer" else tip_all  # (what its success rule reads)
    prog = evaluate(task, samples[samples[:, 0] >= t0])
    t1 = prog.done_t if prog.done_t is not None else last
    lengths = {
        arm: path_length(_window(tp, t0, t1)[:, 1:])
        for arm, tp in {task.arms[0]: tip_all, **streams.more_tips}.items()
    }
    length = sum(lengths.values())
    ideal = task.ideal_length_m()
    windows = (_window(fs, t0, t1) for fs in (streams.force, *streams.more_forces.values()))
    forces = [fs for fs in windows if len(fs)]  # each arm's force in the trial
    f = np.concatenate([fs[:, 1] for fs in forces]) if forces else np.zeros(0)
    contact = f > 0.05
    contact_s = sum(time_true(np.column_stack([fs[:, 0], fs[:, 1] > 0.05]), t0, t1) for fs in forces)
    rcm = _window(streams.rcm, t0, t1)
    trocar = rcm[rcm[:, 2] > 0.5] if len(rcm) else rcm
    held = _window(streams.safety, t0, t1)
    # the state at t0 holds until its first change inside the window
    before = streams.safety[streams.safety[:, 0] < t0] if len(streams.safety) else streams.safety
    if len(before):
        held = np.vstack([[t0, before[-1, 1]], held])
    clutch = streams.clutch[streams.clutch[:, 0] <= t1] if len(streams.clutch) else streams.clutch
    collide = _window(streams.collide, t0, t1)
    errors = {
        "tissue_force": sum(excursions(fs, task.force_limit_n) for fs in forces),
        "path_exit": len(prog.exits) if task.kind == "path" else 0,
        "rcm_error": excursions(trocar[:, :2], task.rcm_limit_mm) if len(trocar) else 0,
        "watchdog_hold": rising(held[:, 1] > 0.5) if len(held) else 0,
        "drop": len(prog.exits) if task.kind == "transfer" else 0,
        "collision": rising(collide[:, 1] > 0.5) if len(collide) else 0,
    }
    return TrialScore(
        completed=prog.done,
        completion_time_s=(t1 - t0) if prog.done else float("nan"),
        path_length_mm=length * 1e3,
        ideal_length_mm=ideal * 1e3,
        economy=ideal / length if length > 0 and prog.done else float("nan"),
        errors=errors,
        peak_force_n=float(f.max()) if f.size else 0.0,
        mean_force_n=float(f[contact].mean()) if contact.any() else 0.0,
        contact_time_s=contact_s,
        rcm_error_max_mm=float(trocar[:, 1].max()) if len(trocar) else float("nan"),
        rcm_error_mean_mm=float(trocar[:, 1].mean()) if len(trocar) else float("nan"),
        clutch_count=rising(clutch[:, 1] > 0.5) if len(clutch) else 0,
        time_held_s=time_true(held, t0, t1),
        goals_reached=len(prog.reached),
        path_exits=[round(t - t0, 3) for t in prog.exits],
        path_lengths_mm={arm: round(v * 1e3, 2) for arm, v in lengths.items()},
    )
