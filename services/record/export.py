"""``telesurg export``: a recording in encodings other tools read (Foxglove, ROS 2, rerun).

``telesurg record`` stores the site's messages byte for byte (MessagePack, ``services/record``).
Foxglove and rerun's MCAP importer do not read MessagePack; this tool writes a second file with
well-known schemas:

* ``--to foxglove OUT.mcap`` — Foxglove's protobuf schemas, written with the Foxglove SDK
  (``foxglove-sdk``): joint states (``foxglove.JointStates``, plottable per joint; also as ROS 2
  ``sensor_msgs/msg/JointState`` in CDR on ``…/joint_state``, which rerun turns into plots),
  poses (``foxglove.PoseInFrame``), the arm's frame transforms on ``/tf``
  (``foxglove.FrameTransforms``: forward kinematics of the measured joints through the robot's
  MuJoCo model, one frame per body), the robot itself on ``/robot_description`` (a URDF made
  from the same MuJoCo model: ROS 2 ``std_msgs/msg/String``, the topic Foxglove's 3D panel and
  rerun's URDF decoder read), the endoscope video (``foxglove.CompressedImage``, the JPEG frames
  as recorded) and events and state changes (``foxglove.Log``).
* ``--to rerun OUT.rrd`` — the mirror's own drawing (what ``telesurg replay --to-rerun`` does).
* ``--to lerobot OUT/`` — one or more recordings as a LeRobotDataset v3.0 for robot learning
  (:mod:`.lerobot`: an episode per engaged period, resampled at ``--fps``).

Example::

    telesurg record --out run.mcap --seconds 10
    telesurg export run.mcap --to foxglove run.foxglove.mcap
    rerun run.foxglove.mcap                       # or open it in Foxglove
    telesurg export run.mcap --to rerun run.rrd
    telesurg export run.mcap run2.mcap --to lerobot dataset/ --fps 30

Only the messages of the mirror's trusted sources are exported on ``master/``, ``slave/`` and
``safety/`` keys, as the mirror draws them; undecodable payloads are counted and skipped.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.services.record import iter_decoded, open_mcap, read_metadata, recording_site, written_whole
from telesurg.shared import robots
from telesurg.shared.errors import ConfigError
from telesurg.shared.keys import Keys
from telesurg.shared.messages import (
    CameraImage,
    CartesianPose,
    JointSetpoint,
    JointState,
    Message,
    OperatingState,
    SafetyEvent,
    SafetyState,
)

log = logging.getLogger("telesurg.export")

TARGETS = ("foxglove", "rerun", "lerobot")
#: the world frame of the exported transforms and slave poses (the MuJoCo scene's world)
WORLD = "world"
#: ROS 2 type store of the CDR messages (std_msgs/String, sensor_msgs/JointState)
ROS2_STORE = "ros2_jazzy"
#: MuJoCo geom groups drawn (the viewer's defaults)
VISIBLE_GROUPS = (0, 1, 2)


# --------------------------------------------------------------------------- robot model


def _rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF roll-pitch-yaw (fixed axes x, y, z) of a rotation matrix."""
    pitch = math.asin(max(-1.0, min(1.0, -float(R[2, 0]))))
    if abs(R[2, 0]) < 1.0 - 1e-9:
        roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
        yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    else:  # gimbal lock: yaw carries the rest
        roll = 0.0
        yaw = math.atan2(-float(R[0, 1]), float(R[1, 1]))
    return roll, pitch, yaw


def _f(*v: float) -> str:
    return " ".join(f"{x:.6g}" for x in v)


