"""``telesurg export --to foxglove``: a live site's recording opened by the mcap reader and rerun.

One recording (module fixture) of a real site — router, watchdog, slave_control, mapping, camera
and, started after the recorder, master_capture — exported by the CLI as a user runs it. The
export is then read back twice: with the ``mcap`` reader and the Foxglove protobuf classes
(``foxglove-schemas-protobuf`` is not a dependency: the schemas are in the file, decoded here with
``google.protobuf`` from the file's own descriptor sets), and with rerun's MCAP importer
(``rerun mcap convert``), whose output ``.rrd`` is read with rerun's own reader.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from telesurg.services.record import iter_decoded, open_mcap
from telesurg.services.record.export import RobotModel, main
from telesurg.shared import robots
from telesurg.shared.messages import CameraImage, CartesianPose, JointState, OperatingState, SafetyEvent
from telesurg.tools.bench.harness import Pipeline

ROOT = Path(__file__).resolve().parents[1]
RERUN = Path(sys.executable).with_name("rerun")
ARM_BODIES = ("link1", "link2", "link3", "link4", "link5", "link6", "forceps")


def _wait_alive(p: Pipeline, service: str, timeout: float) -> bool:
    key = p.node.keys.alive(service)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(r.ok is not None for r in p.node.session.liveliness().get(key, timeout=0.5)):
            return True
        time.sleep(0.1)
    return False


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path]]:
    """(the recording, its Foxglove export) of an 8 s live session with the camera."""
    tmp = tmp_path_factory.mktemp("export")
    run, out = tmp / "run.mcap", tmp / "run.foxglove.mcap"
    argv = [sys.executable, "-m", "telesurg.services.cli", "record", "--out", str(run), "--seconds", "8"]
    with Pipeline(tmp / "logs", mirror=False, impair=False, master=False, probe=False, camera=True) as p:
        rec = subprocess.Popen(
            [*argv, "--connect", p.spec.endpoint],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            assert _wait_alive(p, "record", 30), "the recorder never came on the bus"
            p.site.restart("master_capture")
            text, _ = rec.communicate(timeout=90)
        finally:
            if rec.poll() is None:
                rec.send_signal(signal.SIGINT)
                rec.wait(15)
    print(text)
    assert rec.returncode == 0
    assert main([str(run), "--to", "foxglove", str(out)]) == 0
    yield run, out


def _foxglove_classes(reader: Any) -> dict[int, Any]:
    """schema id → protobuf message class, built from the FileDescriptorSet stored in the file."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    summary = reader.get_summary()
    out = {}
    for sid, schema in summary.schemas.items():
        if schema.encoding != "protobuf":
            continue
        fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
        pool = descriptor_pool.DescriptorPool()
        for fd in fds.file:
            pool.Add(fd)
        out[sid] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    return out


def _recorded(run: Path) -> dict[str, list[Any]]:
    got: dict[str, list[Any]] = {}
    with open_mcap(run) as reader:
        for topic, _lt, _pt, _d, msg in iter_decoded(reader):
            if msg is not None:
                got.setdefault(topic.split("/", 2)[2], []).append(msg)
    return got


