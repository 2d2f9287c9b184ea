"""The joint-servo protocol, the servo-controller emulator and the ``serial`` slave backend.

Layers: pure message tests (documented bytes, round trips, strict validation, the expected-robot
check); round trips through pyserial over ``loop://`` and a real pseudo-terminal; the emulator's
own rules (sequence order, limits, watchdog) driven by hand; the ``serial`` backend against an
in-process emulator on a pty (handshake, refusal of a wrong robot, damaged frames, sequence gaps,
silence, the controller's watchdog and fault flag, clamps, the MuJoCo shadow); the fault hold of
the control loops; ``python -m telesurg.tools.emulate emulate-slave`` as a real process.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import select
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import telesurg.shared.servo_protocol as sp
from conftest import wait_until
from telesurg.services.slave_control import SlaveControlConfig
from telesurg.services.slave_control.arm import FaultHold
from telesurg.services.slave_control.backends import MujocoBackend
from telesurg.services.slave_control.control import FollowController, Lease, Setpoint
from telesurg.services.slave_control.factory import make_backend
from telesurg.services.slave_control.serial_backend import (
    SerialBackend,
    SerialBackendConfig,
    ShadowConfig,
    ShadowedBackend,
)
from telesurg.shared.config import load_config
from telesurg.shared.errors import ConfigError, DeviceConnectionError, MessageError
from telesurg.shared.kinematics import quat_from_matrix
from telesurg.shared.robots import arms_of
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk
from telesurg.shared.serial_link import Frame, FrameReader, SerialLink, decode_frame, encode_frame
from telesurg.shared.servo_protocol import (
    Disable,
    Enable,
    Hello,
    HelloRequest,
    ServoRobot,
    State,
    decode_message,
    encode_message,
    send_message,
)
from telesurg.tools.emulate import main as device_main
from telesurg.tools.emulate.emulator import BoardEmulator
from telesurg.tools.emulate.servo_emulator import ServoEmulator, ServoEmulatorOptions

pytestmark = pytest.mark.timeout(120)
REPO = Path(__file__).resolve().parent.parent

MH3F_ROBOT = ServoRobot.of("mh3f")
HOME = np.array(MH3F_ROBOT.home)
STATE = State(1234, (0.1, -0.2), (0.0, 0.5), (0.25, -1.0), 0x06, 41, False, True)


# --------------------------------------------------------------------------- helpers


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    """(controller fd, device path) of a raw pseudo-terminal pair, both ends closed afterwards."""
    controller, device = os.openpty()
    tty.setraw(device)
    try:
        yield controller, os.ttyname(device)
    finally:
        for fd in (controller, device):
            with contextlib.suppress(OSError):
                os.close(fd)


@contextlib.contextmanager
def serving(emu: ServoEmulator) -> Iterator[ServoEmulator]:
    """Run ``emu`` in a thread for the duration of the block."""
    stop = threading.Event()
    th = threading.Thread(target=emu.serve, args=(stop,), daemon=True)
    th.start()
    try:
        yield emu
    finally:
        stop.set()
        th.join(timeout=5.0)


def backend_on(path: str, model: str = "mh3f", **cfg: Any) -> SerialBackend:
    """A serial backend on ``path``; timeouts of 400 ms unless given (this CI host stalls)."""
    cfg = {"stale_ms": 400.0, "timeout_ms": 400.0, **cfg}
    return SerialBackend(SerialBackendConfig(path, **cfg), ServoRobot.of(model), arms_of(model))


def run_steps(b: SerialBackend | ShadowedBackend, seconds: float, q: Any = None, until: Any = None) -> bool:
    """Step ``b`` in real time (command ``q(t)`` if given) for ``seconds`` or until ``until()``."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        if q is not None:
            b.command(q(time.monotonic() - t0))
        time.sleep(b.dt)
        b.step()
        if until is not None and until():
            return True
    return until is None


