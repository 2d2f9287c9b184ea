"""The study harness without a site: protocol files and their errors (with the line), the seeded
and blinded schedule, resume after an interruption, the tasks' success rules and scores, and the
synthetic operator closing the loop through a delayed plant (docs/study.md)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from telesurg.services.master_capture.devices.policy import PolicyObservation
from telesurg.shared import tasks
from telesurg.shared.errors import ConfigError
from telesurg.shared.tasks import Goal, Streams, TaskSpec
from telesurg.tools import study
from telesurg.tools.study import report, runner
from telesurg.tools.study.operator import make, min_jerk, via_points
from telesurg.tools.study.protocol import ProtocolError, codes, parse, schedule

GOOD = """\
[study]
name = "delay"
seed = 7
tasks = ["mh3f-targets", "mh3f-wire"]
repetitions = 2
practice = 1

[[condition]]
name = "0 ms"
delay_ms = 0

[[condition]]
name = "150 ms"
delay_ms = 150
jitter_ms = 10
scale = 0.4
"""


def error(text: str) -> str:
    with pytest.raises(ProtocolError) as e:
        parse(text, "p.toml")
    return str(e.value)


# ----------------------------------------------------------------------------- protocol


def test_a_good_protocol_parses_with_defaults() -> None:
    p = parse(GOOD)
    assert p.tasks == ("mh3f-targets", "mh3f-wire") and p.repetitions == 2 and p.blinded
    assert [c.name for c in p.conditions] == ["0 ms", "150 ms"]
    assert p.conditions[1].delay_ms == 150 and p.conditions[1].jitter_ms == 10
    assert p.conditions[0].scale == 0.5 and p.conditions[1].scale == 0.4


@pytest.mark.parametrize(
    ("edit", "line", "words"),
    [
        (("mh3f-wire", "mh3f-peg"), 4, "unknown task 'mh3f-peg'; known: mh3f-targets, mh3f-trocar-targets"),
        (("delay_ms = 150", "delay_ms = -5"), 14, "delay_ms=-5 outside [0, 10000]"),
        (('name = "0 ms"\ndelay_ms = 0\n', 'name = "0 ms"\n'), 8, "#1 missing field 'delay_ms'"),
        (("seed = 7\n", ""), 1, "missing field 'seed'"),
        (("scale = 0.4", "scale = 0"), 16, "scale=0 outside (0, 2]"),
        (("jitter_ms = 10", "jiter_ms = 10"), 15, "unknown key 'jiter_ms'"),
        (("jitter_ms = 10", "loss = 0.02"), 15, "cannot lose packets"),
        (("repetitions = 2", "repetitions = 0"), 5, "repetitions must be an integer in [1, 1000]"),
        (("delay_ms = 150", "delay_ms = 5"), 15, "jitter_ms=10 > delay_ms=5"),
        (('[[condition]]\nname = "150 ms"', '[[condition]]\nname = "150 ms"\n= 3'), 14, "not valid TOML"),
    ],
)
def test_a_bad_protocol_is_refused_naming_its_line(edit: tuple[str, str], line: int, words: str) -> None:
    text = GOOD.replace(*edit, 1)
    assert text != GOOD
    msg = error(text)
    assert msg.startswith(f"p.toml:{line}:"), msg
    assert words in msg


def test_a_missing_file_or_table_is_refused() -> None:
    assert "missing the [study] table" in error('[[condition]]\nname = "a"\ndelay_ms = 0\n')
    assert "no [[condition]]" in error(GOOD.split("[[condition]]")[0])
    with pytest.raises(ProtocolError, match="cannot read"):
        study.load(Path("/nonexistent/p.toml"))  # type: ignore[attr-defined]


def test_the_cli_refuses_a_bad_protocol_and_writes_nothing(tmp_path: Path, capsys: Any) -> None:
    bad = tmp_path / "p.toml"
    bad.write_text(GOOD.replace("delay_ms = 150", "delay_ms = -1"))
    assert study.main([str(bad), "--out", str(tmp_path / "out")]) == 2
    assert "p.toml:14:" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- schedule


def test_the_schedule_is_complete_seeded_per_participant_and_practice_first() -> None:
    p = parse(GOOD)
    a, again, b = schedule(p, "p01"), schedule(p, "p01"), schedule(p, "p02")
    assert a == again  # the seed decides it
    assert [(t.task, t.condition.name) for t in a] != [(t.task, t.condition.name) for t in b]
    practice, main = a[:2], a[2:]
    assert all(t.practice and t.condition.delay_ms == 0 and t.code == "practice" for t in practice)
    assert sorted((t.task, t.condition.name, t.repetition) for t in main) == sorted(
        (task, c.name, r) for task in p.tasks for c in p.conditions for r in (1, 2)
    )
    assert [t.index for t in a] == list(range(len(a)))
    assert len({t.seed for t in a}) == len(a)  # each trial's operator has its own seed


def test_blinded_codes_hide_the_condition() -> None:
    p = parse(GOOD)
    for who in ("p01", "p02", "p03"):
        c = codes(p, who)
        assert sorted(c.values()) == ["A", "B"]
        for t in schedule(p, who)[2:]:
            assert t.condition.name not in t.code and str(int(t.condition.delay_ms)) not in t.code
    assert len({tuple(codes(p, f"p{i}").items()) for i in range(8)}) == 2  # shuffled per participant


# ----------------------------------------------------------------------------- resume


def fake_row(trial: Any) -> dict[str, Any]:
    """A finished trial's row as run_trial makes it (no site)."""
    delay = trial.condition.delay_ms
    s = tasks.TrialScore(
        True, 5.0 + delay / 50, 200.0, 180.0, 0.9, dict.fromkeys(tasks.ERROR_KINDS, 0),
        0.5, 0.3, 1.0, math.nan, math.nan, 1, 0.0, 4, [],
    )  # fmt: skip
    return {
        "trial": trial.index, "task": trial.task, "condition": trial.condition.name, "code": trial.code,
        "repetition": trial.repetition, "practice": trial.practice, **s.row(),
    }  # fmt: skip