class RobotModel:
    """One robot's MuJoCo scene: body frames at given joints, and a URDF of its visual geoms.

    Frame names are the MuJoCo body names (``world`` for the world body, ``body<i>`` for an
    unnamed one). Joint values are set per arm through the registry's ``model_joints``.
    """

    def __init__(self, spec: robots.RobotSpec, arm_ids: Sequence[str]) -> None:
        import mujoco

        self._mj = mujoco
        self.spec = spec
        self.model = mujoco.MjModel.from_xml_path(str(spec.scene))
        self.data = mujoco.MjData(self.model)
        mujoco.mj_kinematics(self.model, self.data)
        self.names = [self._body_name(b) for b in range(self.model.nbody)]
        self.qadr: dict[str, list[int]] = {}
        for arm in arm_ids:
            try:
                profile = robots.arm_profile(spec.name, arm)
            except ConfigError:  # an arm id the model does not have: no frames for it
                continue
            adr = []
            for jn in profile.model_joints:
                jid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, jn)
                adr.append(int(self.model.jnt_qposadr[jid]))
            self.qadr[arm] = adr

    def _body_name(self, b: int) -> str:
        if b == 0:
            return WORLD
        return self.model.body(b).name or f"body{b}"

    def set_joints(self, arm: str, q: Sequence[float]) -> bool:
        """Put an arm's joints (message order) into the model; False if the arm is unknown."""
        adr = self.qadr.get(arm)
        if adr is None or len(adr) != len(q):
            return False
        self.data.qpos[adr] = q
        self._mj.mj_kinematics(self.model, self.data)
        return True

    def relative_poses(self) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
        """``(parent, child, translation (3,), quaternion w x y z (4,))`` of every body."""
        out = []
        mj = self._mj
        for b in range(1, self.model.nbody):
            p = int(self.model.body_parentid[b])
            pos_p, quat_p = self.data.xpos[p], self.data.xquat[p]
            inv = np.zeros(4)
            mj.mju_negQuat(inv, quat_p)
            rel_q = np.zeros(4)
            mj.mju_mulQuat(rel_q, inv, self.data.xquat[b])
            rel_p = np.zeros(3)
            mj.mju_rotVecQuat(rel_p, self.data.xpos[b] - pos_p, inv)
            out.append((self.names[p], self.names[b], rel_p, rel_q))
        return out

    def urdf(self) -> str:
        """A URDF of the scene's bodies and visible primitive geoms (planes and meshes left out).

        Every body is a link; each is attached to its parent by a joint at its rest pose (hinge →
        revolute, slide → prismatic, with the joint's axis and range; else fixed). The motion
        comes from ``/tf``.
        """
        mj, m = self._mj, self.model
        robot = ET.Element("robot", name=self.spec.name)
        for b in range(m.nbody):
            link = ET.SubElement(robot, "link", name=self.names[b])
            for g in range(m.ngeom):
                if int(m.geom_bodyid[g]) != b or int(m.geom_group[g]) not in VISIBLE_GROUPS:
                    continue
                self._visual(link, g)
            if b == 0:
                continue
            kind, axis, limit = "fixed", None, None
            if int(m.body_jntnum[b]) == 1:
                j = int(m.body_jntadr[b])
                jt = int(m.jnt_type[j])
                if jt in (int(mj.mjtJoint.mjJNT_HINGE), int(mj.mjtJoint.mjJNT_SLIDE)):
                    kind = "revolute" if jt == int(mj.mjtJoint.mjJNT_HINGE) else "prismatic"
                    axis = m.jnt_axis[j]
                    lo, hi = m.jnt_range[j] if m.jnt_limited[j] else (-math.pi, math.pi)
                    limit = (float(lo), float(hi))
            joint = ET.SubElement(robot, "joint", name=f"{self.names[b]}_joint", type=kind)
            ET.SubElement(joint, "parent", link=self.names[int(m.body_parentid[b])])
            ET.SubElement(joint, "child", link=self.names[b])
            R = np.zeros(9)
            mj.mju_quat2Mat(R, m.body_quat[b])
            ET.SubElement(joint, "origin", xyz=_f(*m.body_pos[b]), rpy=_f(*_rpy(R.reshape(3, 3))))
            if axis is not None and limit is not None:
                ET.SubElement(joint, "axis", xyz=_f(*axis))
                ET.SubElement(
                    joint, "limit", lower=_f(limit[0]), upper=_f(limit[1]), effort="0", velocity="0"
                )
        ET.indent(robot)
        return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"

    def _visual(self, link: ET.Element, g: int) -> None:
        mj, m = self._mj, self.model
        t = int(m.geom_type[g])
        size = m.geom_size[g]
        rgba = m.mat_rgba[m.geom_matid[g]] if int(m.geom_matid[g]) >= 0 else m.geom_rgba[g]
        if rgba[3] <= 0.0:
            return
        R = np.zeros(9)
        mj.mju_quat2Mat(R, m.geom_quat[g])
        R3 = R.reshape(3, 3)
        shapes: list[tuple[str, dict[str, str], np.ndarray]] = []
        pos = np.asarray(m.geom_pos[g], dtype=float)
        G = mj.mjtGeom
        if t == int(G.mjGEOM_SPHERE):
            shapes.append(("sphere", {"radius": _f(size[0])}, pos))
        elif t == int(G.mjGEOM_BOX):
            shapes.append(("box", {"size": _f(*(2 * size[:3]))}, pos))
        elif t == int(G.mjGEOM_CYLINDER):
            shapes.append(("cylinder", {"radius": _f(size[0]), "length": _f(2 * size[1])}, pos))
        elif t == int(G.mjGEOM_CAPSULE):  # a cylinder and its two end spheres
            shapes.append(("cylinder", {"radius": _f(size[0]), "length": _f(2 * size[1])}, pos))
            for s in (-1.0, 1.0):
                shapes.append(("sphere", {"radius": _f(size[0])}, pos + R3[:, 2] * s * size[1]))
        elif t == int(G.mjGEOM_ELLIPSOID):  # a box around it
            shapes.append(("box", {"size": _f(*(2 * size[:3]))}, pos))
        for shape, attrs, p in shapes:
            visual = ET.SubElement(link, "visual", name=f"geom{g}")
            ET.SubElement(visual, "origin", xyz=_f(*p), rpy=_f(*_rpy(R3)))
            ET.SubElement(ET.SubElement(visual, "geometry"), shape, attrs)
            mat = ET.SubElement(visual, "material", name=f"geom{g}")
            ET.SubElement(mat, "color", rgba=_f(*rgba))


