"""``telesurg bridge ros2`` without a site: the rmw_zenoh wire format, the CRTK types, the checks of
inbound commands and the console's engage rules, and one bridge on two real zenoh sessions.

The bridge's bytes are read back with the independent client's codec (``tests/ros2_client.py``:
pycdr2 and ``struct``), not with the bridge's own rosbags code.
"""

from __future__ import annotations

import struct
import threading
import time
from typing import Any

import numpy as np
import pytest
import ros2_client as rc
import zenoh
from conftest import wait_until
from telesurg.services.bridge import crtk, rmw
from telesurg.services.bridge.gate import Console, Rejected, check_joints, check_pose
from telesurg.services.bridge.ros2 import Bridge, BridgeConfig
from telesurg.shared.bus import BusConfig, Node, open_session
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import JointSetpoint, JointState, MasterButtons
from telesurg.shared.robots import arm_profile

PROFILE = arm_profile("mh3f", "arm1")
HOME = np.array(PROFILE.home)


@pytest.fixture(scope="module")
def codec() -> crtk.Codec:
    return crtk.Codec()


# -- wire format -----------------------------------------------------------------------------------
def test_keys_and_tokens_follow_rmw_zenoh() -> None:
    h = rc.JOINT_STATE_HASH
    assert (
        rmw.topic_key(0, "/arm1/measured_js", crtk.JOINT_STATE, h)
        == f"0/arm1/measured_js/{rc.JOINT_STATE_DDS}/{h}"
    )
    node = rmw.RosNode(3, "ab12", 0, "telesurg_bridge")
    assert node.token() == "@ros2_lv/3/ab12/0/0/NN/%/%/telesurg_bridge"
    tok = node.endpoint_token(2, "MS", "/arm1/servo_jp", crtk.JOINT_STATE, h)
    assert (
        tok
        == f"@ros2_lv/3/ab12/0/2/MS/%/%/telesurg_bridge/%arm1%servo_jp/{rc.JOINT_STATE_DDS}/{h}/::,10:,:,:,,"
    )
    assert rmw.dds_type_name(crtk.STRING_STAMPED) == rc.STRING_STAMPED_DDS
    for bad in ("arm1/x", "/arm 1/x", ""):
        with pytest.raises(ConfigError):
            rmw.check_topic(bad)
    with pytest.raises(ConfigError):
        rmw.dds_type_name("JointState")


def test_attachment_layout() -> None:
    gid = bytes(range(16))
    raw = rmw.encode_attachment(7, 1_700_000_000_123_456_789, gid)
    assert rc.parse_attachment(raw) == (7, 1_700_000_000_123_456_789, gid)  # the client's own parser
    assert rmw.decode_attachment(rc.attachment(9, gid))[::2] == (9, gid)
    assert rmw.decode_attachment(raw + bytes(7)) == rmw.decode_attachment(raw)  # padding ignored
    for bad in (b"", raw[:20], struct.pack("<qqB", 1, 2, 3) + bytes(16)):
        with pytest.raises(ValueError):
            rmw.decode_attachment(bad)
    with pytest.raises(ValueError):
        rmw.encode_attachment(1, 2, b"short")


def test_types_hashes_and_cdr_agree_with_an_independent_codec(codec: crtk.Codec) -> None:
    assert codec.type_hash(crtk.JOINT_STATE) == rc.JOINT_STATE_HASH
    assert len({codec.type_hash(t.typename) for t in crtk.TOPICS}) == 4
    stamp = 1_700_000_000_123_456_789
    js = codec.encode(codec.joint_state(stamp, ("j1", "j2"), (0.1, -0.2), (1.0, 2.0)), crtk.JOINT_STATE)
    m = rc.JointState.deserialize(js)
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == divmod(stamp, 1_000_000_000)
    assert (m.name, m.position, m.velocity, m.effort) == (["j1", "j2"], [0.1, -0.2], [1.0, 2.0], [])
    cmd = codec.decode(rc.StringStamped(rc.header(), "enable").serialize(), crtk.STRING_STAMPED)
    assert cmd.string == "enable"
    for junk in (b"", b"\x00\x01\x00\x00\xff\xff", js[:-5]):
        with pytest.raises(ValueError):
            codec.decode(junk, crtk.JOINT_STATE)


