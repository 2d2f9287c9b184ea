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

#: pedal pressed from 0.5 s on and held: one engage, so any HOLD ends the following for good
HELD_PEDAL = ["scripted.clutch=[[0.5, 1e9]]", "scripted.clutch_repeat_s=0.0"]
#: s the stalled subscriber stays on the bus while the slave is watched
WINDOW_S = 12.0
#: share of the slave's joint samples that reach the test's own subscriber when nothing stalls
KEPT = 0.8


def watch(tmp: Path, router: list[str]) -> tuple[list[str], int, bool]:
    """Holds seen by the probe, slave joint samples received, and whether the slave still
    follows, over WINDOW_S with a stalled subscriber on the bus."""
    overrides = {"master_capture": HELD_PEDAL, "router": router}
    with Pipeline(tmp / "logs", mirror=False, impair=False, overrides=overrides) as p:
        assert p.wait_following(30), "the slave never followed"
        with Load.parse("stalled").running(p.spec.endpoint, tmp):
            t0 = now_ns()
            n0 = len(p.p.joints)
            time.sleep(WINDOW_S)
            with p.p.lock:
                holds = [" ".join(s[2]) for s in p.p.safety if s[0] >= t0 and s[1] == "HOLD"]
            joints = len(p.p.joints) - n0
            following = p.p.following()
        p.close()
    return holds, joints, following


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
    holds, joints, following = watch(tmp_path, router=[])
    print(f"holds {holds[:3]}, slave joint samples {joints} in {WINDOW_S} s, following {following}")
    assert not holds, f"the watchdog held while a subscriber stalled: {holds[:3]}"
    assert following, "the slave stopped following"
    assert joints > KEPT * 250 * WINDOW_S  # the slave's measured_js (250 Hz) kept coming


@pytest.mark.process
def test_without_control_ids_the_stalled_subscriber_stalls_the_streams(tmp_path: Path) -> None:
    """The hazard the router's rules remove, with zenoh's default (``control_zids=[]``): the
    router waits for the stalled subscriber, up to 5 s a sample, and the other subscribers' streams
    stop with it — the slave's joints for seconds, and the watchdog HOLDs when it is the mapping's
    or the master's stream that waits."""
    holds, joints, following = watch(tmp_path, router=["control_zids=[]"])
    print(f"holds {holds[:3]}, slave joint samples {joints} in {WINDOW_S} s, following {following}")
    assert holds or joints < KEPT * 250 * WINDOW_S, "the stalled subscriber held nothing up"
