"""Control modes of the slave arm (slave_control.modes): non-trocar, transitional, trocar."""

from __future__ import annotations

import copy
import math
import random
from collections.abc import Callable
from itertools import pairwise

import pytest
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import CONTROL_MODES, Header, OperatingState, decode
from telesurg.shared.robots.mh3f.modes import (
    CARTESIAN_AXES,
    JOINT_AXES,
    ControlMode,
    ControlModes,
    Frame,
    Jog,
    ModeConfig,
    MotionMode,
    Phase,
    PostureMethod,
    Reply,
)

DEG = math.radians(1.0)
OUT = -0.100  # m: tip 100 mm before the trocar
ALIGNED = 0.02 * DEG
J45 = (0.2, -0.1)  # rad to go for J4 (+11.46°) and J5 (-5.73°)
BASIC = ["master_slave", "jog", "direct_teach", "playback"]


def ok(reply: Reply) -> None:
    assert reply.accepted, reply.reason


def status(m: ControlModes) -> tuple[object, ...]:
    """(control mode, phase, motion mode, active jog)."""
    return (m.control_mode, m.phase, m.motion, m.jog_command)


def transitions_text(m: ControlModes) -> list[str]:
    return [t for k, t in m.events if k == "mode_transition"]


# --------------------------------------------------------------------------- states


def build(name: str) -> ControlModes:
    """A machine brought into state ``name`` through legal commands only."""
    m = ControlModes()
    m.update(None, None, False)
    if name == "non_trocar_untaught":
        return m
    ok(m.teach_trocar())
    m.update(OUT, 20 * DEG, True, j45_to_target_rad=J45)
    if name == "non_trocar":
        return m
    if name == "non_trocar_jog":
        ok(m.set_motion_mode("jog"))
        ok(m.jog("world", "z", 1))
        return m
    if name.startswith("posture_"):
        method = name.removeprefix("posture_")
        ok(m.begin_posture_adjust(method, program_axis_angle_rad=0.02 * DEG))
        if method == "jog":
            ok(m.jog("joint", "j4", 1))
        return m
    ok(m.begin_posture_adjust("ptp"))
    m.update(OUT, ALIGNED, True)
    ok(m.finish_posture_adjust())
    ok(m.insert())
    if name == "insert":
        return m
    if name == "remove_stopped":  # abort with the tip 10 mm in: only the way out is left
        m.update(0.010, ALIGNED, True)
        ok(m.abort())
        return m
    m.update(0.060, ALIGNED, True)
    assert m.control is ControlMode.TROCAR
    ok(m.set_motion_mode("master_slave"))
    if name == "trocar":
        return m
    if name == "trocar_jog":
        ok(m.set_motion_mode("jog"))
        ok(m.jog("world", "z", -1))
        return m
    if name == "trocar_lost":
        m.update(0.060, ALIGNED, False)
        return m
    assert name == "remove"
    ok(m.remove())
    m.update(0.030, ALIGNED, True)
    return m


STATES = [
    "non_trocar_untaught",
    "non_trocar",
    "non_trocar_jog",
    "posture_ptp",
    "posture_jog",
    "posture_direct_teach",
    "posture_playback",
    "insert",
    "trocar",
    "trocar_jog",
    "trocar_lost",
    "remove",
    "remove_stopped",
]

LABELS = {
    "non_trocar_untaught": ("non_trocar", None, None),
    "non_trocar": ("non_trocar", None, None),
    "non_trocar_jog": ("non_trocar", None, "jog"),
    "posture_ptp": ("transitional/posture (ptp)", "posture", "ptp"),
    "posture_jog": ("transitional/posture (jog)", "posture", "jog"),
    "posture_direct_teach": ("transitional/posture (direct_teach)", "posture", "direct_teach"),
    "posture_playback": ("transitional/posture (playback)", "posture", "playback"),
    "insert": ("transitional/insert", "insert", "jog"),
    "trocar": ("trocar", None, "master_slave"),
    "trocar_jog": ("trocar", None, "jog"),
    "trocar_lost": ("trocar", None, None),
    "remove": ("transitional/remove", "remove", "jog"),
    "remove_stopped": ("transitional/remove", "remove", None),
}


