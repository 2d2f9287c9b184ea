"""Teleoperation in the camera frame through the running services (issue #18, acceptance 2).

The real pipeline (deploy/local: router, watchdog, slave_control on MuJoCo, mapping) and the real
camera service; the test is the surgeon's master (a 250 Hz pose and clutch it publishes) and the
hand on the endoscope holder (``camera/endo/servo_cp``). It judges what the surgeon sees: the
slave's measured tip (``slave/arm1/measured_cp``) projected into the picture with the pose and
intrinsics the camera publishes.

1. The endoscope turned 90° about its view axis: a master motion to the right moves the tip to
   the right in the picture (±10°).
2. The endoscope turned back by 90° while engaged, the master still: the slave moves < 1 mm;
   from there a master motion to the right is again right in the (new) picture.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from helpers import GoalMaster as Master
from helpers import settled_tip
from telesurg.services.camera import pose_matrix, quat_xyzw
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import CameraImage, CartesianPose, OperatingState
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process


@dataclass
class Seen:
    lock: threading.Lock = field(default_factory=threading.Lock)
    tips: list[tuple[float, np.ndarray]] = field(default_factory=list)
    cam: CartesianPose | None = None
    image: CameraImage | None = None
    follow: bool = False
    lease: bool = False

    def on_tip(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            self.tips.append((time.monotonic(), np.array(m.position)))

    def on_cam(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            self.cam = m

    def on_image(self, m: CameraImage, key: str) -> None:
        with self.lock:
            self.image = m

    def on_state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.follow, self.lease = m.follow, m.lease_ok

    def settled_tip(self, quiet_mm: float = 0.02, timeout: float = 8.0) -> np.ndarray:
        """The tip once it moved less than ``quiet_mm`` over 0.3 s."""
        return np.asarray(settled_tip(self.lock, self.tips, quiet_mm, timeout))

    def camera(self) -> np.ndarray:
        with self.lock:
            assert self.cam is not None
            return pose_matrix(self.cam)


def turned(T: np.ndarray, deg: float) -> np.ndarray:
    """The camera pose turned by ``deg`` about its own view axis (optical z)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return out


def angle_between(R0: np.ndarray, R1: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(R0.T @ R1)) - 1.0) / 2.0))))


def image_direction(
    T_cam: np.ndarray, img: CameraImage, p0: np.ndarray, p1: np.ndarray
) -> tuple[float, float]:
    """(angle, length in px) of the tip's motion p0 → p1 in the picture; 0° = right, 90° = up."""

    def pixel(p: np.ndarray) -> np.ndarray:
        pc = T_cam[:3, :3].T @ (p - T_cam[:3, 3])
        return np.array([img.fx * pc[0] / pc[2] + img.cx, img.fy * pc[1] / pc[2] + img.cy])

    d = pixel(p1) - pixel(p0)
    return math.degrees(math.atan2(-d[1], d[0])), float(np.hypot(*d))  # (v grows downward)


@pytest.fixture
def site(tmp_path: Path) -> Iterator[tuple[Pipeline, Master, Seen, Node]]:
    with (
        Pipeline(
            tmp_path / "logs",
            mirror=False,
            impair=False,
            master=False,
            probe=False,
            camera=True,
            overrides={"mapping": ["scale=0.5"]},
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as node,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as console,
    ):
        assert "camera" not in p.site.off, f"the camera did not start: {p.site.off}"
        seen = Seen()
        k = node.keys
        node.subscribe(k.slave("arm1", "measured_cp"), CartesianPose, seen.on_tip)
        node.subscribe(k.slave("arm1", "operating_state"), OperatingState, seen.on_state)
        node.subscribe(k.camera("endo", "measured_cp"), CartesianPose, seen.on_cam, latest=True)
        node.subscribe(k.camera("endo", "image"), CameraImage, seen.on_image)
        m = Master(node)
        m.start()
        try:
            yield p, m, seen, console
        finally:
            m.stop.set()
            m.join(2)
    for f in sorted((tmp_path / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-1500:]}")


def test_master_right_is_right_in_the_picture_and_a_camera_turn_moves_nothing(
    site: tuple[Pipeline, Master, Seen, Node],
) -> None:
    pipe, master, seen, console = site
    assert pipe.wait(lambda: seen.cam is not None and seen.image is not None and len(seen.tips) > 10, 30)
    assert pipe.wait(lambda: seen.lease, 30), "no lease from the watchdog"
    holder = console.outlet(console.keys.camera("endo", "servo_cp"), control=False)

    def move_camera(T: np.ndarray) -> None:
        pose = CartesianPose(holder.header(), "base", tuple(float(x) for x in T[:3, 3]), quat_xyzw(T[:3, :3]))
        for _ in range(3):  # (a bulk-priority stream: say it again if the first is lost)
            holder.put(pose)
            if pipe.wait(lambda: angle_between(seen.camera()[:3, :3], T[:3, :3]) < 0.5, 3):
                return
        raise AssertionError("the camera did not take the commanded pose")

    T0 = seen.camera()
    T90 = turned(T0, 90.0)
    move_camera(T90)
    time.sleep(0.3)  # the mapping hears the new pose

    def engage() -> None:
        for _ in range(5):
            master.clutch = False
            time.sleep(0.3)
            master.clutch = True
            if pipe.wait(lambda: seen.follow, 5):
                return
        raise AssertionError("no engage")

    def right(dx: float) -> tuple[np.ndarray, np.ndarray]:
        """The master dx to the right; the settled tip before and after (redone after a hold)."""
        for _ in range(4):
            p0 = seen.settled_tip()
            master.goal = master.goal + np.array([dx, 0.0, 0.0])
            time.sleep(dx / 0.04 + 0.2)
            p1 = seen.settled_tip()
            if seen.follow:
                return p0, p1
            print("a watchdog hold interrupted the motion (load): engage again")
            engage()
        raise AssertionError("the motion was interrupted four times")

    engage()
    p0, p1 = right(0.02)
    with seen.lock:
        img = seen.image
    assert img is not None
    ang, px = image_direction(T90, img, p0, p1)
    moved = (p1 - p0) * 1e3
    print(
        f"camera turned 90°: master 20 mm right → tip {np.round(moved, 2)} mm, "
        f"{px:.1f} px at {ang:+.1f}° in the picture"
    )
    # 20 mm at the site's 0.5 is 10 mm; a watchdog DEGRADED on a busy host halves the motion scale
    # (exactly 5 mm): either way the tip clearly moved
    assert np.linalg.norm(moved) > 3.0, f"the tip moved only {moved} mm"
    assert abs(ang) <= 10.0, f"the tip went {ang:+.1f}° in the picture, not right"

    # the endoscope turned back while engaged, the hand still
    before = seen.settled_tip()
    move_camera(T0)
    after = seen.settled_tip()
    assert seen.follow, "the camera turn disengaged the mapping"
    jump_mm = float(np.linalg.norm(after - before) * 1e3)
    print(f"camera turned back 90° while engaged: the slave moved {jump_mm:.3f} mm")
    assert jump_mm < 1.0

    q0, q1 = right(0.02)
    ang2, px2 = image_direction(T0, img, q0, q1)
    print(f"then master 20 mm right → {px2:.1f} px at {ang2:+.1f}° in the turned-back picture")
    assert abs(ang2) <= 10.0
    master.clutch = False