@pytest.mark.process
def test_the_export_opens_with_the_mcap_reader_with_well_known_schemas(exported: tuple[Path, Path]) -> None:
    run, out = exported
    rec = _recorded(run)
    js_rec = [m for m in rec["slave/arm1/measured_js"] if isinstance(m, JointState)]
    cp_rec = [m for m in rec["slave/arm1/measured_cp"] if isinstance(m, CartesianPose)]
    img_rec = [m for m in rec.get("camera/endo/image", []) if isinstance(m, CameraImage)]
    assert len(js_rec) > 500 and len(cp_rec) > 500, {k: len(v) for k, v in rec.items()}

    with out.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        classes = _foxglove_classes(reader)
        schema_of = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        decoded: dict[str, list[Any]] = {}
        raw: dict[str, list[bytes]] = {}
        for schema, channel, m in reader.iter_messages(log_time_order=True):
            if schema is not None and schema.id in classes:
                decoded.setdefault(channel.topic, []).append(classes[schema.id].FromString(m.data))
            else:
                raw.setdefault(channel.topic, []).append(m.data)

    names = {t: (s.name, s.encoding) for t, s in schema_of.items()}
    print({t: (n, len(decoded.get(t, raw.get(t, [])))) for t, n in sorted(names.items())})
    assert names["/slave/arm1/measured_js"] == ("foxglove.JointStates", "protobuf")
    assert names["/slave/arm1/measured_js/joint_state"] == ("sensor_msgs/msg/JointState", "ros2msg")
    assert names["/slave/arm1/measured_cp"] == ("foxglove.PoseInFrame", "protobuf")
    assert names["/tf"] == ("foxglove.FrameTransforms", "protobuf")
    assert names["/robot_description"] == ("std_msgs/msg/String", "ros2msg")
    assert names["/events"] == ("foxglove.Log", "protobuf")

    # every measured joint sample, values and stamps as recorded
    js = decoded["/slave/arm1/measured_js"]
    assert len(js) == len(js_rec)
    for a, b in zip(js, js_rec, strict=True):
        assert [j.name for j in a.joints] == list(b.names)
        assert [j.position for j in a.joints] == list(b.position)
        assert a.timestamp.seconds * 1_000_000_000 + a.timestamp.nanos == b.header.stamp_ns
    # poses as recorded, in the scene's world frame
    cp = decoded["/slave/arm1/measured_cp"]
    assert len(cp) == len(cp_rec)
    assert cp[-1].frame_id == "world"
    assert [cp[-1].pose.position.x, cp[-1].pose.position.y, cp[-1].pose.position.z] == list(
        cp_rec[-1].position
    )
    # the frame transforms are the FK of the measured joints: the forceps tip of the MuJoCo model
    # at the exported frames is the recorded measured_cp (the slave's own FK) at the same sample
    tfs = decoded["/tf"]
    assert len(tfs) == len(js_rec)
    spec, _profile = robots.recognise("arm1", js_rec[-1].names) or (None, None)
    assert spec is not None and spec.name == "mh3f"
    frames = {t.child_frame_id: t for t in tfs[-1].transforms}
    assert set(ARM_BODIES) <= set(frames)
    T = np.eye(4)
    chain = []
    name = "forceps"
    while name != "world":
        chain.append(frames[name])
        name = frames[name].parent_frame_id
    for t in reversed(chain):
        q = t.rotation
        w, x, y, z = q.w, q.x, q.y, q.z
        R = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = R, [t.translation.x, t.translation.y, t.translation.z]
        T = T @ step
    model = RobotModel(spec, ["arm1"])
    import mujoco

    site = mujoco.mj_name2id(model.model, mujoco.mjtObj.mjOBJ_SITE, "tip")
    tip_in_forceps = model.model.site_pos[site]
    tip = T[:3, :3] @ tip_in_forceps + T[:3, 3]
    last_cp = min(cp_rec, key=lambda m: abs(m.header.stamp_ns - js_rec[-1].header.stamp_ns))
    assert np.linalg.norm(tip - np.array(last_cp.position)) < 1e-3, (tip, last_cp.position)

    # the robot's description: a URDF with the arm's links
    from rosbags.typesys import Stores, get_typestore

    urdf = (
        get_typestore(Stores.ROS2_JAZZY)
        .deserialize_cdr(raw["/robot_description"][0], "std_msgs/msg/String")
        .data
    )
    assert urdf.startswith("<?xml") and all(f'<link name="{b}">' in urdf for b in ARM_BODIES)
    # the endoscope video: the recorded JPEG frames, unchanged
    if img_rec:
        imgs = decoded["/camera/endo/image"]
        assert names["/camera/endo/image"] == ("foxglove.CompressedImage", "protobuf")
        assert len(imgs) == len(img_rec) and imgs[-1].format == "jpeg" and imgs[-1].data == img_rec[-1].data
    # events and state changes as logs: every recorded event; the slave's first state
    events_rec = [
        m for k, v in rec.items() if k.startswith("events/") for m in v if isinstance(m, SafetyEvent)
    ]
    assert len(decoded.get("/events", [])) == len(events_rec)
    assert all(e.message for e in decoded.get("/events", []))
    first_state = next(m for m in rec["slave/arm1/operating_state"] if isinstance(m, OperatingState))
    assert decoded["/slave/arm1/operating_state"][0].message.startswith(first_state.state)


