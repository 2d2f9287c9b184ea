"""An independent ROS 2-over-zenoh client, as an rmw_zenoh node would behave, for the bridge tests.

It shares no code with the bridge (nothing of ``telesurg`` is imported): CDR through pycdr2 (the
bridge uses rosbags), the rmw_zenoh key expressions, attachment and liveliness tokens written
here from rmw_zenoh's design (ros2/rmw_zenoh docs/design.md), and the type hashes of ROS 2 Jazzy
as constants. It runs in its own process::

    python tests/ros2_client.py --connect tcp/127.0.0.1:7447 --arm arm1

and talks to the test over stdin / stdout, one JSON object per line. Out: ``{"ready": …}`` once
it found the bridge's ``servo_jp`` subscription in the liveliness graph and received a
``measured_js``; ``{"js": stamp_ns, "pos": […], "att_seq": n}`` for every ``js_every``-th
``measured_js``; ``{"sent": n, "q": […]}`` once a second. In (commands): ``enable`` /
``disable`` (a ``state_command``), ``sync`` (stand where the arm is), ``target J DQ`` (joint J
moves to its start + DQ rad, at ``speed`` rad/s, streamed as ``servo_jp`` at 100 Hz), ``bad KIND``
(one invalid ``servo_jp``: ``count``, ``nan``, ``limit``, ``cdr``), ``quit``.
"""

import argparse
import json
import math
import os
import struct
import sys
import threading
import time
from dataclasses import dataclass

import zenoh
from pycdr2 import IdlStruct
from pycdr2.types import float64, int32, sequence, uint32

#: REP-2016 type hashes of ROS 2 Jazzy (``ros2 interface``; what rmw_zenoh puts in every key)
JOINT_STATE_HASH = "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
JOINT_STATE_DDS = "sensor_msgs::msg::dds_::JointState_"
STRING_STAMPED_DDS = "crtk_msgs::msg::dds_::StringStamped_"