# --------------------------------------------------------------------------- foxglove


@dataclass
class ExportCounts:
    """What an export wrote and skipped."""

    messages: int = 0
    undecodable: int = 0
    untrusted: int = 0
    skipped: int = 0
    written: dict[str, int] = field(default_factory=dict)
    robot: str = ""

    def add(self, topic: str) -> None:
        self.written[topic] = self.written.get(topic, 0) + 1

    def as_dict(self) -> dict[str, Any]:
        return {
            "messages": self.messages,
            "undecodable": self.undecodable,
            "untrusted": self.untrusted,
            "skipped": self.skipped,
            "robot": self.robot,
            "written": dict(sorted(self.written.items())),
        }


def _arms_and_robot(
    path: Path, prefix: str, trusted: frozenset[str]
) -> tuple[dict[str, tuple[str, ...]], Any]:
    """The arms of a recording (joint names of their first trusted ``measured_js``) and the robot."""
    arms: dict[str, tuple[str, ...]] = {}
    with open_mcap(path) as reader:
        for topic, _lt, _pt, _d, msg in iter_decoded(reader, lambda t: t.endswith("/measured_js")):
            if not isinstance(msg, JointState) or msg.header.source not in trusted:
                continue
            parts = topic[len(prefix) :].split("/")
            if len(parts) == 3 and parts[0] == "slave" and parts[1] not in arms:
                arms[parts[1]] = msg.names
    spec = None
    for arm, names in arms.items():
        found = robots.recognise(arm, names)
        if found is not None:
            spec = found[0]
            break
        log.warning("arm %s: joint names %s match no registered robot: no frames or model", arm, names)
    return arms, spec