def _rrd_entities(rrd: Path) -> dict[str, set[str]]:
    """entity path → component names in an .rrd, read with rerun's own reader."""
    from rerun.chunk import RrdReader

    out: dict[str, set[str]] = {}
    for chunk in RrdReader(str(rrd)).stream():
        out.setdefault(chunk.entity_path, set()).update(chunk.to_record_batch().schema.names)
    return out


@pytest.mark.process
def test_rerun_imports_the_export_with_the_arm(exported: tuple[Path, Path], tmp_path: Path) -> None:
    _run, out = exported
    rrd = tmp_path / "export.rrd"
    env = dict(os.environ, RERUN_ANALYTICS="0")
    r = subprocess.run(
        [str(RERUN), "mcap", "convert", str(out), "-o", str(rrd)],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    ents = _rrd_entities(rrd)
    print(sorted(ents))
    # the foxglove lenses: transforms, poses, logs, image; ROS 2 joint states as plots
    assert any("Transform3D" in c for c in ents["/tf"])
    assert any("InstancePoses3D" in c for c in ents["/slave/arm1/measured_cp"])
    assert any("TextLog" in c for c in ents["/slave/arm1/operating_state"])
    assert any("Scalars" in c for c in ents["/slave/arm1/measured_js/joint_state/position"])
    assert any("EncodedImage" in c for c in ents.get("/camera/endo/image", {"EncodedImage"}))
    # the arm's geometry from the URDF: one visual per link, in the link's frame
    for b in ARM_BODIES:
        assert any(e.startswith(f"/mh3f/visual_geometries/{b}/") for e in ents), b


# --------------------------------------------------------------------------- rerun, in a browser


def _arm_pixels(png: bytes) -> int:
    """Pixels of the MH3F's blue casting (drawn from the URDF) in the 3D view (left 60 %)."""
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int32)
    left = img[:, : img.shape[1] * 6 // 10]
    r, g, b = left[..., 0], left[..., 1], left[..., 2]
    return int(((b > r + 40) & (b > g + 15) & (b > 120)).sum())


def serve_export(mcap: Path, workdir: Path, png_out: Path, wait_s: float, min_s: float = 20.0) -> int:
    """Load ``mcap`` with rerun's MCAP importer in this process (``rr.log_file_from_path``), with
    a layout whose 3D view is in the URDF's ``world`` frame; serve it to headless chromium and
    screenshot it every 5 s until the arm is drawn (after ``min_s`` at least: the rest of the page
    loads too) or ``wait_s``. Returns the arm's pixel count of the saved PNG."""
    import rerun as rr
    import rerun.blueprint as rrb
    from helpers import chromium, screenshot
    from telesurg.services.launcher import free_port
    from telesurg.shared.viewer import viewer_url

    rec = rr.RecordingStream("telesurg_export")
    uri = rr.serve_grpc(grpc_port=free_port(), recording=rec)
    web = free_port()
    rr.serve_web_viewer(web_port=web, open_browser=False, connect_to=uri)
    arm = rrb.Spatial3DView(
        name="arm: URDF on /robot_description, moved by /tf",
        origin="/",
        contents=["/mh3f/**", "/slave/arm1/measured_cp", "/slave/arm1/setpoint_cp"],
        spatial_information=rrb.archetypes.SpatialInformation(target_frame="world"),
        eye_controls=rrb.archetypes.EyeControls3D(position=[1.15, -1.05, 0.85], look_target=[0.4, 0.0, 0.25]),
    )
    side = rrb.Vertical(
        rrb.Spatial2DView(name="endoscope", origin="/camera/endo/image"),
        rrb.TimeSeriesView(
            name="measured joints [rad]", origin="/slave/arm1/measured_js/joint_state/position"
        ),
        rrb.TextLogView(
            name="events", origin="/", contents=["/events", "/safety/**", "/slave/arm1/operating_state"]
        ),
    )
    rec.send_blueprint(rrb.Blueprint(rrb.Horizontal(arm, side, column_shares=[3, 2]), collapse_panels=True))
    rr.log_file_from_path(mcap, recording=rec)
    rec.flush()
    png, arm = b"", 0
    with chromium(viewer_url(uri, web), workdir) as (cdp, session):
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:  # software WebGL on a busy host: a shot every 5 s
            time.sleep(5.0)
            try:
                shot = screenshot(cdp, session)
            except TimeoutError:  # chromium too busy to answer in time: try again
                continue
            png, arm = shot, _arm_pixels(shot)
            if arm > 2000 and time.monotonic() > deadline - wait_s + min_s:
                break
    rec.disconnect()
    png_out.write_bytes(png)
    return arm


@pytest.mark.timeout(600)
@pytest.mark.process
def test_rerun_shows_the_arm_from_the_export(exported: tuple[Path, Path], tmp_path: Path) -> None:
    from helpers import CHROMIUM

    if not CHROMIUM.exists():
        pytest.skip("needs Debian chromium at /usr/bin/chromium: apt-get install -y chromium")
    _run, out = exported
    png = tmp_path / "export_rerun.png"
    arm = serve_export(out, tmp_path, png, 300.0)
    print(f"screenshot {png}: {arm} px of the arm's blue")
    assert arm > 2000, "rerun drew no arm from the export's URDF and transforms"


if __name__ == "__main__":  # the picture of docs/console.md from an existing export
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        n = serve_export(
            Path(sys.argv[1]), Path(d), Path(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) > 3 else 90
        )
    print(f"wrote {sys.argv[2]}: {n} px of the arm")


# --------------------------------------------------------------------------- unit: every robot


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@pytest.mark.parametrize("name", ["mh3f", "plas", "vip"])
def test_exported_frames_and_urdf_of_every_robot(name: str) -> None:
    """For each arm of each built-in robot, at random joints within its limits: the tip site
    placed by chaining the exported parent → child frames from ``world`` is the registry's
    ``pose_of(q)`` (the kinematics the services use); the URDF has one link per body."""
    import xml.etree.ElementTree as ET

    import mujoco

    spec = robots.get(name)
    arms = [a.arm for a in spec.arms("arm1")]
    model = RobotModel(spec, arms)
    rng = np.random.default_rng(7)
    for profile in spec.arms("arm1"):
        for _ in range(5):
            q = rng.uniform(profile.lower, profile.upper)
            assert model.set_joints(profile.arm, q)
            frames = {child: (parent, p, r) for parent, child, p, r in model.relative_poses()}
            site = mujoco.mj_name2id(model.model, mujoco.mjtObj.mjOBJ_SITE, profile.tip_site)
            body = model.names[int(model.model.site_bodyid[site])]
            T = np.eye(4)
            while body != "world":
                parent, p, r = frames[body]
                step = np.eye(4)
                step[:3, :3], step[:3, 3] = _quat_matrix(r), p
                T = step @ T
                body = parent
            tip = T[:3, :3] @ model.model.site_pos[site] + T[:3, 3]
            expected = profile.pose_of(q)[:3, 3]
            assert np.linalg.norm(tip - expected) < 1e-6, (name, profile.arm, q, tip, expected)
    assert not model.set_joints("arm9", [0.0])  # an arm the model does not have: no frames
    root = ET.fromstring(model.urdf().split("\n", 1)[1])
    links = [link.get("name") for link in root.iter("link")]
    assert len(links) == len(set(links)) == model.model.nbody
    assert sum(1 for _ in root.iter("visual")) > 5
    kinds = {j.get("type") for j in root.iter("joint")}
    assert kinds & {"revolute", "prismatic"}, kinds


@pytest.mark.parametrize("to", ["rerun", "foxglove"])
def test_a_damaged_recording_writes_nothing_and_keeps_an_existing_output(
    to: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + os.urandom(200))  # the magic, then no valid record
    fresh, kept = tmp_path / "fresh.out", tmp_path / "kept.out"
    kept.write_text("an earlier export")
    assert main([str(bad), str(fresh), "--to", to]) == 1
    assert main([str(bad), str(kept), "--to", to]) == 1
    err = capsys.readouterr().err
    assert f"cannot export {bad}" in err and f"({fresh} not written)" in err
    assert not fresh.exists() and kept.read_text() == "an earlier export"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.mcap", "kept.out"]  # no .part left