@pytest.mark.parametrize("name", STATES)
def test_builders_reach_their_state(name: str) -> None:
    m = build(name)
    label, phase, motion = LABELS[name]
    assert (m.label, m.phase, m.motion) == (label, phase, motion)


# --------------------------------------------------------------------------- commands


Command = Callable[[ControlModes], Reply]


def _jog(frame: str, axis: str, d: int) -> Command:
    return lambda m: m.jog(frame, axis, d)


def _begin(method: str, program: float | None = None) -> Command:
    return lambda m: m.begin_posture_adjust(method, program_axis_angle_rad=program)


def _mode(mode: str) -> Command:
    return lambda m: m.set_motion_mode(mode)


ALL_JOGS = [
    f"{f} {a}{'+' if d > 0 else '-'}"
    for f in Frame
    for a in (JOINT_AXES if f is Frame.JOINT else CARTESIAN_AXES)
    for d in (1, -1)
]

#: Every command (except stop/abort, always accepted), by a key.
COMMANDS: dict[str, Command] = {
    "teach_trocar": lambda m: m.teach_trocar(),
    "begin(ptp)": _begin("ptp"),
    "begin(jog)": _begin("jog"),
    "begin(direct_teach)": _begin("direct_teach"),
    "begin(playback)": _begin("playback", 0.02 * DEG),
    "begin(playback, program 2°)": _begin("playback", 2.0 * DEG),
    "begin(playback, program unknown)": _begin("playback"),
    "begin(bogus)": _begin("bogus"),
    "finish": lambda m: m.finish_posture_adjust(),
    "insert": lambda m: m.insert(),
    "remove": lambda m: m.remove(),
    **{f"mode({mm})": _mode(mm) for mm in [*BASIC, "ptp", "bogus"]},
    **{f"jog({j})": _jog(j.split()[0], j.split()[1][:-1], 1 if j[-1] == "+" else -1) for j in ALL_JOGS},
    "jog(bogus frame)": _jog("tool", "x", 1),
    "jog(joint x)": _jog("joint", "x", 1),
    "jog(world j1)": _jog("world", "j1", 1),
    "jog(direction 0)": _jog("forceps", "x", 0),
    "jog(direction 2)": _jog("forceps", "x", 2),
}

_BEGIN_ALL = {"begin(ptp)", "begin(jog)", "begin(direct_teach)", "begin(playback)"}
_MODES_BASIC = {f"mode({mm})" for mm in BASIC}
_TROCAR_JOGS = {
    f"jog({f} {a}{s})" for f in ("world", "base", "work", "forceps") for a in ("x", "y", "z") for s in "+-"
} | {"jog(forceps rx+)", "jog(forceps rx-)", "jog(joint j6+)", "jog(joint j6-)"}

#: The accepted commands in each state; every other command in COMMANDS must be refused.
ALLOWED: dict[str, set[str]] = {
    "non_trocar_untaught": {"teach_trocar"} | _MODES_BASIC,
    "non_trocar": {"teach_trocar"} | _BEGIN_ALL | _MODES_BASIC,
    "non_trocar_jog": {"teach_trocar"} | _BEGIN_ALL | _MODES_BASIC | {f"jog({j})" for j in ALL_JOGS},
    "posture_ptp": {"mode(ptp)"},
    "posture_jog": {"mode(jog)", "jog(joint j4+)", "jog(joint j5-)"},  # toward the J4/J5 targets
    "posture_direct_teach": {"mode(direct_teach)"},
    "posture_playback": {"mode(playback)"},
    "insert": {"insert", "mode(jog)", "jog(forceps x+)", "jog(forceps x-)"},
    "trocar": {"remove"} | _MODES_BASIC,
    "trocar_jog": {"remove"} | _MODES_BASIC | _TROCAR_JOGS,
    "trocar_lost": {"remove"},
    "remove": {"remove", "mode(jog)", "jog(forceps x-)"},
    "remove_stopped": {"remove", "mode(jog)"},
}


def test_tables_cover_every_state_and_command() -> None:
    assert set(ALLOWED) == set(STATES) == set(LABELS)
    for allowed in ALLOWED.values():
        assert allowed <= set(COMMANDS)
    assert len(_TROCAR_JOGS) == 28 and len(ALL_JOGS) == 60