# -- checks and engage -----------------------------------------------------------------------------
def test_check_joints_rejects_what_must_not_reach_the_slave() -> None:
    names = PROFILE.joint_names
    assert np.allclose(check_joints(PROFILE, names, tuple(HOME)), HOME)
    assert np.allclose(check_joints(PROFILE, (), tuple(HOME)), HOME)  # positional
    bad = {
        "wrong joint count": ((), tuple(HOME[:-1])),
        "are not the arm's": (tuple(reversed(names)), tuple(HOME)),
        "not finite": ((), (float("nan"), *HOME[1:])),
        "outside its limits": ((), (PROFILE.upper[0] + 0.01, *HOME[1:])),
    }
    for why, (n, q) in bad.items():
        with pytest.raises(Rejected, match=why):
            check_joints(PROFILE, n, q)
    with pytest.raises(Rejected, match="jump"):
        check_joints(PROFILE, (), tuple(HOME + 0.2), previous=HOME, max_step_rad=0.1)


def test_check_pose_solves_ik_and_rejects_nonsense() -> None:
    from telesurg.shared.kinematics.transforms import quat_from_matrix

    T = PROFILE.pose(HOME)
    quat = tuple(float(v) for v in quat_from_matrix(T[:3, :3]))
    pos = tuple(float(v) for v in T[:3, 3])
    q = check_pose(PROFILE, "base", pos, quat, HOME)  # type: ignore[arg-type]
    assert np.allclose(PROFILE.pose(q), T, atol=1e-6)
    with pytest.raises(Rejected, match="frame_id"):
        check_pose(PROFILE, "world", pos, quat, HOME)  # type: ignore[arg-type]
    with pytest.raises(Rejected, match="unit quaternion"):
        check_pose(PROFILE, "", pos, (0.0, 0.0, 0.0, 2.0), HOME)  # type: ignore[arg-type]
    with pytest.raises(Rejected, match="non-finite"):
        check_pose(PROFILE, "", (float("inf"), 0.0, 0.0), quat, HOME)  # type: ignore[arg-type]
    with pytest.raises(Rejected, match="IK"):
        check_pose(PROFILE, "", (5.0, 0.0, 0.0), quat, HOME)  # type: ignore[arg-type]


def test_console_engage_rules() -> None:
    c = Console(servo_timeout_s=0.1)
    assert c.on_servo(0.0) == (False, False)  # not engaged: holds
    assert c.command("enable")[0]
    assert c.on_servo(0.01) == (True, True)  # the engage edge: follow=false first
    assert c.on_servo(0.02) == (True, False)
    assert not c.on_slave(False, "")  # not yet following: no disengage
    c.on_slave(True, "")
    assert c.on_slave(False, "lease: HOLD") and not c.enabled  # a hold disengages
    assert c.command("resume")[0] and c.enabled
    assert not c.tick(0.05) and c.tick(0.2) and not c.enabled  # a silent console disengages
    ok, why = c.command("home")
    assert not ok and "homed" in why
    ok, why = c.command("fly")
    assert not ok and "enable" in why
    assert c.command("disable") == (True, "disengaged: the slave holds")