def read_frames(fd: int, timeout: float = 0.5) -> list[Frame]:
    """Every frame arriving on ``fd`` within ``timeout``."""
    reader, out = FrameReader(), list[Frame]()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if select.select([fd], [], [], 0.05)[0]:
            with contextlib.suppress(BlockingIOError):
                out += reader.feed(os.read(fd, 4096))
    return out


# --------------------------------------------------------------------------- messages


def test_documented_setpoint_bytes() -> None:
    wire = encode_message(sp.Setpoint(7, (0.5, -0.25), 100), 9)
    expected = (
        "04 01 33 09 0d 83 a3 73 65 71 07 a1 71 92 cb 3f e0 01 01 01 01 01 04 cb bf d0 01 "
        "01 01 01 01 0f aa 74 69 6d 65 6f 75 74 5f 6d 73 64 a4 cb 00"
    )
    assert wire.hex(" ") == expected
    doc = " ".join((sp.__doc__ or "").split())
    assert expected[:80] in doc and expected[81:] in doc  # the module docstring shows these bytes
    robots = " ".join((REPO / "docs" / "robots.md").read_text(encoding="utf-8").split())
    assert expected[:80] in robots  # and so does docs/robots.md (Hardware)
    assert decode_message(decode_frame(wire)) == sp.Setpoint(7, (0.5, -0.25), 100)


def test_link_budget_of_the_docs() -> None:
    worst_state = State(2**32 - 1, (1e-300,) * 6, (1e-300,) * 6, (1e-300,) * 6, 0x7F, 2**32 - 1, True, True)
    worst_sp = sp.Setpoint(2**32 - 1, (1e-300,) * 6, 10_000)
    assert len(encode_message(worst_state, 0xFFFF)) == 253  # docs: 253 bytes per 6-joint STATE
    assert len(encode_message(worst_sp, 0xFFFF)) == 89  # docs: 89 bytes per 6-joint SETPOINT
    hello = ServoRobot.of("plas").hello(10_000, "x" * 32)  # the largest robot fits a frame
    assert len(encode_message(hello, 0)) < 1024


@pytest.mark.parametrize(
    "msg",
    [
        MH3F_ROBOT.hello(200, "0.1.0"),
        STATE,
        HelloRequest(),
        Enable(2**32 - 1),
        Disable(),
        sp.Setpoint(0, (1.0,) * 16, 1),
    ],
)
def test_message_round_trip(msg: sp.ServoMessage) -> None:
    assert decode_message(decode_frame(encode_message(msg, 3))) == msg


def test_lists_from_the_wire_become_tuples_of_floats() -> None:
    s = State.from_body({**STATE.body(), "q": [1, 2], "qd": [0, 0], "current": [0, 0]})
    assert s.q == (1.0, 2.0) and all(type(v) is float for v in s.q)


GOOD_HELLO = MH3F_ROBOT.hello(200, "t").body()