@pytest.mark.parametrize("name", STATES)
def test_each_command_in_each_state_is_allowed_or_refused_without_side_effects(name: str) -> None:
    for key, command in COMMANDS.items():
        m = build(name)
        before = copy.deepcopy(m)
        reply = command(m)
        assert reply.accepted == (key in ALLOWED[name]), f"{name}: {key}: {reply}"
        assert reply.reason.strip(), f"{name}: {key}: empty reason"
        if not reply.accepted:
            assert m == before, f"{name}: refused {key} changed the machine"


@pytest.mark.parametrize("name", STATES)
def test_allowed_lists_exactly_the_accepted_commands(name: str) -> None:
    shown = build(name).allowed()
    assert shown["state"] == [LABELS[name][0]]
    listed = set(shown["commands"]) - {"jog", "stop", "abort"}
    expected = ALLOWED[name] - {k for k in ALLOWED[name] if k.startswith("jog(")}
    rename = {"teach_trocar": "teach_trocar", "finish": "finish_posture_adjust", "insert": "insert"}
    rename |= {"remove": "remove", **{f"begin({p})": f"begin_posture_adjust({p})" for p in PostureMethod}}
    rename |= {f"mode({mm})": f"set_motion_mode({mm})" for mm in MotionMode}
    assert listed == {rename[k] for k in expected}
    modes = {k for k in ALLOWED[name] if k.startswith("mode(")}
    assert {f"mode({mm})" for mm in shown["motion_modes"]} == modes
    assert {f"jog({j})" for j in shown["jog"]} == {k for k in ALLOWED[name] if k.startswith("jog(")}
    assert ("jog" in shown["commands"]) == bool(shown["jog"])
    assert shown["commands"][-2:] == ["stop", "abort"]


def test_allowed_in_transitional_insert() -> None:
    assert build("insert").allowed() == {
        "state": ["transitional/insert"],
        "commands": ["insert", "set_motion_mode(jog)", "jog", "stop", "abort"],
        "motion_modes": ["jog"],
        "jog": ["forceps x+", "forceps x-"],
    }


REASONS = [
    ("non_trocar_untaught", "insert", "insert refused: no trocar taught"),
    ("non_trocar_untaught", "begin(ptp)", "posture adjustment refused: no trocar taught"),
    ("non_trocar", "insert", "insert refused in non_trocar mode: adjust the posture first"),
    ("non_trocar", "mode(ptp)", "ptp refused in non_trocar mode: point-to-point is a posture-adjustment"),
    ("non_trocar", "jog(world x+)", "jog along world x+ refused: motion mode is none (select jog first)"),
    ("non_trocar", "begin(playback, program 2°)", "taught point 2.0° off the trocar direction (limit 0.05°)"),
    ("non_trocar", "begin(playback, program unknown)", "alignment of the program's taught point unknown"),
    ("non_trocar", "begin(bogus)", "unknown method 'bogus'"),
    ("non_trocar", "remove", "remove refused in non_trocar mode: the forceps is not inserted"),
    ("non_trocar_jog", "jog(bogus frame)", "unknown frame 'tool'"),
    ("non_trocar_jog", "jog(joint x)", "'x' is not an axis of the joint frame (j1, j2, j3, j4, j5, j6)"),
    ("non_trocar_jog", "jog(direction 0)", "direction must be +1 or -1, got 0"),
    ("non_trocar_jog", "mode(bogus)", "unknown motion mode 'bogus'"),
    ("posture_ptp", "finish", "finish_posture_adjust refused: forceps axis 20.0° off the trocar direction"),
    ("posture_ptp", "mode(master_slave)", "master_slave refused in transitional/posture (ptp): only ptp"),
    ("posture_ptp", "begin(jog)", "already adjusting"),
    ("posture_ptp", "teach_trocar", "teach_trocar refused in transitional/posture (ptp)"),
    ("posture_ptp", "insert", "insert refused in transitional/posture (ptp): finish the posture adjustment"),
    ("posture_jog", "jog(joint j4-)", "J4 must move toward its target (+11.46° to go)"),
    ("posture_jog", "jog(joint j3+)", "only joints j4 and j5 may move"),
    ("posture_direct_teach", "jog(joint j4+)", "jog is not the chosen posture method"),
    ("insert", "jog(world x+)", "jog along world x+ refused in transitional/insert: only the forceps axis"),
    ("insert", "jog(forceps y+)", "only the forceps axis (forceps x) is allowed"),
    ("insert", "mode(master_slave)", "master_slave refused in transitional mode"),
    ("insert", "remove", "remove refused in transitional/insert: back out with jog(forceps, x, -1)"),
    ("trocar", "insert", "insert refused in trocar mode: the forceps is already inserted"),
    ("trocar", "teach_trocar", "teach_trocar refused in trocar mode"),
    ("trocar", "begin(ptp)", "posture adjustment refused in trocar mode"),
    ("trocar", "mode(ptp)", "ptp refused in trocar mode"),
    ("trocar_jog", "jog(world rx+)", "the trocar fixes the shaft direction"),
    ("trocar_jog", "jog(joint j1+)", "only j6"),
    ("trocar_lost", "mode(master_slave)", "master_slave refused in trocar mode: no trocar taught"),
    ("remove", "jog(forceps x+)", "refused in transitional/remove: only outward (forceps x-)"),
    ("remove", "insert", "insert refused in transitional/remove"),
    ("remove", "mode(direct_teach)", "direct_teach refused in transitional mode"),
]