def to_foxglove(path: str | Path, out: str | Path, *, overwrite: bool = True) -> dict[str, Any]:
    """Write ``out`` (MCAP, Foxglove protobuf schemas + ROS 2 CDR) from a recording; counts."""
    import foxglove
    from foxglove import channels as fc
    from foxglove import messages as fm
    from rosbags.typesys import Stores, get_typestore
    from telesurg.services.mirror import MirrorConfig

    path, out = Path(path), Path(out)
    trusted = frozenset(MirrorConfig().trusted_sources)
    store = get_typestore(Stores(ROS2_STORE))
    counts = ExportCounts()
    with open_mcap(path) as reader:
        site = recording_site(reader)
        meta = read_metadata(reader, "telesurg.recording")
    prefix = Keys(site).prefix + "/"
    arms, spec = _arms_and_robot(path, prefix, trusted)
    model = RobotModel(spec, list(arms)) if spec is not None else None
    counts.robot = spec.name if spec is not None else ""

    def ts(ns: int) -> Any:
        return fm.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)

    def ros_time(ns: int) -> Any:
        Time = store.types["builtin_interfaces/msg/Time"]
        return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    ctx = foxglove.Context()
    out.parent.mkdir(parents=True, exist_ok=True)
    chans: dict[str, Any] = {}

    def channel(topic: str, make: Any) -> Any:
        if topic not in chans:
            chans[topic] = make(topic)
        return chans[topic]

    def ros2_channel(topic: str, typename: str) -> Any:
        def make(t: str) -> Any:
            msgdef, _digest = store.generate_msgdef(typename, ros_version=2)
            schema = foxglove.Schema(name=typename, encoding="ros2msg", data=msgdef.encode())
            return foxglove.Channel(t, schema=schema, message_encoding="cdr", context=ctx)

        return channel(topic, make)

    def ros2_log(topic: str, typename: str, msg: Any, log_ns: int) -> None:
        ros2_channel(topic, typename).log(bytes(store.serialize_cdr(msg, typename)), log_time=log_ns)
        counts.add(topic)

    def log_to(topic: str, make: Any, msg: Any, log_ns: int) -> None:
        channel(topic, lambda t: make(t, context=ctx)).log(msg, log_time=log_ns)
        counts.add(topic)

    last_state: dict[str, tuple[Any, ...]] = {}
    level = {"info": fm.LogLevel.Info, "warning": fm.LogLevel.Warning, "error": fm.LogLevel.Error}
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists")
    with written_whole(out) as part, foxglove.open_mcap(part, allow_overwrite=True, context=ctx) as writer:
        writer.write_metadata("telesurg.export", {"source": str(path), "site": site, "robot": counts.robot})
        if meta:
            writer.write_metadata("telesurg.recording", meta)
        first = True
        with open_mcap(path) as reader:
            for topic, lt, _pt, _data, msg in iter_decoded(reader):
                counts.messages += 1
                if msg is None:
                    counts.undecodable += 1
                    continue
                rel = topic[len(prefix) :] if topic.startswith(prefix) else topic
                role = rel.split("/", 1)[0]
                if role in ("master", "slave", "safety") and msg.header.source not in trusted:
                    counts.untrusted += 1
                    continue
                if first and model is not None:  # the robot, once, at the start
                    String = store.types["std_msgs/msg/String"]
                    ros2_log("/robot_description", "std_msgs/msg/String", String(data=model.urdf()), lt)
                    first = False
                if not _export_one(
                    rel, lt, msg, model, fm, fc, ts, ros_time, store, ros2_log, log_to, level, last_state
                ):
                    counts.skipped += 1
    log.info("wrote %s: %d messages read, %d written", out, counts.messages, sum(counts.written.values()))
    return counts.as_dict()