@pytest.mark.parametrize(
    ("kind", "body", "match"),
    [
        (sp.KIND_HELLO, {**GOOD_HELLO, "proto": 2}, "HELLO proto=2 unsupported"),
        (sp.KIND_HELLO, {**GOOD_HELLO, "joints": 5}, "HELLO lower has 6 values, expected 5"),
        (
            sp.KIND_HELLO,
            {**GOOD_HELLO, "upper": GOOD_HELLO["lower"]},
            "joint 1: lower .* must be below upper",
        ),
        (sp.KIND_HELLO, {**GOOD_HELLO, "max_velocity": [1, 1, 1, 1, 1, 0]}, "max_velocity 0.0 must be > 0"),
        (sp.KIND_HELLO, {k: v for k, v in GOOD_HELLO.items() if k != "fw"}, r"missing field\(s\) \['fw'\]"),
        (sp.KIND_HELLO, {**GOOD_HELLO, "model": ""}, "model must be 1..32 characters"),
        (sp.KIND_STATE, {**STATE.body(), "extra": 1}, r"unknown field\(s\) \['extra'\]"),
        (sp.KIND_STATE, {**STATE.body(), "qd": [0.0]}, "STATE qd has 1 values, expected 2"),
        (sp.KIND_STATE, {**STATE.body(), "q": [float("nan"), 0.0]}, r"STATE q\[0\]=nan is not finite"),
        (sp.KIND_STATE, {**STATE.body(), "q": [True, 0.0]}, r"q\[0\] must be a number, got bool"),
        (sp.KIND_STATE, {**STATE.body(), "fault": 0x80}, "sets reserved bits"),
        (sp.KIND_STATE, {**STATE.body(), "enabled": 1}, "STATE enabled must be a boolean"),
        (sp.KIND_STATE, {**STATE.body(), "t_us": -1}, r"t_us=-1 outside \[0, 4294967295\]"),
        (sp.KIND_STATE, {**STATE.body(), "q": [], "qd": [], "current": []}, "STATE q has 0 values"),
        (sp.KIND_SETPOINT, {"seq": 1, "q": [0.0], "timeout_ms": 0}, r"timeout_ms=0 outside \[1, 10000\]"),
        (sp.KIND_SETPOINT, {"seq": 2**32, "q": [0.0], "timeout_ms": 5}, "SETPOINT seq=4294967296 outside"),
        (sp.KIND_SETPOINT, {"seq": 1, "q": [0.0] * 17, "timeout_ms": 5}, "has 17 values, need 1..16"),
        (sp.KIND_SETPOINT, {"seq": 1, "q": "0", "timeout_ms": 5}, "SETPOINT q must be an array, got str"),
        (sp.KIND_ENABLE, {}, r"ENABLE missing field\(s\) \['seq'\]"),
        (sp.KIND_DISABLE, {"why": "x"}, r"DISABLE unknown field\(s\) \['why'\]; valid: none"),
        (0x7F, {}, "unknown servo frame kind 0x7F; valid: 0x21 HELLO"),
        (0x02, {}, "0x02 is the encoder board's SAMPLE: a master's board on this port"),
    ],
)
def test_strict_validation_names_the_problem(kind: int, body: dict[str, Any], match: str) -> None:
    with pytest.raises(MessageError, match=match):
        decode_message(decode_frame(encode_frame(kind, 0, body)))


def test_fault_bits_and_counters() -> None:
    assert sp.describe_faults(0) == "none"
    assert sp.describe_faults(sp.FAULT_OVERCURRENT | sp.FAULT_LIMIT) == (
        "overcurrent, joint outside its limits (0x0A)"
    )
    assert sp.seq_delta32(2**32 - 1, 0) == 1 and sp.seq_delta32(5, 3) == -2


def test_check_hello_refuses_another_robot_and_accepts_float32_limits() -> None:
    r = MH3F_ROBOT
    f32 = np.float32
    r.check_hello(dataclasses.replace(r.hello(100), upper=tuple(float(f32(v)) for v in r.upper)))
    r.check_hello(dataclasses.replace(r.hello(100), max_velocity=(1.0,) * 6))  # slower: accepted
    with pytest.raises(MessageError, match="drives model 'plas', expected 'mh3f': wrong robot"):
        r.check_hello(ServoRobot.of("plas").hello(100))
    with pytest.raises(MessageError, match="has 5 joints, model mh3f has 6"):
        r.check_hello(Hello("mh3f", "", 5, r.lower[:5], r.upper[:5], r.max_velocity[:5], 100))
    upper = list(r.upper)
    upper[2] -= 0.01
    with pytest.raises(MessageError, match=r"joint j3 upper limit 4\.52786, expected 4\.53786"):
        r.check_hello(dataclasses.replace(r.hello(100), upper=tuple(upper)))


# --------------------------------------------------------------------------- transports