@pytest.mark.parametrize(("name", "key", "text"), REASONS)
def test_refusal_reasons(name: str, key: str, text: str) -> None:
    m = build(name)
    before = copy.deepcopy(m)
    reply = COMMANDS[key](m)
    assert not reply.accepted and text in reply.reason, reply.reason
    assert m == before


# --------------------------------------------------------------------------- legal paths


@pytest.mark.parametrize("method", list(PostureMethod))
def test_insert_and_remove_through_every_posture_method(method: PostureMethod) -> None:
    m = ControlModes()
    m.update(None, None, False)
    ok(m.teach_trocar())
    m.update(OUT, 30 * DEG, True, j45_to_target_rad=(0.3, 0.2))
    ok(m.begin_posture_adjust(method, program_axis_angle_rad=0.0))
    expected_motion = {"ptp": "ptp", "jog": "jog", "direct_teach": "direct_teach", "playback": "playback"}
    assert (m.control_mode, m.phase, m.posture_method) == ("transitional", Phase.POSTURE, method)
    assert m.motion == expected_motion[method]
    if method is PostureMethod.JOG:
        ok(m.jog("joint", "j4", 1))
        m.update(OUT, 10 * DEG, True, j45_to_target_rad=(0.1, 0.2))
        assert m.jog_command == Jog(Frame.JOINT, "j4", 1)  # still on its way
        m.update(OUT, 5 * DEG, True, j45_to_target_rad=(0.0, 0.2))
        assert m.jog_command is None  # J4 reached its target: the jog stops itself
        ok(m.jog("joint", "j5", 1))
        m.update(OUT, ALIGNED, True, j45_to_target_rad=(0.0, -0.01))
        assert m.jog_command is None  # J5 passed its target
    m.update(OUT, ALIGNED, True)
    ok(m.finish_posture_adjust())
    assert (m.label, m.motion, m.posture_method) == ("transitional/insert", MotionMode.JOG, None)
    ok(m.insert())
    assert m.jog_command == Jog(Frame.FORCEPS, "x", 1)
    for depth in (-0.05, -0.001, 0.0, 0.02, 0.0499999):
        m.update(depth, ALIGNED, True)
        assert m.label == "transitional/insert"
    m.update(0.05, ALIGNED, True)  # exactly 50 mm
    assert status(m) == ("trocar", None, MotionMode.JOG, None)
    ok(m.set_motion_mode("master_slave"))
    m.update(0.08, ALIGNED, True)
    ok(m.remove())
    assert (m.label, m.motion, m.jog_command) == ("transitional/remove", "jog", Jog(Frame.FORCEPS, "x", -1))
    for depth in (0.07, 0.05, 0.0, -0.001, -0.002):
        m.update(depth, 30 * DEG, True)  # alignment does not matter on the way out
        assert m.label == "transitional/remove"
    m.update(-0.0021, ALIGNED, True)
    assert status(m) == ("non_trocar", None, None, None)
    assert m.transitions == 5
    assert transitions_text(m) == [
        f"non_trocar → transitional/posture ({method})",
        f"transitional/posture ({method}) → transitional/insert",
        "transitional/insert → trocar: depth 50.0 mm ≥ 50.0 mm",
        "trocar → transitional/remove",
        "transitional/remove → non_trocar: tip out of the trocar (depth -2.1 mm < -2.0 mm)",
    ]
    assert m.trocar_taught  # a second insertion can start right away
    ok(m.begin_posture_adjust("ptp"))


