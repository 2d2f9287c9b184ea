"""A subscriber that stops reading does not take the surgeon's control away (issue #21).

Control streams are published with ``CongestionControl.BLOCK``; zenoh's router then waits for
*every* subscriber of a sample before it routes the next. A viewer, recorder or console that stops
reading (hung, starved at low priority, or hostile) used to stall the mapping's and the slave's
streams with it: the watchdog HOLDs. The launcher now gives the control services zenoh ids and
the router waits for those alone (services/router ``congestion_rules``).

Real processes on loopback: router, watchdog, slave_control (MuJoCo), mapping, a scripted master
whose pedal stays pressed; the stalled subscriber is the benches' ``--load stalled``: a plain
zenoh client on ``**`` whose handler is a FIFO of one sample that it never reads, so its zenoh
stops taking data off the socket.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from telesurg.services.launcher import ZID_SERVICES, SiteSpec, service_argv
from telesurg.services.router import RouterConfig, congestion_rules
from telesurg.shared.bus import BusConfig, open_session
from telesurg.shared.errors import ConfigError
from telesurg.tools.bench.harness import Pipeline, now_ns
from telesurg.tools.bench.load import Load

#: the operator presses the pedal for 3 s of every 4 s, as a surgeon re-engages after a hold
PEDAL = ["scripted.clutch=[[0.5, 3.5]]", "scripted.clutch_repeat_s=4.0"]
#: s the stalled subscriber stays on the bus while the slave is watched
WINDOW_S = 12.0
#: share of the slave's joint samples that reach the test's own subscriber when nothing stalls
KEPT = 0.8
#: s: the longest hold a busy host's scheduling causes here is ~0.1 s (a stream a few tens of ms
#: past the watchdog's 80 ms); the stalled subscriber's hazard stops the streams for seconds
STALL_S = 0.5


def hold_episodes(safety: list[tuple], t0: int, t1: int) -> list[tuple[float, str]]:  # type: ignore[type-arg]
    """(length s, causes) of each watchdog HOLD in [t0, t1] ns, until its next other state (or t1)."""
    out, start, why = [], None, ""
    for rec in safety:
        if rec[0] < t0 or rec[0] > t1:
            continue
        if rec[1] == "HOLD" and start is None:
            start, why = rec[0], " ".join(rec[2])
        elif rec[1] != "HOLD" and start is not None:
            out.append(((rec[0] - start) / 1e9, why))
            start = None
    if start is not None:
        out.append(((t1 - start) / 1e9, why))
    return out


def watch(tmp: Path, router: list[str]) -> tuple[list[tuple[float, str]], int, bool, str]:
    """The watchdog's holds (length, causes), slave joint samples received, whether the slave
    followed in the window's last pedal period, over WINDOW_S with a stalled subscriber on the
    bus; and the pipeline's diagnosis."""
    overrides = {"master_capture": PEDAL, "router": router}
    with Pipeline(tmp / "logs", mirror=False, impair=False, overrides=overrides) as p:
        assert p.wait_following(30), "the slave never followed\n" + p.diagnose()
        with Load.parse("stalled").running(p.spec.endpoint, tmp):
            t0 = now_ns()
            n0 = len(p.p.joints)
            time.sleep(WINDOW_S)
            t1 = now_ns()
            with p.p.lock:
                holds = hold_episodes(p.p.safety, t0, t1)
                followed = any(r[1] for r in p.p.op if r[0] >= t1 - 4_000_000_000)
            joints = len(p.p.joints) - n0
            why = p.diagnose()
        p.close()
    return holds, joints, followed, why


def test_zenoh_ids_are_checked_before_zenoh_sees_them() -> None:
    for bad in ("0abc", "ABC", "xyz", "1" * 33):
        with pytest.raises(ConfigError, match="bus zid"):
            BusConfig(connect=["tcp/127.0.0.1:7447"], zid=bad).validate()
        with pytest.raises(ConfigError, match="control_zids"):
            RouterConfig(control_zids=["8abc", bad]).validate()


def test_a_session_takes_the_id_it_is_given(endpoint: str) -> None:
    session = open_session(BusConfig(connect=[endpoint], zid="8badf00d"))
    try:
        assert str(session.zid()) == "8badf00d"
    finally:
        session.close()  # type: ignore[no-untyped-call]


def test_the_launcher_tells_the_router_the_ids_it_gives_the_control_services() -> None:
    spec = SiteSpec(services=("watchdog", "slave_control", "mapping", "master_capture", "mirror"))
    assert set(spec.zids) == set(ZID_SERVICES) and len(set(spec.zids.values())) == len(ZID_SERVICES)
    router = service_argv(spec, "router")
    told = next(a for a in router if a.startswith("control_zids="))
    assert sorted(json.loads(told.partition("=")[2])) == sorted(spec.zids.values())
    for name in ZID_SERVICES:
        assert f"bus.zid={json.dumps(spec.zids[name])}" in service_argv(spec, name)
    assert not any(a.startswith("bus.zid=") for a in service_argv(spec, "mirror"))  # an observer
    assert SiteSpec().zids != spec.zids  # each site its own


def test_rules_drop_for_everyone_then_block_for_the_control_sessions() -> None:
    assert congestion_rules([]) == []
    drop, block = congestion_rules(["8abc", "9def"])
    assert "zids" not in drop and drop["overwrite"] == {"congestion_control": "drop"}
    assert block["zids"] == ["8abc", "9def"] and block["overwrite"] == {"congestion_control": "block"}
    for rule in (drop, block):  # only the control streams (REAL_TIME), only on the way out
        assert rule["qos"] == {"priority": "real_time"} and rule["flows"] == ["egress"]


@pytest.mark.process
def test_a_stalled_subscriber_does_not_stall_the_control_path(tmp_path: Path) -> None:
    holds, joints, followed, why = watch(tmp_path, router=[])
    print(f"holds {holds[:3]}, slave joint samples {joints} in {WINDOW_S} s, followed {followed}")
    long = [h for h in holds if h[0] > STALL_S]
    assert not long, f"the control streams stalled while a subscriber did: {long[:3]}\n{why}"
    assert followed, f"the slave stopped following\n{why}"
    assert joints > KEPT * 250 * WINDOW_S  # the slave's measured_js (250 Hz) kept coming


@pytest.mark.process
def test_without_control_ids_the_stalled_subscriber_stalls_the_streams(tmp_path: Path) -> None:
    """The hazard the router's rules remove, with zenoh's default (``control_zids=[]``): the
    router waits for the stalled subscriber, up to 5 s a sample, and the other subscribers' streams
    stop with it — the slave's joints for seconds, and the watchdog HOLDs when it is the mapping's
    or the master's stream that waits."""
    holds, joints, followed, _ = watch(tmp_path, router=["control_zids=[]"])
    print(f"holds {holds[:3]}, slave joint samples {joints} in {WINDOW_S} s, followed {followed}")
    long = [h for h in holds if h[0] > STALL_S]
    assert long or joints < KEPT * 250 * WINDOW_S, "the stalled subscriber held nothing up"