def test_loop_round_trip_and_noise_is_counted() -> None:
    msgs: list[sp.ServoMessage] = [MH3F_ROBOT.hello(100), STATE, HelloRequest(), Enable(3), Disable()]
    with SerialLink("loop://") as link:
        for m in msgs:
            send_message(link, m)
        got = [link.receive(timeout=1.0) for _ in msgs]
        assert [decode_message(f) for f in got if f is not None] == msgs
        wire = encode_message(STATE, 5)
        link._port.write(b"\x13\x37noise\x00" + wire[: len(wire) // 2] + b"\x00" + wire)
        f = link.receive(timeout=1.0)
        assert f is not None and decode_message(f) == STATE
        assert link.reader.error_count == 2 and link.reader.frames == 6


def test_pty_round_trip_with_the_emulator(pty_pair: tuple[int, str]) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(model="vip", rate_hz=100))
    with SerialLink(path) as link, serving(emu):
        send_message(link, HelloRequest())
        assert wait_until(lambda: emu.stats.requests == 1 and emu.stats.states >= 3, 5.0)
        msgs: list[Any] = []

        def answered() -> bool:  # (the emulator counts the request before it writes its answer)
            msgs.extend(decode_message(f) for f in link.poll())
            n_hello, n_state = (sum(isinstance(m, c) for m in msgs) for c in (Hello, State))
            return n_hello >= 2 and n_state >= 3

        assert wait_until(answered, 5.0)
    hellos = [m for m in msgs if isinstance(m, Hello)]
    states = [m for m in msgs if isinstance(m, State)]
    assert len(hellos) == 2 and hellos[0] == ServoRobot.of("vip").hello(100, "emulator")  # boot + answer
    assert len(states) >= 3 and states[-1].q == ServoRobot.of("vip").home
    assert not states[-1].enabled and not states[-1].watchdog_tripped and states[-1].fault == 0


# --------------------------------------------------------------------------- the emulator's rules


def test_emulator_applies_only_newer_setpoints_within_limits_and_trips_its_watchdog(
    pty_pair: tuple[int, str],
) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(model="mh3f", lag_ms=5))
    target = HOME + np.array([0.05, 0, 0, 0, 0, 0])
    with SerialLink(path) as link, serving(emu):
        send_message(link, sp.Setpoint(1, tuple(target), 100))  # disabled: ignored
        send_message(link, Enable(10))
        send_message(link, sp.Setpoint(12, tuple(target), 300))
        send_message(link, sp.Setpoint(11, tuple(HOME), 300))  # late: ignored
        assert wait_until(lambda: emu.stats.setpoints == 1 and emu.stats.stale_setpoints == 1, 5.0)
        assert emu.stats.ignored_setpoints == 1 and emu.last_seq_applied == 12
        assert wait_until(lambda: abs(emu.q[0] - target[0]) < 1e-4, 5.0)  # it moves there
        assert wait_until(lambda: emu.watchdog_tripped, 5.0)  # then no SETPOINT for 300 ms
        t_trip, q_trip = time.monotonic(), emu.q.copy()
        assert not emu.enabled and emu.stats.watchdog_trips == 1
        send_message(link, sp.Setpoint(13, tuple(HOME), 300))  # tripped: ignored until ENABLE
        assert wait_until(lambda: emu.stats.ignored_setpoints == 2, 5.0)
        assert np.array_equal(emu.q, q_trip)
        send_message(link, Enable(20))
        bad = HOME.copy()
        bad[1] = 3.0  # j2 above its 90° limit
        send_message(link, sp.Setpoint(21, tuple(bad), 300))
        assert wait_until(lambda: emu.fault == sp.FAULT_SETPOINT, 5.0)
        assert not emu.enabled and emu.stats.bad_setpoints == 1 and not emu.watchdog_tripped
        assert time.monotonic() - t_trip < 5.0


# --------------------------------------------------------------------------- the serial backend


def test_backend_handshake_follow_and_tip(pty_pair: tuple[int, str]) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(model="mh3f", rate_hz=200))
    b = backend_on(path)
    with serving(emu):
        with b:
            follow_and_check(b, emu)
        assert wait_until(lambda: emu.stats.disables == 1, 5.0)  # a clean exit disables (holds)
        assert not emu.enabled