def test_state_fits_operating_state_message() -> None:
    assert {c.value for c in ControlMode} == CONTROL_MODES - {"joint"}  # joint: the joint-space slaves
    for name in STATES:
        m = build(name)
        msg = OperatingState(Header("slave_control", 0, 1), control_mode=m.control_mode)
        got = decode(msg.encode())
        assert isinstance(got, OperatingState) and got.control_mode == m.label.split("/")[0]


# --------------------------------------------------------------------------- thresholds


def crossings(values: list[float], threshold: float) -> int:
    return sum((a >= threshold) != (b >= threshold) for a, b in pairwise(values))


def test_trocar_threshold_switches_once_under_jitter() -> None:
    m = build("insert")
    rng = random.Random(1)
    ramp = [-0.02 + 0.0008 * i + rng.uniform(-0.003, 0.003) for i in range(120)]  # -20 → +76 mm
    hover = [0.05 + rng.uniform(-0.004, 0.004) for _ in range(300)]
    depths = ramp + hover
    assert crossings(depths, 0.05) >= 10  # the noise really does cross the threshold, many times
    first = next(i for i, d in enumerate(depths) if d >= 0.05)
    start = m.transitions
    for i, d in enumerate(depths):
        m.update(d, ALIGNED, True)
        assert (m.control is ControlMode.TROCAR) == (i >= first), i
    assert m.transitions == start + 1
    depth = f"{depths[first] * 1e3:.1f} mm"
    assert transitions_text(m)[-1] == f"transitional/insert → trocar: depth {depth} ≥ 50.0 mm"


def test_exit_threshold_switches_once_under_jitter() -> None:
    m = build("trocar")
    m.update(0.06, ALIGNED, True)
    ok(m.remove())
    rng = random.Random(2)
    ramp = [0.06 - 0.0002 * i + rng.uniform(-0.003, 0.003) for i in range(351)]  # 60 → -10 mm
    back = [rng.uniform(-0.004, 0.055) for _ in range(200)]  # after the exit: noise, even past 50 mm
    depths = ramp + back
    assert crossings(ramp, 0.05) >= 3 and crossings(ramp, -0.002) >= 3
    assert max(back) >= 0.05 and crossings(back, -0.002) >= 5
    first = next(i for i, d in enumerate(depths) if d < -0.002)
    start = m.transitions
    for i, d in enumerate(depths):
        m.update(d, ALIGNED, True)
        assert m.label == ("non_trocar" if i >= first else "transitional/remove"), i
    assert m.transitions == start + 1


def test_exit_needs_the_margin_not_just_zero() -> None:
    m = build("remove")
    rng = random.Random(3)
    for _ in range(500):  # tip sitting in the trocar valve: depth noise between -1.9 and +1 mm
        m.update(rng.uniform(-0.0019, 0.001), ALIGNED, True)
    assert m.label == "transitional/remove"
    m.update(-0.002, ALIGNED, True)
    assert m.label == "transitional/remove"  # strictly beyond the margin
    m.update(-0.00201, ALIGNED, True)
    assert m.label == "non_trocar"


def test_no_automatic_switch_outside_its_phase() -> None:
    m = build("non_trocar")
    for d in (0.06, -0.01, 0.1):
        m.update(d, ALIGNED, True)
    assert m.label == "non_trocar" and m.transitions == 0
    m = build("posture_ptp")
    m.update(0.06, ALIGNED, True)  # a depth past 50 mm in the posture phase does not mean trocar mode
    assert m.label == "transitional/posture (ptp)"
    m = build("trocar")
    for d in (-0.01, 0.0, 0.03, -0.05):
        m.update(d, ALIGNED, True)
    assert m.label == "trocar"  # trocar mode is left by remove() only