def test_an_interrupted_study_keeps_its_trials_and_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: Any
) -> None:
    proto = tmp_path / "p.toml"
    proto.write_text(GOOD)
    out = tmp_path / "out"
    ran: list[int] = []

    def interrupted(trial: Any, where: Any, margin: float, **how: Any) -> dict[str, Any]:
        if trial.index == 3:
            raise KeyboardInterrupt
        ran.append(trial.index)
        return fake_row(trial)

    monkeypatch.setattr(study, "run_trial", interrupted)
    assert study.main([str(proto), "--out", str(out)]) == 130
    assert ran == [0, 1, 2]
    err = capsys.readouterr().err
    assert "3 of 10 trials kept" in err and "run the same command again to resume" in err
    lines = (out / "results.jsonl").read_text().splitlines()
    assert [json.loads(x)["trial"] for x in lines] == [0, 1, 2]
    # a crash mid-write tears the last line: that trial runs again
    with (out / "results.jsonl").open("a") as f:
        f.write('{"trial": 3, "task": "mh3f-')

    def failing(trial: Any, where: Any, margin: float, **how: Any) -> dict[str, Any]:
        if trial.index == 5:
            raise runner.TrialFailed("trial 5: services exited: {'slave_control': -9}")
        ran.append(trial.index)
        return fake_row(trial)

    monkeypatch.setattr(study, "run_trial", failing)
    assert study.main([str(proto), "--out", str(out)]) == 1
    assert ran == [0, 1, 2, 3, 4]  # trial 5 tried twice (a retry), then the study stops
    assert "slave_control" in capsys.readouterr().err

    monkeypatch.setattr(study, "run_trial", lambda t, w, m, **how: (ran.append(t.index), fake_row(t))[1])
    assert study.main([str(proto), "--out", str(out)]) == 0
    assert ran == list(range(10))  # every trial exactly once
    assert "resuming: 5 of 10 trials done, 5 to go" in capsys.readouterr().out
    rows = runner.finished(out / "results.jsonl")
    assert sorted(rows) == list(range(10))
    assert (out / "report.png").stat().st_size > 1000
    report = (out / "report.md").read_text()
    assert "| mh3f-targets | 150 ms | 2 | 2 |" in report

    # another protocol in the same directory is refused, not mixed in
    proto.write_text(GOOD.replace("seed = 7", "seed = 8"))
    assert study.main([str(proto), "--out", str(out)]) == 2
    assert "--restart" in capsys.readouterr().err