def follow_and_check(b: SerialBackend, emu: ServoEmulator) -> None:
    """Handshake done; the emulated joints follow a 2-s motion, the tip is the FK of the joints."""
    assert b.phase == "running" and b.fault == "" and emu.enabled
    r = b.read()
    assert np.allclose(r.position, HOME)
    t = fk(r.position, MH3F)
    assert np.allclose(r.tip_position, t[:3, 3]) and np.allclose(r.tip_quat, quat_from_matrix(t[:3, :3]))

    def q(t: float) -> np.ndarray:
        return HOME + 0.2 * np.sin(2.0 * t) * np.array([1, 0.5, -0.5, 1, 1, 1])

    errs = []

    def track() -> bool:
        errs.append(float(np.max(np.abs(b.read().position - q(time.monotonic() - t0)))))
        return False

    t0 = time.monotonic()
    run_steps(b, 2.0, q, track)
    assert b.fault == "" and b.phase == "running"
    moved = float(np.ptp([q(t)[0] for t in np.linspace(0, 2, 50)]))
    print(f"\nfollowed for 2 s: joint error median {np.median(errs):.4f}, max {max(errs):.4f} rad")
    assert moved > 0.3 and np.median(errs) < 0.05  # lag 20 ms + link ≈ 0.02 rad at 0.4 rad/s
    assert b.stats.setpoints > 50
    assert wait_until(lambda: b.stats.setpoints - emu.stats.setpoints <= 2, 5.0)  # all applied
    assert b.stats.corrupt == b.stats.invalid == b.stats.gaps == 0 and b.stats.max_setpoint_lag <= 5


@pytest.mark.parametrize(
    ("setup", "match"),
    [
        ("plas", r"drives model 'plas', expected 'mh3f': wrong robot"),
        ("limit", r"joint j3 upper limit 4\.43786, expected 4\.53786"),
        ("encoder", r"HELLO not understood: .*0x01 is the encoder board's HELLO"),
    ],
)
def test_a_wrong_robot_is_refused_and_nothing_but_hello_request_is_sent(
    pty_pair: tuple[int, str], setup: str, match: str
) -> None:
    controller, path = pty_pair
    reader = FrameReader()
    sent: list[Frame] = []

    def snoop_and_answer() -> None:  # the controller side: record the host's frames, answer
        if setup == "encoder":
            board = BoardEmulator(controller)
            board.send_hello()
            return
        emu = ServoEmulator(controller, ServoEmulatorOptions(model="plas" if setup == "plas" else "mh3f"))
        if setup == "limit":
            upper = list(emu.hello.upper)
            upper[2] -= 0.1
            emu.hello = dataclasses.replace(emu.hello, upper=tuple(upper))
        emu.send(emu.hello)

    b = backend_on(path, handshake_ms=2000)
    done = threading.Event()

    def controller_side() -> None:
        while not done.is_set():
            if select.select([controller], [], [], 0.02)[0]:
                with contextlib.suppress(BlockingIOError):
                    frames = reader.feed(os.read(controller, 4096))
                    sent.extend(frames)
                    if any(f.kind == sp.KIND_HELLO_REQUEST for f in frames):
                        snoop_and_answer()

    th = threading.Thread(target=controller_side, daemon=True)
    th.start()
    try:
        t0 = time.monotonic()
        with pytest.raises(DeviceConnectionError, match=f"refused the controller on {path}: .*{match}"), b:
            pass
        refused_after = time.monotonic() - t0
        time.sleep(0.2)
    finally:
        done.set()
        th.join(5.0)
    assert {f.kind for f in sent} == {sp.KIND_HELLO_REQUEST}  # no ENABLE, no SETPOINT
    assert b.stats.refused == 1 and refused_after < 1.0  # refused at once, no waiting for a timeout