@dataclass
class Time(IdlStruct, typename="builtin_interfaces/msg/Time"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs/msg/Header"):
    stamp: Time
    frame_id: str


@dataclass
class JointState(IdlStruct, typename="sensor_msgs/msg/JointState"):
    header: Header
    name: sequence[str]
    position: sequence[float64]
    velocity: sequence[float64]
    effort: sequence[float64]


@dataclass
class StringStamped(IdlStruct, typename="crtk_msgs/msg/StringStamped"):
    header: Header
    string: str


def header(frame: str = "") -> Header:
    t = time.time_ns()
    return Header(Time(t // 1_000_000_000, t % 1_000_000_000), frame)


def attachment(seq: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment: int64 sequence number, int64 source timestamp, length + 16-byte GID."""
    return struct.pack("<qqB", seq, time.time_ns(), len(gid)) + gid


def parse_attachment(raw: bytes) -> tuple[int, int, bytes]:
    seq, ts, n = struct.unpack_from("<qqB", raw)
    if n != 16 or len(raw) != 17 + n:
        raise ValueError(f"attachment of {len(raw)} bytes, gid length {n}")
    return seq, ts, raw[17:]


def emit(obj: object) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


class Client:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        # pycdr2 builds each type's (de)serializer on first use: build them here, on one thread
        JointState.deserialize(JointState(header(), ["a"], [0.0], [], []).serialize())
        StringStamped.deserialize(StringStamped(header(), "").serialize())
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.domain, self.arm = args.domain, args.arm
        self.lock = threading.Lock()
        self.tx_lock = threading.Lock()
        self.q0: list[float] | None = None
        self.q_meas: list[float] = []  # the newest measured_js
        self.names: list[str] = []
        self.offset = [0.0] * 32
        self.target = [0.0] * 32
        self.n_js = 0
        self.sent = 0
        self.seq = 0
        self.gid = os.urandom(16)
        zid = str(self.session.info.zid())
        node = f"@ros2_lv/{self.domain}/{zid}/0/0/NN/%/%/crtk_console"
        self.tokens = [self.session.liveliness().declare_token(node)]
        self.servo_key = f"{self.domain}/{self.arm}/servo_jp/{JOINT_STATE_DDS}/{JOINT_STATE_HASH}"
        js_key = f"{self.domain}/{self.arm}/measured_js/{JOINT_STATE_DDS}/{JOINT_STATE_HASH}"
        qos = "::,10:,:,:,,"
        for eid, kind, topic, dds in (
            (1, "MS", "measured_js", JOINT_STATE_DDS),
            (2, "MP", "servo_jp", JOINT_STATE_DDS),
        ):
            tok = (
                f"@ros2_lv/{self.domain}/{zid}/0/{eid}/{kind}/%/%/crtk_console/%{self.arm}%{topic}/{dds}/"
                f"{JOINT_STATE_HASH}/{qos}"
            )
            self.tokens.append(self.session.liveliness().declare_token(tok))
        self.sub = self.session.declare_subscriber(js_key, self.on_js)
        self.servo = self.session.declare_publisher(self.servo_key)
        self.command_pub = None

    def discover(self, timeout: float = 80.0) -> dict[str, str]:
        """The bridge's endpoints from the liveliness graph: topic → token."""
        deadline = time.monotonic() + timeout
        found: dict[str, str] = {}
        while time.monotonic() < deadline:
            for reply in self.session.liveliness().get(f"@ros2_lv/{self.domain}/**", timeout=2.0):
                if reply.ok is None:
                    continue
                parts = str(reply.ok.key_expr).split("/")
                # @ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<ns>/<node>/<topic>/<type>/<hash>/<qos>
                if len(parts) == 13 and parts[8] != "crtk_console":
                    found[f"{parts[5]} {parts[9]}"] = str(reply.ok.key_expr)
            if f"MS %{self.arm}%servo_jp" in found and f"MS %{self.arm}%state_command" in found:
                return found
            time.sleep(0.2)
        raise SystemExit(f"no bridge found in the liveliness graph: {sorted(found)}")

    def on_js(self, sample: zenoh.Sample) -> None:
        att = parse_attachment(sample.attachment.to_bytes()) if sample.attachment is not None else None
        m = JointState.deserialize(sample.payload.to_bytes())
        stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        with self.lock:
            if self.q0 is None:
                self.q0 = list(m.position)
                self.names = list(m.name)
            self.q_meas = list(m.position)
            self.n_js += 1
            n = self.n_js
        if n % self.args.js_every == 1:
            emit({"js": stamp, "pos": list(m.position), "att_seq": att[0] if att else None})

    def put_servo(self, names: list[str], q: list[float], raw: bytes | None = None) -> None:
        with self.tx_lock:  # (pycdr2 serializes into a buffer per type: one thread at a time)
            self.seq += 1
            payload = raw if raw is not None else JointState(header(), names, q, [], []).serialize()
            self.servo.put(payload, attachment=attachment(self.seq, self.gid))

    def state_command(self, text: str, hash_: str) -> None:
        if self.command_pub is None:
            key = f"{self.domain}/{self.arm}/state_command/{STRING_STAMPED_DDS}/{hash_}"
            self.command_pub = self.session.declare_publisher(key)
            time.sleep(0.2)
        with self.tx_lock:
            self.seq += 1
            payload = StringStamped(header(), text).serialize()
            self.command_pub.put(payload, attachment=attachment(self.seq, self.gid))

    def stream(self, stop: threading.Event) -> None:
        """servo_jp at 100 Hz: the start pose + offsets moving toward their targets."""
        period, step = 0.01, self.args.speed * 0.01
        next_t = time.monotonic()
        last_report = 0.0
        while not stop.is_set():
            with self.lock:
                q0 = self.q0
                for j in range(len(self.offset)):
                    d = self.target[j] - self.offset[j]
                    self.offset[j] += max(-step, min(step, d))
                q = None if q0 is None else [v + self.offset[j] for j, v in enumerate(q0)]
            if q is not None:
                self.put_servo(self.names, q)
                self.sent += 1
                if time.monotonic() - last_report > 1.0:
                    last_report = time.monotonic()
                    emit({"sent": self.sent, "q": q})
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))

    def bad(self, kind: str) -> None:
        with self.lock:
            q0, names = list(self.q0 or []), list(self.names)
        if kind == "count":
            self.put_servo(names[:-1], q0[:-1])
        elif kind == "nan":
            self.put_servo(names, [math.nan, *q0[1:]])
        elif kind == "limit":
            self.put_servo(names, [q0[0] + 10.0, *q0[1:]])
        elif kind == "cdr":
            self.put_servo(names, q0, raw=b"\x00\x01\x00\x00\xff\xff")


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--connect", required=True)
    p.add_argument("--domain", type=int, default=0)
    p.add_argument("--arm", default="arm1")
    p.add_argument("--speed", type=float, default=0.2, help="rad/s toward a target")
    p.add_argument("--js-every", type=int, default=5)
    args = p.parse_args()
    c = Client(args)
    found = c.discover()
    servo_token = found[f"MS %{args.arm}%servo_jp"]
    if servo_token.split("/")[10:12] != [JOINT_STATE_DDS, JOINT_STATE_HASH]:
        raise SystemExit(f"the bridge's servo_jp is not a Jazzy sensor_msgs/JointState: {servo_token}")
    command_hash = found[f"MS %{args.arm}%state_command"].split("/")[11]
    deadline = time.monotonic() + 60
    while c.q0 is None and time.monotonic() < deadline:  # (the site's measured_js, through the bridge)
        time.sleep(0.05)
    if c.q0 is None:
        raise SystemExit("no measured_js from the bridge")
    emit({"ready": sorted(found), "q0": c.q0, "names": c.names})
    stop = threading.Event()
    threading.Thread(target=c.stream, args=(stop,), daemon=True).start()
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        if words[0] in ("enable", "disable"):
            c.state_command(words[0], command_hash)
        elif words[0] == "target":
            with c.lock:
                c.target[int(words[1])] = float(words[2])
        elif words[0] == "sync":  # stand where the arm is (before engaging again after a hold)
            with c.lock:
                assert c.q0 is not None
                for j, (v, v0) in enumerate(zip(c.q_meas, c.q0, strict=True)):
                    c.offset[j] = c.target[j] = v - v0
        elif words[0] == "bad":
            c.bad(words[1])
        elif words[0] == "quit":
            break
        emit({"ok": line.strip()})
    stop.set()
    c.session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