def test_a_blinded_study_never_prints_the_condition(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: Any
) -> None:
    proto = tmp_path / "p.toml"
    proto.write_text(GOOD.replace("practice = 1", "practice = 0"))
    panel: list[str] = []  # what the console's trial panel is given to show

    def run(t: Any, w: Any, m: float, **how: Any) -> dict[str, Any]:
        panel.append(how["shown"])
        assert how["total"] == 8 and how["master"] == "operator"
        return fake_row(t)

    monkeypatch.setattr(study, "run_trial", run)
    monkeypatch.setattr(report, "write", lambda *a: [])  # (the report: the resume test's)
    assert study.main([str(proto), "--out", str(tmp_path / "b")]) == 0
    shown = [line for line in capsys.readouterr().out.splitlines() if line.startswith("trial")]
    assert len(shown) == 8 and all("ms" not in line and "condition " in line for line in shown)
    assert len(panel) == 8 and all(p.startswith("condition ") and "ms" not in p for p in panel), panel
    panel.clear()
    proto.write_text(GOOD.replace("practice = 1", "practice = 0\nblinded = false"))
    assert study.main([str(proto), "--out", str(tmp_path / "u")]) == 0
    assert any("150 ms" in line for line in capsys.readouterr().out.splitlines() if line.startswith("trial"))
    assert "150 ms" in panel  # (not blinded: the condition itself)


# ----------------------------------------------------------------------------- tasks and scores


def test_tasks_are_registered_by_the_robot_folder() -> None:
    assert {"mh3f-targets", "mh3f-wire"} <= set(tasks.names())
    with pytest.raises(ConfigError, match="unknown task 'nope'; known: mh3f-targets"):
        tasks.get("nope")
    t = tasks.get("mh3f-targets")
    for g in t.goals:  # every target is on the tissue's surface (within the touch depth)
        assert abs(g.position[2] - 0.2575) < 0.002
    wire = tasks.get("mh3f-wire")
    assert math.isclose(wire.tube_radius_m, 0.005) and len(wire.path) > 10


def test_the_trocar_task_s_targets_are_on_its_organ_and_reachable_through_the_trocar() -> None:
    import mujoco
    from telesurg.shared import robots
    from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, within_limits
    from telesurg.shared.robots.mh3f.trocar import posture_adjust, rcm_error, trocar_ik

    t = tasks.get("mh3f-trocar-targets")
    assert (t.setup, t.scene) == ("trocar", "scene_trocar_task.xml")
    m = mujoco.MjModel.from_xml_path(str(robots.get("mh3f").scene_file(t.scene)))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    marks = [d.geom(n).xpos for n in ("organ_target_a", "organ_target_b")]
    organ = d.geom("organ")
    semi = m.geom_size[organ.id]
    for g, mark in zip(t.goals, [*marks, *marks], strict=True):
        assert np.linalg.norm(np.array(g.position[:2]) - mark[:2]) < 1e-6  # under the scene's mark
        rel = (np.array(g.position) - organ.xpos) / semi
        assert abs(np.linalg.norm(rel) - 1.0) < 0.05  # on the organ's surface (touch depth 0.5 mm)
    # from the start pose: the insert flow's alignment, the tip 50 mm in, then every target by
    # the trocar IK within the joint limits and on the trocar
    trocar = np.array([0.5, 0.0, 0.2])
    q = posture_adjust(np.array(t.q_start), trocar)
    q = trocar_ik(trocar + 0.05 * fk(q)[:3, 0], trocar, q)
    assert np.linalg.norm(fk(q)[:3, 3] - np.array(t.start_tip)) < 1e-3
    for g in t.goals:
        q = trocar_ik(np.array(g.position), trocar, q)
        assert within_limits(q, MH3F) and rcm_error(q, trocar) < 1e-6


