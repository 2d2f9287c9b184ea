"""The force stream on a real zenoh bus (two sessions on loopback): what reaches a haptic device.

A haptic console takes ``slave/<arm>/measured_cf`` from slave_control only; each decoded force goes
through the force renderer to a simulated Touch. Forged, unsigned and replayed messages are refused
by the bus before decoding; non-finite ones by the strict decoder; an oversized one (a signed,
well-formed 500 N) by the renderer. Every one is counted, and the device only ever gets the genuine
1 N.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import msgpack
import numpy as np
import pytest
from conftest import wait_until
from telesurg.services.master_capture.devices.touch_sim.model import HeldDevice, TouchModel, press_and_slide
from telesurg.shared import auth
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.haptics import ForceRenderer, RenderConfig
from telesurg.shared.messages import CartesianWrench


def test_only_genuine_forces_reach_the_device(endpoint: str) -> None:
    bus = BusConfig(connect=[endpoint])
    renderer = ForceRenderer(RenderConfig())
    offered: list[tuple[float, float, float]] = []

    def take(msg: CartesianWrench, key: str) -> None:
        offered.append(msg.force)
        renderer.offer(msg.force, time.monotonic())

    with (
        Node(bus, "t", "master_capture") as console,
        Node(bus, "t", "slave_control") as slave,
        Node(bus, "t", "intruder") as bad,
    ):
        key = console.keys.slave("arm1", "measured_cf")
        console.subscribe(key, CartesianWrench, take, sources=["slave_control"])
        out = slave.outlet(key)
        time.sleep(0.3)
        genuine = CartesianWrench(out.header(), "base", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0)).encode()
        att = out._signer.attach(auth.PUT, key, genuine)
        slave.session.put(key, genuine, attachment=att)
        stats = console.streams.get(key)
        assert wait_until(lambda: len(offered) == 1)
        # replayed: the same bytes and authenticator again
        slave.session.put(key, genuine, attachment=att)
        # unsigned, and signed by another identity claiming to be slave_control
        forged = CartesianWrench(out.header(), "base", (0.0, 0.0, 50.0), (0.0, 0.0, 0.0)).encode()
        bad.session.put(key, forged)
        forger = auth.Signer("intruder", bad.keyring.keys["intruder"])
        bad.session.put(key, forged, attachment=forger.attach(auth.PUT, key, forged))
        # signed by slave_control but NaN / Inf: the strict decoder refuses them
        for value in (math.nan, math.inf):
            body = msgpack.unpackb(CartesianWrench(out.header(), "base", (0.0, 0.0, 1.0)).encode())
            body["force"] = [0.0, 0.0, value]
            raw = msgpack.packb(body)
            slave.session.put(key, raw, attachment=out._signer.attach(auth.PUT, key, raw))
        # signed and well formed but 500 N: the renderer refuses it
        out.put(CartesianWrench(out.header(), "base", (0.0, 0.0, 500.0), (0.0, 0.0, 0.0)))
        assert wait_until(lambda: len(offered) == 2)
        # 2 unauthenticated, 1 replayed, 2 not decodable: all rejected before any callback
        assert wait_until(lambda: stats.rejected == 5), stats
        assert stats.unauthenticated == 2 and stats.replayed == 1 and stats.received == 2
        assert renderer.rejected == 1 and offered[-1] == (0.0, 0.0, 500.0)
    device = HeldDevice(TouchModel(), press_and_slide())
    now = renderer.fresh_at
    forces = [np.linalg.norm(device.write_force(renderer.step(now + k * 1e-3, 1e-3))) for k in range(20)]
    assert max(forces) <= 1.0 + 1e-9  # the genuine 1 N, approached at the rate limit; nothing else


def haptic_console(
    endpoint: str, monkeypatch: pytest.MonkeyPatch
) -> tuple[Any, threading.Event, threading.Thread]:
    """master_capture's real loop (not started) with a touch_sim whose hand stays put (no contact
    in its script) and haptics on for arm1 (the naive controller: the force as it comes)."""
    from telesurg.services import master_capture
    from telesurg.services.master_capture import devices
    from telesurg.services.master_capture.devices.touch_sim import TouchSim, TouchSimConfig

    dev = TouchSim(TouchSimConfig(surface_mm=-1000.0))
    monkeypatch.setattr(devices, "open_device", lambda name, settings=None: dev)
    cfg = master_capture.MasterCaptureConfig(
        device="touch_sim", rate_hz=1000.0, bus=BusConfig(connect=[endpoint])
    )
    cfg.haptics.slave_arm = "arm1"
    cfg.haptics.controller = "naive"
    stop = threading.Event()
    return dev, stop, threading.Thread(target=master_capture.run, args=(cfg, stop), daemon=True)


def test_master_capture_renders_the_slave_force_and_fades_it(
    endpoint: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """master_capture with the touch_sim device and haptics on (its real loop, in a thread, on a
    real bus): nothing while the pair is not engaged; engaged, the device pushes with force_scale
    × the slave's contact force; when the stream stops it fades to zero no faster than 10 N/s; a
    watchdog HOLD fades it too, and so does a clutch release."""
    from telesurg.shared.messages import SafetyState, TeleopState

    dev, stop, thread = haptic_console(endpoint, monkeypatch)
    bus = BusConfig(connect=[endpoint])
    samples: list[tuple[float, float]] = []

    def force() -> float:
        f = float(np.linalg.norm(dev.sim.motor))
        samples.append((time.monotonic(), f))
        return f

    with (
        Node(bus, "local", "slave_control") as slave,
        Node(bus, "local", "watchdog") as watchdog,
        Node(bus, "local", "mapping") as mapping,
    ):
        thread.start()
        out = slave.outlet(slave.keys.slave("arm1", "measured_cf"))
        teleop = mapping.outlet(mapping.keys.mapping("arm1", "teleop_state"))

        def pair(state: str) -> None:
            teleop.put(TeleopState(teleop.header(), "m1", "arm1", state))

        time.sleep(0.5)

        def push(seconds: float, fz: float) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                out.put(CartesianWrench(out.header(), "base", (0.0, 0.0, fz), (0.0, 0.0, 0.0)))
                force()
                time.sleep(0.002)

        push(0.6, 2.0)
        assert force() == 0.0  # not engaged: the slave's contact is not the master's to feel
        pair("ENABLED")
        push(0.3, 2.0)
        # 0.5 × 2 N (the loop runs in a thread of this process: on a busy host give it the time)
        end = time.monotonic() + 3.0
        while force() != pytest.approx(1.0, abs=0.05) and time.monotonic() < end:
            push(0.05, 2.0)
        assert force() == pytest.approx(1.0, abs=0.05)
        samples.clear()
        assert wait_until(lambda: force() == 0.0, timeout=2.0)  # the stream stopped: faded out
        # a fade, not a step: any two readings during it (however few a busy host lets this
        # thread take) fall at no more than 10 N/s
        fade = [(t, f) for t, f in samples if 0.0 < f < 0.99]
        assert len(fade) >= 2, samples[:5]
        (t0, f0), (t1, f1) = fade[0], fade[-1]
        assert (f0 - f1) / (t1 - t0) <= 10.0 * 1.2  # ≤ 10 N/s
        end = time.monotonic() + 3.0
        push(0.4, 2.0)
        while force() != pytest.approx(1.0, abs=0.05) and time.monotonic() < end:
            push(0.05, 2.0)
        assert force() == pytest.approx(1.0, abs=0.05)
        held = watchdog.outlet(watchdog.keys.safety("arm1", "state"))
        held.put(SafetyState(held.header(), "arm1", "HOLD", ("test hold",)))
        push(0.4, 2.0)  # the slave still sends: the hold alone fades it
        assert force() < 0.99 - 0.2
        held.put(SafetyState(held.header(), "arm1", "OK", ()))
        end = time.monotonic() + 3.0
        while force() != pytest.approx(1.0, abs=0.05) and time.monotonic() < end:
            push(0.05, 2.0)
        assert force() == pytest.approx(1.0, abs=0.05)
        pair("IDLE")  # the operator clutched out
        push(0.4, 2.0)
        assert force() < 0.99 - 0.2
        stop.set()
        thread.join(timeout=5)
    assert not thread.is_alive()
    assert max(f for _, f in samples) <= 3.3


def test_the_slave_force_is_felt_in_the_frame_the_master_moves_in(
    endpoint: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The mapping moves the slave through R_ms (the camera's view or the work frame; its teleop
    state's ``rotation``): a force along the slave's base y, with R_ms a quarter turn about z
    (master x → slave y), pushes the master's handle along its own x."""
    from telesurg.shared.messages import TeleopState

    dev, stop, thread = haptic_console(endpoint, monkeypatch)
    bus = BusConfig(connect=[endpoint])
    quarter = (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))
    with Node(bus, "local", "slave_control") as slave, Node(bus, "local", "mapping") as mapping:
        thread.start()
        out = slave.outlet(slave.keys.slave("arm1", "measured_cf"))
        teleop = mapping.outlet(mapping.keys.mapping("arm1", "teleop_state"))
        time.sleep(0.5)
        felt = np.zeros(3)
        end = time.monotonic() + 5.0
        while time.monotonic() < end:
            teleop.put(TeleopState(teleop.header(), "m1", "arm1", "ENABLED", rotation=quarter))
            for _ in range(25):
                out.put(CartesianWrench(out.header(), "base", (0.0, 2.0, 0.0), (0.0, 0.0, 0.0)))
                time.sleep(0.002)
            felt = dev.sim.motor.copy()
            if np.allclose(felt, (1.0, 0.0, 0.0), atol=0.05):
                break
        stop.set()
        thread.join(timeout=5)
    print(f"slave force (0, 2, 0) N in the base frame → master {np.round(felt, 3)} N")
    assert felt == pytest.approx((1.0, 0.0, 0.0), abs=0.05)  # 0.5 × R_msᵀ (0, 2, 0)