def test_a_silent_port_is_refused_with_a_timeout(pty_pair: tuple[int, str]) -> None:
    _, path = pty_pair
    with (
        pytest.raises(DeviceConnectionError, match=r"no HELLO from the controller .* within 200 ms"),
        backend_on(path, handshake_ms=200),
    ):
        pass
    with (
        pytest.raises(DeviceConnectionError, match="cannot open serial port '/nonexistent/tty'"),
        backend_on("/nonexistent/tty"),
    ):
        pass


def test_damaged_frames_and_sequence_gaps_are_counted_never_fatal(pty_pair: tuple[int, str]) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(rate_hz=200, garbage_every=4, drop_every=7))
    b = backend_on(path)
    faults = set()
    with serving(emu), b:
        run_steps(b, 1.5, lambda t: HOME, lambda: faults.add(b.fault) and False)
        st = b.stats
    print(f"\nemulator: {emu.stats.garbage} noise bursts, {emu.stats.dropped} STATEs dropped; backend: {st}")
    assert faults == {""} and b.phase == "running"  # never a hold
    assert st.corrupt >= emu.stats.garbage // 2  # noise that hit a frame, or was a frame of its own
    assert st.gaps >= emu.stats.dropped - 2 and st.lost >= st.gaps  # (a few hidden by corrupt frames)
    assert st.restarts == 0 and st.states > 50


def test_silence_holds_then_the_link_is_reopened_with_a_new_handshake(pty_pair: tuple[int, str]) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(rate_hz=200, silence_at=0.5, silence_for=1.0))
    b = backend_on(path, stale_ms=150, reconnect_s=0.2)
    with serving(emu), b:
        assert run_steps(b, 5.0, lambda t: HOME, lambda: b.fault != "")
        t_fault = time.monotonic()
        silent_for = t_fault - (emu._enabled_at or 0) - 0.5
        assert b.fault.startswith("serial link lost: no valid STATE from the controller")
        assert b.read().fault == b.fault and b.stats.link_losses == 1
        sent = b.stats.setpoints
        # the host stopped writing SETPOINTs: the controller's own watchdog stops the joints
        assert wait_until(lambda: emu.watchdog_tripped, 2.0)
        assert run_steps(b, 5.0, lambda t: HOME, lambda: b.phase == "running")
        back = time.monotonic() - t_fault
        print(f"\nsilence → hold after {silent_for * 1e3:.0f} ms (stale_ms 150); back {back:.2f} s later")
        assert 0.13 < silent_for < 1.0
        assert (
            b.fault == "" and b.stats.reconnects >= 1 and emu.stats.requests >= 2 and emu.stats.enables == 2
        )
        assert not emu.watchdog_tripped and emu.enabled  # the new ENABLE cleared the trip
        run_steps(b, 0.2, lambda t: HOME)
        assert b.stats.setpoints > sent


def test_controller_watchdog_trip_holds_and_is_re_enabled(pty_pair: tuple[int, str]) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(rate_hz=200))
    b = backend_on(path, timeout_ms=100, stale_ms=1000, reconnect_s=0.3)
    with serving(emu), b:
        run_steps(b, 0.3, lambda t: HOME)
        time.sleep(0.4)  # the host stalls: no SETPOINT for 400 ms
        assert wait_until(lambda: emu.watchdog_tripped, 2.0)  # (the emulator thread checks it)
        assert run_steps(b, 2.0, lambda t: HOME, lambda: b.fault != "")
        assert b.fault.startswith("controller watchdog tripped: no SETPOINT within 100 ms")
        assert b.phase == "tripped" and b.stats.watchdog_trips >= 1
        t0 = time.monotonic()
        assert run_steps(b, 3.0, lambda t: HOME, lambda: b.fault == "")
        assert time.monotonic() - t0 >= 0.25 and emu.stats.enables >= 2 and emu.enabled


def test_fault_flag_holds_disables_and_stays(pty_pair: tuple[int, str]) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(rate_hz=200, fault_at=0.3))
    b = backend_on(path, reconnect_s=0.1)
    with serving(emu), b:
        assert run_steps(b, 3.0, lambda t: HOME + 0.1 * t, lambda: b.fault != "")
        assert b.fault == "controller fault: overcurrent (0x02)" and b.phase == "faulted"
        sent = b.stats.setpoints
        run_steps(b, 0.5, lambda t: HOME)
        assert b.fault == "controller fault: overcurrent (0x02)"  # latched: no automatic re-enable
        assert b.stats.setpoints == sent and emu.stats.disables == 1 and emu.stats.enables == 1


