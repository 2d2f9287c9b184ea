"""The two-host key split on one machine (issue #39, acceptance 5): the console host holds only its
own identities' keys (docs/deploy.md's ``telesurg keys export …`` and ``keys import``, run as
written) and a link to the slave site; the site's services run on the site's keyring, which no
longer holds them.

Real services (router, watchdog, slave_control on MuJoCo, mapping) on the site's keyring, the
master on the console host's; the operator's console a node on the console host's keyring. What a
user notices: the master drives the slave, the console reads state, its command and e-stop work;
and nothing the console host can sign with — its link key, its own keys, a key it makes itself —
moves, holds or releases the slave in the name of a site identity (each such message is refused
as unauthenticated and counted by the slave).
"""

from __future__ import annotations

import secrets
import time
from pathlib import Path

import numpy as np
import pytest
from telesurg.shared import auth
from telesurg.shared.bus import BusConfig, Node, open_session
from telesurg.shared.messages import (
    Command,
    CommandReply,
    EStop,
    Header,
    JointSetpoint,
    JointState,
    SafetyLease,
    SafetyState,
    Sequencer,
)
from telesurg.tools.bench.harness import Pipeline, now_ns
from test_docs_recipes import two_host_keys

pytestmark = pytest.mark.process


def test_a_console_host_with_only_its_own_keys(tmp_path: Path) -> None:
    site_keys, pack = two_host_keys(tmp_path)  # docs/deploy.md's export and import, as written
    pipe = Pipeline(tmp_path / "logs", mirror=False, impair=False)
    pipe.spec.keys_dir = site_keys
    pipe.spec.service_keys["master_capture"] = pack  # the master runs on the console host
    console_bus = BusConfig(connect=[pipe.spec.endpoint], keys_dir=str(pack))
    with pipe, Node(console_bus, pipe.spec.site, "console") as console:
        k = console.keys
        states: list[tuple[int, str]] = []  # (received ns, state)
        console.subscribe(
            k.safety("arm1", "state"), SafetyState, lambda m, _k: states.append((now_ns(), m.state))
        )
        js: list[JointState] = []
        console.subscribe(k.slave("arm1", "measured_js"), JointState, lambda m, _k: js.append(m))

        # drive: the console host's master engages and moves the slave
        assert pipe.wait_following(60), "the slave never followed the console host's master"
        moved = 0.0
        deadline = time.monotonic() + 20.0
        while moved <= 2.0 and time.monotonic() < deadline:
            pipe.wait_following(10)
            t0 = now_ns()
            time.sleep(1.0)
            moved = max(moved, pipe.p.motion_after(t0, 1.0))
        print(f"tip moved {moved:.1f} mm in 1 s of following")
        assert moved > 2.0
        # state: the console host verifies the site's streams and replies
        assert pipe.wait(lambda: bool(states) and bool(js), 5), "the console host saw no state"
        seq = Sequencer("console")
        reply = console.request(k.command("arm1"), Command(seq.next(), "arm1", "state"), CommandReply, 3.0)
        assert reply.name == "state" and reply.header.source == "slave_control"

        # e-stop from the console host latches
        estop = console.outlet(k.estop)
        time.sleep(0.3)
        t_stop = now_ns()
        estop.put(EStop(estop.header(), "*", "estop", "split-keys test"))
        assert pipe.wait(lambda: pipe.p.first_safety_after(t_stop, ("ESTOP",)) is not None, 5)
        assert pipe.wait(lambda: bool(states) and states[-1][1] == "ESTOP", 5)
        t_latched = states[-1][0]

        # forgeries with everything the console host holds, while the e-stop is latched (and the
        # arm has come to rest)
        pipe.wait(lambda: pipe.p.motion_after(now_ns() - 500_000_000, 0.5) < 0.02, 5)
        t_forge = now_ns()
        forged = _forge(pipe, pack, js[-1])
        time.sleep(1.0)
        latched = [state for t, state in states if t >= t_latched]
        assert latched and all(s == "ESTOP" for s in latched), f"the latch moved: {latched}"
        with pipe.p.lock:
            refused = [
                text
                for t, src, kind, text in pipe.p.events
                if t >= t_stop and src == "slave_control" and kind == "unauthenticated"
            ]
        claimed = {s for s in ("watchdog", "mapping") if any(f"claimed signer '{s}'" in t for t in refused)}
        print(f"{forged} forged messages; slave_control refused as unauthenticated: {refused[:2]}")
        assert claimed == {"watchdog", "mapping"}, refused
        motion = pipe.p.motion_after(t_forge, (now_ns() - t_forge) / 1e9)
        assert motion < 0.1, f"the slave moved {motion:.3f} mm under forged messages"

        # the console's reset clears it
        t_reset = now_ns()
        estop.put(EStop(estop.header(), "*", "reset", "split-keys test"))
        cleared = pipe.wait(lambda: any(t > t_reset and s != "ESTOP" for t, s in states[-3:]), 5)
        assert cleared, f"the console's reset did not clear the e-stop: {states[-3:]}, {t_reset}"


def _forge(pipe: Pipeline, pack: Path, js: JointState) -> int:
    """Leases (allow) as the watchdog, setpoints as the mapping and e-stop resets as the watchdog,
    signed with each key material of the console host's keyring; returns how many were sent."""
    ring = auth.Keyring.load(pack)
    keys = {
        "link key": (ring.links["slave-site"].send, ()),
        "own key + link key": (secrets.token_bytes(auth.KEY_BYTES), ring.send_keys()),
        "console key + link key": (ring.keys["console"], ring.send_keys()),
    }
    k = pipe.node.keys
    session = open_session(BusConfig(connect=[pipe.spec.endpoint]))
    n = 0
    try:
        for key, links in keys.values():
            wd = auth.Signer("watchdog", key, links=links)
            mp = auth.Signer("mapping", key, links=links)
            for i in range(50):
                now = time.time_ns()
                lease = SafetyLease(Header("watchdog", 10_000 + i, now), "arm1", True, 250.0, "").encode()
                q = np.array(js.position)
                q[0] += 0.2 * i / 50
                sp = JointSetpoint(
                    Header("mapping", 10_000 + i, now), js.names, tuple(q), follow=True
                ).encode()
                reset = EStop(Header("watchdog", 10_000 + i, now), "*", "reset", "forged").encode()
                for signer, key_expr, payload in (
                    (wd, k.safety("arm1", "lease"), lease),
                    (mp, k.slave("arm1", "servo_jp"), sp),
                    (wd, k.estop, reset),
                ):
                    session.put(key_expr, payload, attachment=signer.attach(auth.PUT, key_expr, payload))
                    n += 1
                time.sleep(0.01)
    finally:
        session.close()  # type: ignore[no-untyped-call]
    return n