def test_config_thresholds_are_used_and_validated() -> None:
    m = ControlModes(ModeConfig(trocar_depth_m=0.03, exit_margin_m=0.0, align_tolerance_rad=5 * DEG))
    ok(m.teach_trocar())
    m.update(OUT, 4 * DEG, True)
    ok(m.begin_posture_adjust("ptp"))
    ok(m.finish_posture_adjust())  # 4° is within the 5° tolerance
    ok(m.insert())
    m.update(0.0299, 4 * DEG, True)
    assert m.label == "transitional/insert"
    m.update(0.03, 4 * DEG, True)
    assert m.label == "trocar"
    ok(m.remove())
    m.update(0.0, 4 * DEG, True)
    assert m.label == "transitional/remove"
    m.update(-1e-6, 4 * DEG, True)
    assert m.label == "non_trocar"
    for bad in (
        {"trocar_depth_m": 0.0},
        {"trocar_depth_m": math.nan},
        {"exit_margin_m": -0.001},
        {"align_tolerance_rad": -1.0},
        {"joint_deadband_rad": math.inf},
    ):
        with pytest.raises(ConfigError):
            ModeConfig(**bad)


# --------------------------------------------------------------------------- safety rules


def test_insert_refused_with_numbers_and_stopped_when_alignment_is_lost() -> None:
    m = build("insert")
    m.events.clear()
    m.update(OUT, 7.3 * DEG, True)
    assert m.jog_command is None and m.label == "transitional/insert"
    assert m.events == [
        (
            "jog_stopped",
            "jog forceps x+ stopped: forceps axis 7.3° off the trocar direction (limit 2.0°)",
        )
    ]
    before = copy.deepcopy(m)
    refused = "insert refused: forceps axis 7.3° off the trocar direction (limit 0.05°)"
    assert m.insert() == Reply(False, refused)
    assert m == before
    ok(m.jog("forceps", "x", -1))  # backing away stays allowed
    m.update(-0.12, 7.3 * DEG, True)
    assert m.jog_command == Jog(Frame.FORCEPS, "x", -1)
    m.update(OUT, ALIGNED, True)
    ok(m.insert())


def test_unknown_measurements_count_as_missing() -> None:
    m = build("insert")
    m.update(math.nan, ALIGNED, True)
    assert m.depth_m is None and m.jog_command is None
    assert m.insert() == Reply(False, "insert refused: insertion depth unknown")
    m.update(OUT, math.inf, True)
    assert m.insert() == Reply(False, "insert refused: forceps axis angle to the trocar unknown")
    m = build("posture_jog")
    m.update(OUT, 20 * DEG, True, j45_to_target_rad=(math.nan, 0.1))
    assert m.jog_command is None and m.j45_to_target_rad is None
    assert "J4 target unknown" in m.jog("joint", "j4", 1).reason
    m = build("posture_ptp")
    m.update(None, ALIGNED, True)
    assert m.finish_posture_adjust() == Reply(False, "finish_posture_adjust refused: insertion depth unknown")
    m.update(-0.001, -0.02 * DEG, True)  # aligned (the magnitude counts) but the tip is not outside
    reply = m.finish_posture_adjust()
    assert not reply.accepted and "tip at depth -1.0 mm" in reply.reason


def test_posture_jog_only_toward_the_target() -> None:
    m = build("posture_jog")  # J4 +11.46°, J5 -5.73° to go; jogging j4+
    assert m.jog_command == Jog(Frame.JOINT, "j4", 1)
    assert not m.jog("joint", "j5", 1).accepted
    ok(m.jog("joint", "j5", -1))
    m.update(OUT, 10 * DEG, True, j45_to_target_rad=(0.1, -0.001))  # 0.06° to go: jogs on
    assert m.jog_command == Jog(Frame.JOINT, "j5", -1)  # (a jog a hold stopped here is not stuck)
    m.update(OUT, 10 * DEG, True, j45_to_target_rad=(0.1, -0.0001))  # J5 within the 0.01° deadband
    assert m.jog_command is None
    stopped = "jog joint j5- stopped: J5 at its target (-0.01° to go, deadband 0.01°)"
    assert m.events[-1] == ("jog_stopped", stopped)
    reply = m.jog("joint", "j5", -1)
    assert not reply.accepted and "J5 at its target" in reply.reason