# -- one bridge on real zenoh sessions -------------------------------------------------------------
def test_bridge_on_the_bus(endpoint: str, codec: crtk.Codec) -> None:
    bus = BusConfig(connect=[endpoint])
    cfg = BridgeConfig(bus=bus)
    servo: list[JointSetpoint] = []
    buttons: list[MasterButtons] = []
    ros_js: list[tuple[Any, bytes | None]] = []
    lock = threading.Lock()
    with (
        Node(bus, "local", "slave_control") as slave,
        Node(bus, "local", "watchdog") as wd,
        Node(bus, "local", "ros2_bridge") as node,
    ):
        bridge = Bridge(cfg, node, codec, PROFILE)
        k = wd.keys
        wd.subscribe(
            k.slave("arm1", "servo_jp"), JointSetpoint, lambda m, _: servo.append(m), sources=["ros2_bridge"]
        )
        wd.subscribe(
            k.master("m1", "buttons"), MasterButtons, lambda m, _: buttons.append(m), sources=["ros2_bridge"]
        )
        ros = open_session(bus)
        try:

            def on_ros_js(s: zenoh.Sample) -> None:
                with lock:
                    att = s.attachment.to_bytes() if s.attachment is not None else None
                    ros_js.append((rc.JointState.deserialize(s.payload.to_bytes()), att))

            js_key = f"0/arm1/measured_js/{rc.JOINT_STATE_DDS}/{rc.JOINT_STATE_HASH}"
            sub = ros.declare_subscriber(js_key, on_ros_js)
            tokens: list[str] = []

            def graph() -> bool:
                tokens[:] = [
                    str(r.ok.key_expr) for r in ros.liveliness().get("@ros2_lv/0/**", timeout=2.0) if r.ok
                ]
                return len(tokens) == 1 + len(crtk.TOPICS)

            assert wait_until(graph, 10), tokens
            assert any("/MS/" in t and "%arm1%servo_jp" in t for t in tokens)
            time.sleep(0.3)
            out = slave.outlet(k.slave("arm1", "measured_js"))
            msg = JointState(out.header(), PROFILE.joint_names, tuple(HOME.tolist()), (0.0,) * 6, (0.0,) * 6)
            out.put(msg)
            assert wait_until(lambda: len(ros_js) == 1)
            got, att = ros_js[0]
            assert got.position == list(msg.position) and got.name == list(PROFILE.joint_names)
            assert att is not None and rc.parse_attachment(att)[0] == 1

            servo_key = f"0/arm1/servo_jp/{rc.JOINT_STATE_DDS}/{rc.JOINT_STATE_HASH}"
            cmd_key = f"0/arm1/state_command/{rc.STRING_STAMPED_DDS}/{codec.type_hash(crtk.STRING_STAMPED)}"
            pub, cmd = ros.declare_publisher(servo_key), ros.declare_publisher(cmd_key)
            time.sleep(0.3)
            names = list(PROFILE.joint_names)
            pub.put(rc.JointState(rc.header(), names, list(HOME), [], []).serialize())
            assert wait_until(lambda: len(servo) == 1)
            assert not servo[0].follow  # not engaged
            for q in ([float("nan"), *HOME[1:]], list(HOME[:-1])):
                pub.put(rc.JointState(rc.header(), [], q, [], []).serialize())
            pub.put(b"\x00\x01\x00\x00garbage")
            pub.put(rc.JointState(rc.header(), names, list(HOME), [], []).serialize(), attachment=b"\x01")
            assert wait_until(lambda: sum(bridge.rejected.values()) == 4)
            assert len(servo) == 1, "a rejected command was forwarded"

            cmd.put(rc.StringStamped(rc.header(), "enable").serialize())
            time.sleep(0.3)
            pub.put(rc.JointState(rc.header(), names, list(HOME + 0.001), [], []).serialize())
            assert wait_until(lambda: len(servo) == 3)
            assert [s.follow for s in servo[1:]] == [False, True]  # the engage edge
            # servo_cp: the pose of some joints → IK → those joints on servo_jp
            from telesurg.shared.kinematics.transforms import quat_from_matrix

            q_cp = HOME + 0.01
            T = PROFILE.pose(q_cp)
            quat = tuple(float(v) for v in quat_from_matrix(T[:3, :3]))
            pose = codec.pose_stamped(time.time_ns(), "base", tuple(T[:3, 3].tolist()), quat)  # type: ignore[arg-type]
            cp_key = (
                f"0/arm1/servo_cp/geometry_msgs::msg::dds_::PoseStamped_/{codec.type_hash(crtk.POSE_STAMPED)}"
            )
            cp_pub = ros.declare_publisher(cp_key)
            time.sleep(0.3)
            cp_pub.put(codec.encode(pose, crtk.POSE_STAMPED))
            assert wait_until(lambda: len(servo) == 4)
            assert np.allclose(servo[3].position, q_cp, atol=1e-6) and servo[3].follow
            bridge.tick()
            assert wait_until(lambda: bool(buttons) and buttons[-1].clutch and buttons[-1].operator_present)
            time.sleep(0.15)
            bridge.tick()  # the console has been silent > servo_timeout_ms: disengaged, absent
            assert wait_until(lambda: not buttons[-1].clutch and not buttons[-1].operator_present)
            sub.undeclare()
        finally:
            bridge.close()
            ros.close()  # type: ignore[no-untyped-call]
