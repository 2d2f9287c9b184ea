"""ros2_bridge: one slave arm's CRTK topics for ROS 2 nodes running rmw_zenoh, on the site's router.

Out (telesurg → ROS 2, one ROS 2 message per telesurg message, stamped with its source time):
``/<arm>/measured_js``, ``/<arm>/setpoint_js`` (``sensor_msgs/JointState``), ``/<arm>/measured_cp``
(``geometry_msgs/PoseStamped``, frame ``base``), ``/<arm>/operating_state``
(``crtk_msgs/OperatingState``). In (ROS 2 → telesurg, with ``control``): ``/<arm>/servo_jp``
(``sensor_msgs/JointState``), ``/<arm>/servo_cp`` (``geometry_msgs/PoseStamped``, IK to joints),
``/<arm>/state_command`` (``crtk_msgs/StringStamped``: ``enable`` / ``disable``). Wire format:
:mod:`telesurg.services.bridge.rmw`; types and CDR: :mod:`telesurg.services.bridge.crtk`.

A ROS 2 console takes the place of the master and the mapping for its arm: the bridge is an
authenticated identity of the site keyring (service id ``ros2_bridge``) and publishes what they
would — ``slave/<arm>/servo_jp`` (one per accepted ROS 2 command, ``follow`` while engaged),
``master/<m>/measured_cp`` (the commanded tip pose, with each setpoint) and ``master/<m>/buttons``
(clutch = engaged, operator present = the console's stream is fresh; ``buttons_hz``) — so the
watchdog judges the console's stream exactly as a master's: a silent console is a stale stream →
HOLD, and the slave moves only under the watchdog's lease. The site names the bridge as the
source of those streams (``deploy/local/ros2.toml``, docs/ros2.md). Every inbound message is
checked first (:mod:`telesurg.services.bridge.gate`); a malformed or refused one is counted,
logged and dropped.

Example::

    telesurg bridge ros2 --arm arm1 --domain 0 --connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from telesurg.services.bridge import crtk, rmw
from telesurg.services.bridge.gate import Console, Rejected, check_joints, check_pose
from telesurg.services.common import service_main
from telesurg.shared.bus import BusConfig, Node, Outlet, only
from telesurg.shared.errors import ConfigError
from telesurg.shared.kinematics.transforms import quat_from_matrix
from telesurg.shared.messages import (
    CartesianPose,
    JointSetpoint,
    JointState,
    MasterButtons,
    OperatingState,
    now_ns,
)
from telesurg.shared.robots import ArmProfile, arm_profile

log = logging.getLogger(__name__)


@dataclass
class BridgeConfig:
    """ros2_bridge config."""

    site: str = "local"  # key prefix telesurg/<site>
    service: str = "ros2_bridge"  # instance id: its key in the site keyring, header src, liveliness
    arm: str = "arm1"  # the slave arm whose CRTK topics are bridged (/<arm>/...)
    model: str = "mh3f"  # slave robot model (shared/robots.py): joint names, limits, FK, IK
    # the master id the ROS 2 console stands in for: the bridge publishes master/<master>/buttons
    # and measured_cp, which the watchdog watches for the arm's pair "<master>:<arm>"
    master: str = "m1"
    domain: int = 0  # ROS_DOMAIN_ID of the ROS 2 nodes (first element of every rmw_zenoh key)
    node_name: str = "telesurg_bridge"  # the ROS 2 node name (root namespace) in `ros2 node list`
    control: bool = True  # accept servo_jp / servo_cp / state_command (false: publish only)
    # ms: the console's servo stream silent this long → not present, disengaged (enable again)
    servo_timeout_ms: float = 100.0
    # rad (m): while engaged, a servo command further than this from the previous one is refused
    # (the slave's own max_setpoint_step_rad refuses it too)
    max_step_rad: float = 0.1
    buttons_hz: float = 50.0  # Hz: master/<m>/buttons (the watchdog's buttons deadline is 200 ms)
    slave_source: str = "slave_control"  # only this service's slave streams are bridged out
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session (the site's router)

    def validate(self) -> None:
        """Raise ConfigError on inconsistent settings."""
        if not 0 <= self.domain <= 232:
            raise ConfigError(f"domain={self.domain} outside [0, 232] (ROS_DOMAIN_ID)")
        if self.servo_timeout_ms <= 0 or self.buttons_hz <= 0 or self.max_step_rad <= 0:
            raise ConfigError("servo_timeout_ms, buttons_hz and max_step_rad must be > 0")
        arm_profile(self.model, self.arm)


@dataclass
class RosPublisher:
    """One rmw_zenoh publisher: its key, GID and sequence number."""

    pub: Any
    typename: str
    gid: bytes = field(default_factory=rmw.new_gid)
    seq: itertools.count[int] = field(default_factory=lambda: itertools.count(1))

    def put(self, payload: bytes, stamp_ns: int) -> None:
        self.pub.put(payload, attachment=rmw.encode_attachment(next(self.seq), stamp_ns, self.gid))


class Bridge:
    """The bridge of one arm on an open node."""

    def __init__(self, cfg: BridgeConfig, node: Node, codec: crtk.Codec, profile: ArmProfile) -> None:
        self.cfg, self.node, self.codec, self.profile = cfg, node, codec, profile
        self.lock = threading.Lock()
        self.console = Console(cfg.servo_timeout_ms / 1e3)
        self.rejected: Counter[str] = Counter()
        self.forwarded = 0
        self.last_q: np.ndarray | None = None  # the last forwarded setpoint
        self.measured: np.ndarray = np.array(profile.home, dtype=np.float64)
        self.closed = False
        k, src = node.keys, only(cfg.slave_source)
        # the telesurg outlets first: a ROS 2 command may arrive as soon as its subscriber exists
        self.servo_out: Outlet | None = None
        self.master_cp: Outlet | None = None
        self.buttons: Outlet | None = None
        if cfg.control:
            self.servo_out = node.outlet(k.slave(cfg.arm, "servo_jp"))
            self.master_cp = node.outlet(k.master(cfg.master, "measured_cp"))
            self.buttons = node.outlet(k.master(cfg.master, "buttons"))
        s = node.session
        zid = str(s.info.zid())
        self.ros = rmw.RosNode(cfg.domain, zid, 0, cfg.node_name)
        self._handles: list[Any] = [s.liveliness().declare_token(self.ros.token())]
        self.pubs: dict[str, RosPublisher] = {}
        ids = itertools.count(1)
        for t in crtk.TOPICS:
            if t.inbound and not cfg.control:
                continue
            topic = f"/{cfg.arm}/{t.name}"
            h = codec.type_hash(t.typename)
            key = rmw.topic_key(cfg.domain, topic, t.typename, h)
            kind = "MS" if t.inbound else "MP"
            self._handles.append(
                s.liveliness().declare_token(self.ros.endpoint_token(next(ids), kind, topic, t.typename, h))
            )
            if t.inbound:
                self._handles.append(s.declare_subscriber(key, self._inbound(t)))
            else:
                pub = s.declare_publisher(key)
                self._handles.append(pub)
                self.pubs[t.name] = RosPublisher(pub, t.typename)
        node.subscribe(k.slave(cfg.arm, "measured_js"), JointState, self._on_js, sources=src)
        node.subscribe(k.slave(cfg.arm, "setpoint_js"), JointState, self._on_setpoint_js, sources=src)
        node.subscribe(k.slave(cfg.arm, "measured_cp"), CartesianPose, self._on_cp, sources=src)
        node.subscribe(k.slave(cfg.arm, "operating_state"), OperatingState, self._on_state, sources=src)
        log.info(
            "ROS 2 node /%s (domain %d, zenoh session %s): %s",
            cfg.node_name,
            cfg.domain,
            zid,
            ", ".join(f"/{cfg.arm}/{t.name}" for t in crtk.TOPICS if cfg.control or not t.inbound),
        )

    # -- telesurg → ROS 2 ------------------------------------------------------------------------
    def _on_js(self, m: JointState, key: str) -> None:
        with self.lock:
            self.measured = np.array(m.position, dtype=np.float64)
        self._out(
            "measured_js",
            self.codec.joint_state(m.header.stamp_ns, m.names, m.position, m.velocity, m.effort),
        )

    def _on_setpoint_js(self, m: JointState, key: str) -> None:
        self._out("setpoint_js", self.codec.joint_state(m.header.stamp_ns, m.names, m.position))

    def _on_cp(self, m: CartesianPose, key: str) -> None:
        self._out(
            "measured_cp", self.codec.pose_stamped(m.header.stamp_ns, m.frame, m.position, m.orientation)
        )

    def _on_state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            if self.console.on_slave(m.follow, m.reason):
                self._report_notes()
        self._out(
            "operating_state", self.codec.operating_state(m.header.stamp_ns, m.state, m.is_homed, m.is_busy)
        )

    def _out(self, name: str, msg: Any) -> None:
        if self.closed:
            return
        p = self.pubs[name]
        try:
            p.put(self.codec.encode(msg, p.typename), now_ns())
        except Exception:
            if not self.closed:  # (a publisher undeclared by close() under a late callback)
                raise

    # -- ROS 2 → telesurg ------------------------------------------------------------------------
    def _inbound(self, t: crtk.Topic) -> Callable[[Any], None]:
        handle = {
            "servo_jp": self._servo_jp,
            "servo_cp": self._servo_cp,
            "state_command": self._state_command,
        }[t.name]

        def on_sample(sample: Any) -> None:
            try:
                if sample.attachment is not None:
                    rmw.decode_attachment(sample.attachment.to_bytes())
                msg = self.codec.decode(sample.payload.to_bytes(), t.typename)
                with self.lock:
                    if self.closed:  # (a late sample while the bridge stops)
                        return
                    handle(msg)
            except (Rejected, ValueError) as exc:
                self._reject(t.name, str(exc))
            except Exception:  # a bug must not kill the zenoh callback thread; nothing was forwarded
                log.exception("ROS 2 %s handler failed (message dropped)", t.name)
                self._reject(t.name, "internal error")

        return on_sample

    def _servo_jp(self, msg: Any) -> None:
        names = tuple(str(n) for n in msg.name)
        position = tuple(float(v) for v in msg.position)
        self._forward(check_joints(self.profile, names, position, self._previous(), self.cfg.max_step_rad))

    def _servo_cp(self, msg: Any) -> None:
        p, o = msg.pose.position, msg.pose.orientation
        near = self.last_q if self.last_q is not None else self.measured
        q = check_pose(self.profile, str(msg.header.frame_id), (p.x, p.y, p.z), (o.x, o.y, o.z, o.w), near)
        self._forward(
            check_joints(self.profile, (), tuple(q.tolist()), self._previous(), self.cfg.max_step_rad)
        )

    def _previous(self) -> np.ndarray | None:
        """The setpoint a new one may not jump from: the last forwarded one while the slave
        follows this console (not before: the slave engages only near its measured joints)."""
        c = self.console
        return self.last_q if c.enabled and c.slave_followed and not c.edge else None

    def _state_command(self, msg: Any) -> None:
        text = str(msg.string)
        ok, why = self.console.command(text)
        self.node.event(
            "ros2_state_command",
            f"{text[:40]!r} {'accepted' if ok else 'refused'}: {why}",
            arm=self.cfg.arm,
            severity="info" if ok else "warning",
        )

    def _forward(self, q: np.ndarray) -> None:
        """One accepted setpoint: servo_jp (and the master's pose) out; caller holds the lock."""
        assert self.servo_out is not None and self.master_cp is not None
        follow, edge = self.console.on_servo(time.monotonic())
        names, pos = self.profile.joint_names, tuple(q.tolist())
        origin = now_ns()
        out = self.servo_out
        if edge:  # an engage: the slave follows on a false → true edge
            out.put(JointSetpoint(out.header(), names, pos, False, origin))
        out.put(JointSetpoint(out.header(), names, pos, follow, origin))
        T = self.profile.pose(q)
        quat = quat_from_matrix(T[:3, :3])
        cp = self.master_cp
        cp.put(
            CartesianPose(
                cp.header(),
                "base",
                (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])),
                (float(quat[0]), float(quat[1]), float(quat[2]), float(quat[3])),
            )
        )
        self.last_q = q
        self.forwarded += 1

    def _reject(self, topic: str, why: str) -> None:
        with self.lock:
            self.rejected[topic] += 1
            n = sum(self.rejected.values())
        if n <= 5 or n % 100 == 0:
            self.node.event(
                "ros2_rejected",
                f"/{self.cfg.arm}/{topic}: {why} ({n} rejected so far)",
                arm=self.cfg.arm,
                severity="warning",
            )

    def _report_notes(self) -> None:
        for note in self.console.notes:
            self.node.event(
                "disengage", f"ROS 2 console disengaged: {note}", arm=self.cfg.arm, severity="warning"
            )
        self.console.notes.clear()

    # -- the loop ---------------------------------------------------------------------------------
    def tick(self) -> None:
        """Buttons at ``buttons_hz``; disengage a silent console."""
        if self.buttons is None:
            return
        now = time.monotonic()
        with self.lock:
            if self.console.tick(now):
                self._report_notes()
            clutch, present = self.console.enabled, self.console.present(now)
        b = self.buttons
        b.put(MasterButtons(b.header(), clutch, present))

    def close(self) -> None:
        """Undeclare the ROS 2 side (tokens, publishers, subscribers); log the counts."""
        with self.lock:  # a handler running now finishes first; later ones see closed
            self.closed = True
        for h in reversed(self._handles):
            with contextlib.suppress(Exception):  # the session may be closing
                h.undeclare()
        log.info(
            "%s: %d setpoints forwarded, %d ROS 2 messages rejected %s",
            self.cfg.arm,
            self.forwarded,
            sum(self.rejected.values()),
            dict(self.rejected) or "",
        )


def run(cfg: BridgeConfig, stop: threading.Event) -> None:
    """Bridge until ``stop``."""
    cfg.validate()
    codec = crtk.Codec()
    profile = arm_profile(cfg.model, cfg.arm)
    with Node(cfg.bus, cfg.site, cfg.service) as node:
        bridge = Bridge(cfg, node, codec, profile)
        period = 1.0 / cfg.buttons_hz
        try:
            while not stop.wait(period):
                bridge.tick()
        finally:
            bridge.close()


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bridge ros2``."""
    return service_main("bridge ros2", BridgeConfig, run, argv, __doc__ or "")