def test_the_slave_joint_limit_is_a_wall_the_master_feels(
    endpoint: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The mapping's teleop state carries the slave's nearest joint limit as a wall in the master's
    frame (``limit_wall``); engaged, a handle put 5 mm beyond it is pushed back along the wall's
    normal by the guidance's spring (the simulated hand gives way a little), within the Touch's
    3.3 N; short of the wall or clutched out, nothing."""
    from telesurg.shared.messages import TeleopState

    dev, stop, thread = haptic_console(endpoint, monkeypatch)
    bus = BusConfig(connect=[endpoint])
    with Node(bus, "local", "mapping") as mapping:
        thread.start()
        teleop = mapping.outlet(mapping.keys.mapping("arm1", "teleop_state"))
        time.sleep(0.5)

        def felt(state: str, beyond_m: float) -> np.ndarray:
            """The device's force a moment after a teleop state whose wall (normal +x) stands
            ``beyond_m`` behind the handle."""
            wall = (1.0, 0.0, 0.0, float(dev.sim.x[0]) - beyond_m)
            f = np.zeros(3)
            end = time.monotonic() + 3.0
            while time.monotonic() < end:
                teleop.put(TeleopState(teleop.header(), "m1", "arm1", state, limit_wall=wall))
                time.sleep(0.05)
                f = dev.sim.motor.copy()
                if state != "ENABLED" or f[0] < -0.5:
                    break
            return f

        inside = felt("ENABLED", -0.01)  # the handle 10 mm short of the wall
        beyond = felt("ENABLED", 0.005)
        idle = felt("IDLE", 0.005)
        stop.set()
        thread.join(timeout=5)
    print(f"short of the wall {np.round(inside, 3)} N, 5 mm beyond {np.round(beyond, 3)} N, idle {idle}")
    assert np.allclose(inside, 0.0, atol=1e-6)
    assert beyond[0] < -1.0 and abs(beyond[1]) < 0.05 and abs(beyond[2]) < 0.05  # back along −n
    assert np.linalg.norm(beyond) <= 3.3 + 1e-6  # the device's limit
    assert np.allclose(idle, 0.0, atol=0.05)