def test_a_scene_that_the_robot_does_not_ship_is_refused_naming_the_valid_ones() -> None:
    from telesurg.shared import robots

    with pytest.raises(ConfigError, match=r"no scene 'scene_x\.xml'; valid: scene_trocar_task\.xml"):
        robots.get("mh3f").scene_file("scene_x.xml")
    with pytest.raises(ConfigError, match=r"valid: scene_pegs\.xml"):
        robots.get("vip").scene_file("scene_trocar_task.xml")
    assert robots.get("vip").scene_file("scene_pegs.xml").name == "scene_pegs.xml"


LINE = TaskSpec(
    "t-line",
    "mh3f",
    "targets",
    "",
    (Goal((0.01, 0, 0), 0.002, 0.2), Goal((0.02, 0, 0), 0.002, 0.2)),
    (0, 0, 0),
)
WIRE = TaskSpec(
    "t-wire", "mh3f", "path", "", (Goal((0.1, 0, 0), 0.003),), (0, 0, 0),
    path=((0.0, 0, 0), (0.1, 0, 0)), tube_radius_m=0.002,
)  # fmt: skip


def tips_through(points: list[tuple[float, float, float]], dt: float = 0.01) -> np.ndarray:
    return np.array([(i * dt, *p) for i, p in enumerate(points)])


def test_a_target_needs_its_dwell_inside_its_radius() -> None:
    brief = [(0, 0, 0)] * 5 + [(0.01, 0, 0)] * 10 + [(0.05, 0, 0)] * 5 + [(0.01, 0, 0)] * 25
    prog = tasks.evaluate(LINE, tips_through(brief))
    assert prog.reached == [pytest.approx(0.4)] and not prog.done  # 0.1 s was not enough; 0.2 s is
    full = brief + [(0.0205, 0.001, 0)] * 21
    prog = tasks.evaluate(LINE, tips_through(full))
    assert prog.done and prog.done_t == pytest.approx(0.65)


def test_a_path_counts_each_exit_from_its_tube() -> None:
    pts = [(x / 1000, 0.0, 0.0) for x in range(0, 101)]
    pts[30] = pts[31] = (0.03, 0.003, 0.0)  # out once (3 mm off a 2 mm tube)
    pts[60] = (0.06, 0.0, 0.0025)  # and again
    prog = tasks.evaluate(WIRE, tips_through(pts))
    assert prog.done and len(prog.exits) == 2
    assert prog.exits == [pytest.approx(0.30), pytest.approx(0.60)]
    d, s = tasks.distance_to_path([(0.05, 0.003, 0.004)], WIRE.path)
    assert d[0] == pytest.approx(0.005) and s[0] == pytest.approx(0.05)