def _export_one(
    rel: str,
    lt: int,
    msg: Message,
    model: RobotModel | None,
    fm: Any,
    fc: Any,
    ts: Any,
    ros_time: Any,
    store: Any,
    ros2_log: Any,
    log_to: Any,
    level: dict[str, Any],
    last_state: dict[str, tuple[Any, ...]],
) -> bool:
    """Write one message's exported forms; False if it has none."""
    stamp = msg.header.stamp_ns
    parts = rel.split("/")
    topic = "/" + rel
    if isinstance(msg, JointState | JointSetpoint):
        n = len(msg.names)
        vel = getattr(msg, "velocity", ()) or (0.0,) * n
        eff = getattr(msg, "effort", ()) or (0.0,) * n
        joints = [
            fm.JointState(name=nm, position=float(p), velocity=float(v), effort=float(e))
            for nm, p, v, e in zip(msg.names, msg.position, vel, eff, strict=False)
        ]
        log_to(topic, fc.JointStatesChannel, fm.JointStates(timestamp=ts(stamp), joints=joints), lt)
        JS = store.types["sensor_msgs/msg/JointState"]
        Header = store.types["std_msgs/msg/Header"]
        ros = JS(
            header=Header(stamp=ros_time(stamp), frame_id=""),
            name=list(msg.names),
            position=np.asarray(msg.position, dtype=np.float64),
            velocity=np.asarray(getattr(msg, "velocity", ()), dtype=np.float64),
            effort=np.asarray(getattr(msg, "effort", ()), dtype=np.float64),
        )
        ros2_log(topic + "/joint_state", "sensor_msgs/msg/JointState", ros, lt)
        if (
            isinstance(msg, JointState)
            and model is not None
            and len(parts) == 3
            and parts[0] == "slave"
            and parts[2] == "measured_js"
            and model.set_joints(parts[1], msg.position)
        ):
            tfs = [
                fm.FrameTransform(
                    timestamp=ts(stamp),
                    parent_frame_id=parent,
                    child_frame_id=child,
                    translation=fm.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                    rotation=fm.Quaternion(x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])),
                )
                for parent, child, p, q in model.relative_poses()
            ]
            log_to("/tf", fc.FrameTransformsChannel, fm.FrameTransforms(transforms=tfs), lt)
        return True
    if isinstance(msg, CartesianPose):
        frame = WORLD if parts[0] in ("slave", "camera") else msg.frame
        w, x, y, z = msg.orientation
        pose = fm.Pose(
            position=fm.Vector3(x=msg.position[0], y=msg.position[1], z=msg.position[2]),
            orientation=fm.Quaternion(x=x, y=y, z=z, w=w),
        )
        log_to(
            topic, fc.PoseInFrameChannel, fm.PoseInFrame(timestamp=ts(stamp), frame_id=frame, pose=pose), lt
        )
        return True
    if isinstance(msg, CameraImage):
        fmt = "jpeg" if msg.encoding == "jpeg" else msg.encoding
        img = fm.CompressedImage(
            timestamp=ts(msg.capture_ns or stamp), frame_id=f"camera_{msg.camera}", data=msg.data, format=fmt
        )
        log_to(topic, fc.CompressedImageChannel, img, lt)
        return True
    if isinstance(msg, SafetyEvent):
        text = f"[{msg.kind}] {msg.arm + ': ' if msg.arm else ''}{msg.text}"
        entry = fm.Log(
            timestamp=ts(stamp),
            level=level.get(msg.severity, fm.LogLevel.Info),
            message=text,
            name=msg.header.source,
            file="",
            line=0,
        )
        log_to("/events", fc.LogChannel, entry, lt)
        return True
    if isinstance(msg, OperatingState | SafetyState):  # changes only, as text
        key = (
            msg.state,
            getattr(msg, "control_mode", ""),
            getattr(msg, "follow", None),
            getattr(msg, "reason", ""),
            tuple(getattr(msg, "causes", ())),
        )
        if last_state.get(rel) == key:
            return True
        last_state[rel] = key
        if isinstance(msg, SafetyState):
            text = f"{msg.arm}: {msg.state}" + (f" ({'; '.join(msg.causes)})" if msg.causes else "")
            lvl = fm.LogLevel.Info if msg.state == "OK" else fm.LogLevel.Warning
        else:
            text = f"{msg.state} {msg.control_mode} follow={msg.follow}" + (
                f" ({msg.reason})" if msg.reason else ""
            )
            lvl = fm.LogLevel.Info
        log_to(
            topic,
            fc.LogChannel,
            fm.Log(timestamp=ts(stamp), level=lvl, message=text, name=msg.header.source, file="", line=0),
            lt,
        )
        return True
    return False