def test_setpoints_are_limit_and_rate_checked_before_they_are_written(pty_pair: tuple[int, str]) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(rate_hz=200))
    b = backend_on(path, speed_fraction=0.1)
    with serving(emu), b:
        far = HOME.copy()
        far[1] = 5.0  # j2: far above its 90° limit, and a jump
        b.command(far)
        b.step()
        sent = b.last_sent
        assert sent is not None
        vmax = np.array(MH3F.max_velocity) * 0.1
        assert np.all(np.abs(sent - HOME) <= vmax * b.dt + 1e-12)  # one period at 10 % speed
        assert b.stats.clipped_limit == 1 and b.stats.clipped_rate == 1
        run_steps(b, 1.0, lambda t: far)
        sent = b.last_sent
        assert sent is not None and sent[1] <= MH3F.upper[1] + 1e-12
        assert emu.stats.bad_setpoints == 0 and emu.fault == 0  # the controller never saw a bad one
        b.command(np.full(6, np.nan))
        n = b.stats.setpoints
        b.step()
        assert b.stats.setpoints == n  # not sent


def test_serial_enable_false_never_enables(pty_pair: tuple[int, str]) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(rate_hz=200))
    with serving(emu), backend_on(path, enable=False) as b:
        run_steps(b, 0.3, lambda t: HOME + 0.1)
        assert b.phase == "disabled" and "serial.enable = false" in b.read().fault
        assert emu.stats.enables == 0 and emu.stats.setpoints == 0 and not emu.enabled


def test_shadow_catches_a_stuck_joint(pty_pair: tuple[int, str]) -> None:
    controller, path = pty_pair
    emu = ServoEmulator(controller, ServoEmulatorOptions(rate_hz=200, stall_joint=1, stall_at=1.0))
    shadow = ShadowedBackend(backend_on(path), MujocoBackend("mh3f", ()), ShadowConfig(0.05, 200.0))
    divs: list[tuple[float, float]] = []

    def q(t: float) -> np.ndarray:  # j1 swings at 0.3 rad/s
        return HOME + np.array([0.3 * t, 0, 0, 0, 0, 0])

    with serving(emu), shadow:

        def watch() -> bool:
            r = shadow.read()
            if r.divergence is not None:
                divs.append((time.monotonic(), r.divergence.max_rad))
            return r.fault != ""

        assert run_steps(shadow, 5.0, q, watch)
        fault = shadow.read().fault
        assert emu._enabled_at is not None
        t_stall = emu._enabled_at + 1.0
        after = time.monotonic() - t_stall
    before = max(d for t, d in divs if t < t_stall)
    print(f"\nshadow: divergence before the stall ≤ {before:.4f} rad; hold {after:.2f} s after it: {fault}")
    assert fault.startswith("shadow divergence") and "at j1" in fault
    assert before < 0.02  # no false alarm while the joint moved freely
    assert 0.2 < after < 2.0  # the limit is crossed ~0.15 s after the stall, then the 200 ms grace


# --------------------------------------------------------------------------- the loops' fault hold