def test_abort_goes_to_the_safe_state() -> None:
    cases = [  # state, depth before abort, label after, transitions added
        ("non_trocar_jog", OUT, "non_trocar", 0),
        ("posture_jog", OUT, "non_trocar", 1),
        ("insert", OUT, "non_trocar", 1),
        ("insert", 0.010, "transitional/remove", 1),  # tip in the trocar: only the way out
        ("insert", None, "transitional/remove", 1),  # unknown: assume inside
        ("trocar_jog", 0.06, "trocar", 0),
        ("remove", 0.03, "transitional/remove", 0),
    ]
    for name, depth, label, added in cases:
        m = build(name)
        m.update(depth, ALIGNED, True, j45_to_target_rad=J45)
        n, before = m.transitions, m.label
        reply = m.abort("pedal released")
        assert reply.accepted and reply.reason, name
        assert (m.label, m.motion, m.jog_command) == (label, None, None), name
        assert m.transitions == n + added, name
        assert m.events[-1][0] == "abort" and m.events[-1][1].startswith("pedal released: motion stopped")
        if added:
            assert f"{before} → {label}: abort (pedal released)" in transitions_text(m)[-1]


def test_losing_the_trocar_aborts() -> None:
    m = build("posture_ptp")
    m.update(OUT, ALIGNED, False)
    assert m.label == "non_trocar" and m.events[-1] == (
        "abort",
        "trocar position lost: motion stopped, transitional/posture (ptp) → non_trocar",
    )
    m = build("trocar")
    m.update(0.06, ALIGNED, False)
    assert (m.label, m.motion) == ("trocar", None)
    m.update(0.06, ALIGNED, False)  # only the falling edge aborts
    assert [k for k, _ in m.events].count("abort") == 1
    ok(m.remove())  # the way out stays open
    m = build("non_trocar")
    m.update(OUT, ALIGNED, False)
    assert m.label == "non_trocar" and not m.trocar_taught and m.events[-1][0] != "abort"


# --------------------------------------------------------------------------- events


def test_events_and_transition_counts() -> None:
    m = ControlModes()
    ok(m.set_motion_mode("jog"))
    ok(m.jog("world", "x", 1))
    ok(m.teach_trocar())
    m.update(OUT, ALIGNED, True)
    assert not m.insert().accepted  # refusals leave no event
    ok(m.begin_posture_adjust("ptp"))
    ok(m.set_motion_mode("ptp"))  # already active: nothing changes
    ok(m.finish_posture_adjust())
    ok(m.insert())
    ok(m.stop())
    ok(m.stop())
    assert m.transitions == 2
    assert m.events == [
        ("motion_mode", "none → jog"),
        ("trocar_taught", "trocar position taught"),
        ("jog_stopped", "jog world x+ stopped: leaving non_trocar"),
        ("mode_transition", "non_trocar → transitional/posture (ptp)"),
        ("motion_mode", "jog → ptp"),
        ("mode_transition", "transitional/posture (ptp) → transitional/insert"),
        ("motion_mode", "ptp → jog"),
        ("jog_stopped", "jog forceps x+ stopped: stopped by the operator"),
    ]
    m.events.clear()  # drained by the caller
    ok(m.insert())
    m.update(0.05, ALIGNED, True)
    assert m.events == [
        ("jog_stopped", "jog forceps x+ stopped: leaving transitional/insert"),
        ("mode_transition", "transitional/insert → trocar: depth 50.0 mm ≥ 50.0 mm"),
    ]
    assert m.transitions == 3


def test_alignment_tolerance_boundary() -> None:
    for angle, accepted in ((0.05 * DEG, True), (0.06 * DEG, False)):
        m = build("posture_ptp")
        m.update(OUT, angle, True)
        assert m.finish_posture_adjust().accepted == accepted
        m = build("insert")
        ok(m.stop())
        m.update(OUT, angle, True)
        reply = m.insert()
        assert reply.accepted == accepted
        if not accepted:
            assert reply.reason == "insert refused: forceps axis 0.06° off the trocar direction (limit 0.05°)"


def test_running_insertion_has_a_wider_alignment_tolerance() -> None:
    m = build("insert")
    m.update(OUT, 1.5 * DEG, True)  # servo lag while moving: 1.5° does not stop it
    assert m.jog_command == Jog(Frame.FORCEPS, "x", 1)
    m.update(OUT, 2.1 * DEG, True)
    assert m.jog_command is None
    assert m.insert().reason == "insert refused: forceps axis 2.1° off the trocar direction (limit 0.05°)"
    m.update(OUT, 1.5 * DEG, True)
    assert not m.insert().accepted  # starting again needs the 0.05° of a fresh start