# --------------------------------------------------------------------------- CLI


def parser() -> argparse.ArgumentParser:
    """Command-line flags of ``telesurg export``."""
    p = argparse.ArgumentParser(
        prog="telesurg export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "file",
        metavar="FILE.mcap",
        nargs="+",
        help="recording made with telesurg record (several for --to lerobot: one dataset)",
    )
    p.add_argument(
        "--to",
        required=True,
        choices=TARGETS,
        help="foxglove (MCAP, well-known schemas), rerun (.rrd) or lerobot (a LeRobotDataset v3.0 folder)",
    )
    p.add_argument("out", metavar="OUT", help="file to write (.mcap, .rrd), or the dataset's new folder")
    p.add_argument("--fps", type=float, default=30.0, help="lerobot: frames a second (default 30)")
    p.add_argument(
        "--camera",
        action="append",
        metavar="CAM",
        help="lerobot: a camera to export as video (repeatable; default: every recorded camera)",
    )
    p.add_argument("--no-video", action="store_true", help="lerobot: no camera videos")
    p.add_argument("--task", default="", help="lerobot: the episodes' task text")
    p.add_argument("--arm", default=None, help="lerobot: the slave arm (default: the first recorded)")
    p.add_argument("--json", metavar="FILE", help="also write the counts as JSON")
    p.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    return p


#: the flags of parser() that take no value
FLAGS = frozenset({"--no-video", "-h", "--help"})


def _positionals_first(argv: list[str]) -> list[str]:
    """``argv`` with the recordings and OUT first (``A.mcap B.mcap --to lerobot OUT`` as
    ``A.mcap B.mcap OUT --to lerobot``): argparse gives a ``+`` positional only the words before
    the first option."""
    pos: list[str] = []
    opts: list[str] = []
    it = iter(argv)
    for a in it:
        if a == "--":
            pos.extend(it)
        elif a.startswith("-") and a not in FLAGS and "=" not in a:
            opts.extend((a, next(it, "")))
        elif a.startswith("-"):
            opts.append(a)
        else:
            pos.append(a)
    return pos + opts


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; 0 on success, 1 on bad input (one line on stderr, nothing written), 2 on bad flags."""
    p = parser()
    args = p.parse_args(_positionals_first(sys.argv[1:] if argv is None else list(argv)))
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    srcs = [Path(f) for f in args.file]
    out = Path(args.out)
    if args.to != "lerobot" and len(srcs) > 1:
        p.error(f"--to {args.to} converts one recording (several only for --to lerobot)")
    for src in srcs:
        if not src.is_file():
            print(f"telesurg export: no such recording: {src}", file=sys.stderr)
            return 1
    src = srcs[0]
    try:  # (each writes OUT whole or not at all)
        if args.to == "foxglove":
            counts: dict[str, Any] = to_foxglove(src, out)
        elif args.to == "rerun":
            from telesurg.services.record.replay import to_rerun

            counts = dict(to_rerun(src, out))
        else:
            from telesurg.services.record.lerobot import DEFAULT_TASK, DatasetError, to_lerobot

            try:
                counts = to_lerobot(
                    srcs,
                    out,
                    fps=args.fps,
                    cameras=[] if args.no_video else args.camera,
                    task=args.task or DEFAULT_TASK,
                    arm=args.arm,
                )
            except DatasetError as e:
                print(f"telesurg export: {e} ({out} not written)", file=sys.stderr)
                return 1
    except Exception as e:  # a damaged file: say which and why
        print(
            f"telesurg export: cannot export {src}: {type(e).__name__}: {e} ({out} not written)",
            file=sys.stderr,
        )
        return 1
    if args.json:
        from telesurg.shared import jsonio

        jsonio.write(args.json, counts)
    written = counts.get("written")
    summary = ", ".join(f"{k} {v}" for k, v in (written or counts).items())
    print(f"wrote {args.out}: {summary}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