def test_the_score_of_a_trial() -> None:
    pts = [(0.0, 0, 0)] * 50 + [(0.01 * i / 10, 0, 0) for i in range(11)] + [(0.01, 0, 0)] * 30
    pts += [(0.01 + 0.01 * i / 10, 0, 0) for i in range(11)] + [(0.02, 0, 0)] * 30
    tip = tips_through(pts)  # t 0 .. 1.31 s
    t = tip[:, 0]
    force = np.column_stack([t, np.where((t > 0.7) & (t < 0.8), 2.5, 0.0) + np.where(t > 1.0, 0.5, 0.0)])
    streams = Streams(
        tip=tip,
        force=force,
        rcm=np.column_stack([t, np.full_like(t, 1.0), np.zeros_like(t)]),
        follow=np.array([[0.2, 0.0], [0.3, 1.0]]),
        clutch=np.array([[0.1, 1.0], [0.9, 0.0], [0.95, 1.0]]),
        safety=np.array([[0.0, 0.0], [0.85, 1.0], [0.95, 0.0]]),
    )
    s = tasks.score(LINE, streams)
    assert s.completed and s.goals_reached == 2
    assert s.completion_time_s == pytest.approx(1.21 - 0.3, abs=0.011)
    assert s.path_length_mm == pytest.approx(20.0) and s.ideal_length_mm == pytest.approx(20.0)
    assert s.economy == pytest.approx(1.0)
    assert s.errors == {
        "tissue_force": 1,
        "path_exit": 0,
        "rcm_error": 0,
        "watchdog_hold": 1,
        "drop": 0,
        "collision": 0,
    }
    assert s.peak_force_n == pytest.approx(2.5) and s.time_held_s == pytest.approx(0.10, abs=1e-9)
    assert s.clutch_count == 2
    assert math.isnan(s.rcm_error_max_mm)  # never in trocar mode
    row = s.row()
    assert row["rcm_error_max_mm"] is None and json.dumps(row)
    nothing = tasks.score(LINE, Streams.empty())
    assert not nothing.completed and math.isnan(nothing.completion_time_s)


def test_an_excursion_over_a_limit_is_one_error_however_it_chatters() -> None:
    t = np.arange(0, 2, 0.01)
    v = np.where((t > 0.2) & (t < 0.5), 2.5 + 0.6 * np.sin(t * 200), 0.0)  # chatter about 2 N
    v = v + np.where((t > 1.0) & (t < 1.1), 3.0, 0.0)  # and a second press after a clear gap
    assert tasks.excursions(np.column_stack([t, v]), 2.0) == 2
    assert tasks.excursions(np.zeros((0, 2)), 2.0) == 0


def test_rcm_errors_count_in_trocar_mode_only() -> None:
    tip = tips_through([(0.0, 0, 0)] * 10)
    t = tip[:, 0]
    # (samples 0.01 s apart: the gap between the two excursions is 0.02 s, under excursions' 0.25 s)
    rcm = np.column_stack([t, [0.5, 3, 3, 0.5, 0.5, 3, 0.5, 5, 5, 5], [1, 1, 1, 1, 1, 1, 1, 0, 0, 0]])
    st = Streams(tip, np.zeros((0, 2)), rcm, np.array([[0.0, 1.0]]), np.zeros((0, 2)), np.zeros((0, 2)))
    s = tasks.score(LINE, st)
    assert s.errors["rcm_error"] == 1 and s.rcm_error_max_mm == 3.0


# ----------------------------------------------------------------------------- the operator


def min_jerk_is_smooth() -> None:
    assert min_jerk(0) == 0 and min_jerk(1) == 1 and min_jerk(0.5) == pytest.approx(0.5)


def simulate(task: str, delay_s: float, seed: int = 0, rate: float = 50.0) -> tasks.TrialScore:
    """The operator on a plant that follows the master at scale 0.5 after ``delay_s`` and shows
    its tip ``delay_s`` later again (a round trip of twice the delay)."""
    spec = tasks.get(task)
    policy = make(task, 0.5, rate, seed)
    start, dt = np.array(spec.start_tip), 1.0 / rate
    master, masters, tips = np.zeros(3), [(0.0, np.zeros(3))], [(0.0, *spec.start_tip)]
    k = round(delay_s / dt)
    for n in range(int(spec.time_limit_s * rate)):
        t = n * dt
        tip = start + 0.5 * masters[max(0, len(masters) - 1 - k)][1]
        tips.append((t, *tip))
        seen = np.array(tips[max(0, len(tips) - 1 - k)][1:])
        out = policy(PolicyObservation(t, np.zeros(6), seen, (0, 0, 0, 1), t > 0.5, master.copy()))
        master = master + (np.zeros(3) if out is None else out)
        masters.append((t, master.copy()))
        if n % 50 == 0 and tasks.evaluate(spec, np.array(tips)).done:
            break
    arr = np.array(tips)
    follow = np.array([[0.5, 1.0]])
    return tasks.score(
        spec, Streams(arr, np.zeros((0, 2)), np.zeros((0, 3)), follow, *(np.zeros((0, 2)),) * 2)
    )


