"""The force stream on a real zenoh bus (two sessions on loopback): what reaches a haptic device.

A haptic console takes ``slave/<arm>/measured_cf`` from slave_control only; each decoded force goes
through the force renderer to a simulated Touch. Forged, unsigned and replayed messages are refused
by the bus before decoding; non-finite ones by the strict decoder; an oversized one (a signed,
well-formed 500 N) by the renderer. Every one is counted, and the device only ever gets the genuine
1 N.
"""

from __future__ import annotations

import math
import time

import msgpack
import numpy as np
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