def test_fault_hold_stops_following_freezes_the_command_and_needs_a_new_engage() -> None:
    ctl = FollowController(np.full(6, 1.0))
    lease = Lease(True, 1e9)
    q0 = HOME.copy()
    ctl.update(0.0, q0, q0, lease, Setpoint(q0, False, 0.0), 0.01)
    ctl.update(0.01, q0, q0, lease, Setpoint(q0, True, 0.01), 0.01)
    assert ctl.following
    held = FaultHold()
    ctl.events.clear()
    out = held.update(ctl, "controller fault: overcurrent (0x02)", q0 + 0.01)
    assert not ctl.following and not ctl.armed and ctl.holds == 1 and held.active
    assert ctl.reason == "controller fault: overcurrent (0x02)" and np.allclose(out, q0 + 0.01)
    assert ctl.events == [("hold", "controller fault: overcurrent (0x02)")]
    assert np.allclose(held.update(ctl, "controller fault: overcurrent (0x02)", q0 + 0.05), q0 + 0.01)
    assert len(ctl.events) == 1 and ctl.holds == 1  # same cause: no new event, frozen command
    out = held.update(ctl, "", q0 + 0.05)  # cleared: restart from where the arm is now
    assert np.allclose(out, q0 + 0.05) and not held.active and ctl.events[-1][0] == "fault_cleared"
    q = ctl.update(0.02, out, out, lease, Setpoint(q0 + 0.05, True, 0.02), 0.01)
    assert not ctl.following and np.allclose(q, out)  # follow=True alone does not engage
    ctl.update(0.03, out, q, lease, Setpoint(q0 + 0.05, False, 0.03), 0.01)
    ctl.update(0.04, out, q, lease, Setpoint(q0 + 0.05, True, 0.04), 0.01)
    assert ctl.following  # a new engage (clutch released, then pressed)


# --------------------------------------------------------------------------- config and CLI


def test_serial_config_keys_and_errors() -> None:
    cfg = load_config(
        SlaveControlConfig,
        None,
        ["backend=serial", "serial.port=/dev/ttyACM0", "serial.speed_fraction=0.1", "shadow=true"],
    )
    assert cfg.serial.baud == 500_000 and cfg.serial.speed_fraction == 0.1 and cfg.shadow
    with pytest.raises(ConfigError, match=r"needs serial\.port"):
        make_backend("serial", "mh3f", (), cfg=load_config(SlaveControlConfig, None, ["backend=serial"]))
    with pytest.raises(ConfigError, match=r"serial.speed_fraction=0.0 outside \(0, 1\]"):
        make_backend(
            "serial",
            "mh3f",
            (),
            cfg=dataclasses.replace(cfg, serial=dataclasses.replace(cfg.serial, speed_fraction=0.0)),
        )
    with pytest.raises(ConfigError, match=r"serial.timeout_ms=5.0 outside \[20, 10000\]"):
        make_backend(
            "serial",
            "mh3f",
            (),
            cfg=dataclasses.replace(cfg, serial=dataclasses.replace(cfg.serial, timeout_ms=5.0)),
        )
    with pytest.raises(ConfigError, match='shadow = true needs backend = "serial"'):
        make_backend("mujoco", "mh3f", (), cfg=cfg)
    with pytest.raises(ConfigError, match="valid: mujoco, serial"):
        make_backend("can", "mh3f", ())


def test_emulate_slave_process_serves_a_two_arm_robot() -> None:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "telesurg.tools.emulate",
            "emulate-slave",
            "--pty",
            "--model",
            "plas",
            "--seconds",
            "20",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/"), path
        with backend_on(path, "plas", handshake_ms=5000) as b:
            assert b.joint_names[:2] == ("arm1_d1", "arm1_theta2") and len(b.joint_names) == 12
            run_steps(b, 0.3, lambda t: np.zeros(12))
            r = b.read()
            assert b.fault == "" and r.site_positions is not None and r.site_positions.shape == (2, 3)
            assert np.allclose(r.site_positions[1], arms_of("plas")[1].tip(np.zeros(6)))
        time.sleep(1.0)  # the DISABLE of the backend's exit is read (by a process on a loaded host)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "1 ENABLEs, 1 DISABLEs" in err, err


def test_emulate_slave_bad_options() -> None:
    assert device_main(["emulate-slave", "--pty", "--stall-joint", "7"]) == 2  # mh3f has 6
    assert device_main(["emulate-slave", "--pty", "--rate", "0"]) == 2
    with pytest.raises(SystemExit):
        device_main(["emulate-slave"])  # no transport