@pytest.mark.parametrize("task", ["mh3f-targets", "mh3f-wire", "mh3f-trocar-targets"])
def test_the_operator_does_the_task_and_delay_makes_it_slower(task: str) -> None:
    times = {}
    for delay in (0.0, 0.15, 0.3):
        s = simulate(task, delay)
        assert s.completed, (task, delay)
        times[delay] = s.completion_time_s
        print(
            f"{task}: delay {delay * 1e3:.0f} ms each way → {s.completion_time_s:.1f} s, "
            f"economy {s.economy:.2f}"
        )
    assert times[0.0] < times[0.15] < times[0.3]
    assert times[0.0] > 2.0  # a person's reaction times and reaches, not a teleport


PEGS = TaskSpec(
    name="test-transfer",
    robot="vip",
    kind="transfer",
    instructions="Hand the peg over.",
    goals=(Goal((-0.02, 0.0, -0.1), 0.005), Goal((0.0, 0.0, -0.09), 0.008), Goal((0.02, 0.0, -0.1), 0.005)),
    start_tip=(-0.03, 0.0, -0.07),
    start_tips=((-0.03, 0.0, -0.07), (0.03, 0.0, -0.07)),
    arms=("arm1", "arm2"),
    obj="peg",
)


def peg_track(*legs: tuple[float, tuple[float, float, float], int]) -> np.ndarray:
    """The object's samples at 50 Hz: each leg (seconds, where it is, holders bits)."""
    rows, t = [], 0.0
    for dur, p, bits in legs:
        for _ in range(round(dur / 0.02)):
            rows.append((t, *p, bits))
            t += 0.02
    return np.array(rows)


def test_a_peg_transfer_is_done_when_placed_after_a_hand_over_and_a_drop_is_counted() -> None:
    start, over, place = (g.position for g in PEGS.goals)
    ok = peg_track(
        (0.5, start, 0), (1.0, start, 1), (0.5, over, 1), (0.5, over, 3), (0.5, over, 2), (1.0, place, 0)
    )
    prog = tasks.evaluate(PEGS, ok)
    assert prog.done and len(prog.reached) == 3 and not prog.exits
    assert prog.done_t == pytest.approx(3.0 + tasks.LET_GO_S, abs=0.03)  # placed once let go 0.3 s
    # placed by the first arm without a hand-over: not done (and let go there before a hand-over, a drop)
    skip = peg_track((0.5, start, 0), (1.0, start, 1), (1.0, place, 1), (1.0, place, 0))
    assert not tasks.evaluate(PEGS, skip).done
    # dropped on the way (free 1 s on the floor), picked up again, then the transfer: one drop
    floor = (-0.01, 0.01, -0.12)
    dropped = peg_track(
        (0.5, start, 1), (1.0, floor, 0), (0.5, floor, 1), (0.5, over, 3), (0.3, over, 2), (1.0, place, 0)
    )
    prog = tasks.evaluate(PEGS, dropped)
    assert prog.done and len(prog.exits) == 1 and prog.exits[0] == pytest.approx(0.5, abs=0.03)
    # a grasp's contacts flickering for less than 0.3 s are no drop
    flicker = peg_track((0.5, start, 1), (0.1, start, 0), (0.5, over, 1), (0.5, over, 2), (1.0, place, 0))
    assert not tasks.evaluate(PEGS, flicker).exits


