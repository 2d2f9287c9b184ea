"""The camera service as a real process on a real site (issue #18, acceptance 1 and 4).

1. The simulated endoscope: frames arrive in sequence at the configured rate, and the picture is
   the slave's — the forceps tip, projected with the published intrinsics and camera pose, lies on
   pixels that differ from the same view rendered without the arm.
4. A real-camera source (PyAV) reads a video file the test makes, through the same service and
   transport: the pictures that arrive are the file's.
"""

from __future__ import annotations

import time
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import simplejpeg
from conftest import wait_until
from telesurg.services.camera import pose_matrix
from telesurg.services.camera.sources import MujocoSource
from telesurg.services.launcher import Site, SiteSpec, free_port
from telesurg.shared import robots
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import CameraImage, CartesianPose, JointState
from telesurg.shared.teleop.camera_frame import project

pytestmark = pytest.mark.process

FPS = 10.0


def _collect(
    spec: SiteSpec, seconds: float, js: bool = False
) -> tuple[list[tuple[int, CameraImage]], list[CartesianPose], list[JointState]]:
    frames: list[tuple[int, CameraImage]] = []
    poses: list[CartesianPose] = []
    joints: list[JointState] = []
    with Node(BusConfig(connect=[spec.endpoint]), spec.site, "probe") as n:
        n.subscribe(
            n.keys.camera("endo", "image"), CameraImage, lambda m, k: frames.append((time.time_ns(), m))
        )
        n.subscribe(
            n.keys.camera("endo", "measured_cp"), CartesianPose, lambda m, k: poses.append(m), latest=True
        )
        if js:
            n.subscribe(n.keys.slave("arm1", "measured_js"), JointState, lambda m, k: joints.append(m))
        assert wait_until(lambda: len(frames) >= 2, 20.0), "no frames from the camera"
        del frames[:]
        time.sleep(seconds)
    return frames, poses, joints


def _report(frames: list[tuple[int, CameraImage]], seconds: float) -> tuple[float, float]:
    seqs = [m.header.seq for _, m in frames]
    span = seqs[-1] - seqs[0] + 1
    in_seq = len(set(seqs)) / span
    ages = np.array([(t - m.capture_ns) / 1e6 for t, m in frames])
    dropped = frames[-1][1].dropped - frames[0][1].dropped
    fps = len(frames) / seconds
    print(
        f"{len(frames)} frames in {seconds:g} s = {fps:.1f} fps (configured {FPS:g}); in sequence "
        f"{in_seq:.1%}; camera dropped {dropped}; age p50 {np.percentile(ages, 50):.1f} ms, "
        f"p99 {np.percentile(ages, 99):.1f} ms"
    )
    return in_seq, (len(frames) + dropped) / seconds


def test_the_endoscope_shows_the_slave(tmp_path: Path) -> None:
    spec = SiteSpec(
        site="cam1",
        port=free_port(),
        services=("camera", "slave_control"),
        overrides={"camera": [f"fps={FPS}"]},
        log_dir=tmp_path,
    )
    seconds = 4.0
    with Site(spec) as site:
        assert site.off == ()
        frames, poses, joints = _collect(spec, seconds, js=True)
    in_seq, made_per_s = _report(frames, seconds)
    assert in_seq >= 0.95
    # every period of the camera is accounted for: a frame sent, or one dropped and counted
    assert made_per_s >= 0.9 * FPS
    img = frames[-1][1]
    assert (img.width, img.height, img.encoding, img.layout) == (320, 240, "jpeg", "mono")
    rgb = simplejpeg.decode_jpeg(img.data, colorspace="RGB")
    assert rgb.shape == (240, 320, 3)
    # the tip, projected with what the camera published
    profile = robots.get("mh3f").arm("arm1")
    q = np.array(joints[-1].position)
    tip = profile.tip(q)
    T = pose_matrix(poses[-1])
    # (the projection the web console's predictive overlay draws with)
    px = project(tip, poses[-1], img.fx, img.fy, img.cx, img.cy)
    assert px is not None, "the tip is behind the camera"
    u, v = px
    assert 1 <= u < img.width - 1 and 1 <= v < img.height - 1, f"tip projects outside the picture ({u}, {v})"
    # the same view without the arm
    bare = MujocoSource(robots.get("mh3f").scene, width=320, height=240, hide_bodies=("base",))
    bare.move(T)
    without = bare.grab(dict(zip(profile.model_joints, q, strict=True))).rgb
    bare.close()
    diff = np.abs(rgb.astype(int) - without.astype(int)).sum(axis=2)
    iu, iv = int(u), int(v)
    at_tip = int(diff[iv - 1 : iv + 2, iu - 1 : iu + 2].max())
    far = int(diff[225:235, 5:15].max())  # bottom-left corner: tissue / table, no arm
    print(
        f"tip at pixel ({u:.1f}, {v:.1f}): colour difference with/without the arm {at_tip}; far corner {far}"
    )
    assert at_tip > 100
    assert far < 40  # the rest of the picture is the same scene (JPEG noise only)


def _make_clip(path: Path, n: int = 48) -> list[np.ndarray]:
    """An H.264 clip of colour fields (red, green, blue, ... changing every 8 frames)."""
    import av

    colours = [(220, 30, 30), (30, 200, 40), (40, 60, 220)]
    frames = []
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=24)
        stream.width, stream.height, stream.pix_fmt = 160, 120, "yuv420p"
        stream.time_base = Fraction(1, 24)
        for i in range(n):
            rgb = np.zeros((120, 160, 3), np.uint8)
            rgb[:] = colours[(i // 8) % 3]
            rgb[50:70, 70:90] = 255  # a white square in the middle
            frames.append(rgb)
            vf = av.VideoFrame.from_ndarray(rgb, format="rgb24")
            for pkt in stream.encode(vf):
                out.mux(pkt)
        for pkt in stream.encode():
            out.mux(pkt)
    return frames


def test_a_real_camera_source_reads_a_video_file(tmp_path: Path) -> None:
    clip = tmp_path / "clip.mp4"
    _make_clip(clip)
    spec = SiteSpec(
        site="cam4",
        port=free_port(),
        services=("camera",),
        overrides={"camera": ["source=video", f"url={str(clip)!r}", f"fps={FPS}", "width=160", "height=120"]},
        log_dir=tmp_path,
    )
    seconds = 3.0
    with Site(spec) as site:
        assert site.off == ()
        frames, _, _ = _collect(spec, seconds)
    in_seq, made_per_s = _report(frames, seconds)
    assert in_seq >= 0.95
    assert made_per_s >= 0.9 * FPS
    seen = set()
    for _, m in frames:
        rgb = simplejpeg.decode_jpeg(m.data, colorspace="RGB").astype(int)
        assert rgb.shape == (120, 160, 3)
        assert (rgb[55:65, 75:85] > 200).all()  # the white square of every frame of the file
        corner = rgb[5:15, 5:15].reshape(-1, 3).mean(axis=0)
        seen.add(int(np.argmax(corner)))  # the dominant colour: 0 red, 1 green, 2 blue
    print(f"colours seen: {sorted(seen)}")
    assert seen == {0, 1, 2}  # the file plays (and loops) through the service