def test_the_score_of_a_transfer_counts_drops_collisions_and_both_arms_paths() -> None:
    start, over, place = (g.position for g in PEGS.goals)
    floor = (-0.01, 0.01, -0.12)
    obj = peg_track(
        (0.5, start, 1), (1.0, floor, 0), (0.5, floor, 1), (0.5, over, 3), (0.3, over, 2), (1.0, place, 0)
    )
    t = obj[:, 0]
    arm1 = np.column_stack([t, np.linspace(0, 0.05, len(t)), np.zeros((len(t), 2))])  # 50 mm
    arm2 = np.column_stack([t, np.zeros(len(t)), np.linspace(0, 0.03, len(t)), np.zeros(len(t))])  # 30 mm
    collide = np.column_stack([t, ((t > 1.0) & (t < 1.2)) | ((t > 2.0) & (t < 2.1))])
    streams = Streams(
        tip=arm1,
        force=np.column_stack([t, np.zeros_like(t)]),
        rcm=np.zeros((0, 3)),
        follow=np.array([[0.0, 1.0]]),
        clutch=np.zeros((0, 2)),
        safety=np.zeros((0, 2)),
        obj=obj,
        collide=collide,
        more_tips={"arm2": arm2},
        more_forces={"arm2": np.column_stack([t, np.where((t > 3.0) & (t < 3.2), 2.5, 0.0)])},
    )
    s = tasks.score(PEGS, streams)
    assert s.completed and s.goals_reached == 3
    assert s.errors["drop"] == 1 and s.errors["collision"] == 2 and s.errors["tissue_force"] == 1
    assert s.errors["path_exit"] == 0
    done_frac = s.completion_time_s / t[-1]
    assert s.path_lengths_mm["arm1"] == pytest.approx(50 * done_frac, rel=0.03)
    assert s.path_lengths_mm["arm2"] == pytest.approx(30 * done_frac, rel=0.03)
    assert s.path_length_mm == pytest.approx(sum(s.path_lengths_mm.values()), abs=0.02)
    assert s.peak_force_n == pytest.approx(2.5)
    legs = [((-0.03, 0.0, -0.07), start), (start, over), ((0.03, 0.0, -0.07), over), (over, place)]
    assert s.ideal_length_mm == pytest.approx(sum(math.dist(a, b) for a, b in legs) * 1e3)


def test_a_transfer_task_needs_its_three_goals_two_arms_and_an_object() -> None:
    with pytest.raises(ConfigError, match="3 goals"):
        TaskSpec(
            "x", "vip", "transfer", "", PEGS.goals[:2], (0.0, 0.0, 0.0), arms=("arm1", "arm2"), obj="peg"
        )
    with pytest.raises(ConfigError, match="an obj"):
        TaskSpec("x", "vip", "transfer", "", PEGS.goals, (0.0, 0.0, 0.0), arms=("arm1", "arm2"))


def test_the_operator_errs_on_purpose_only_when_told() -> None:
    """``press_mm`` aims every touch that deep into the tissue; ``detour_mm`` takes the wire's middle
    via point that far to the side, out of its tube; without them it aims at the goals themselves."""
    targets, wire = tasks.get("mh3f-targets"), tasks.get("mh3f-wire")
    plain, pressed = via_points(targets, 0.012), via_points(targets, 0.012, press_m=0.009)
    touches = [g.position for g in targets.goals]
    assert [g.position for g in plain[1::3]] == touches
    for g, want in zip(pressed[1::3], touches, strict=True):
        np.testing.assert_allclose(np.subtract(want, g.position), (0.0, 0.0, 0.009))
    straight, detour = via_points(wire, 0.012), via_points(wire, 0.012, detour_m=0.010)
    off = [float(tasks.distance_to_path([g.position], wire.path)[0][0]) for g in detour]
    assert max(float(tasks.distance_to_path([g.position], wire.path)[0][0]) for g in straight) < 1e-9
    assert sorted(off)[-2] < 1e-9 and max(off) == pytest.approx(0.010, abs=1e-3)  # one via point out
