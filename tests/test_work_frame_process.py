"""The work frame in the master mapping and in jogs, through the running services (issue #20: "a real
work frame ... in jog and in the master mapping").

A site file like deploy/local's with one more ``[site]`` fact, ``work_frame_rpy_deg = [180, 0,
-60]`` (a laparoscope looking straight down, turned 30° from the default view), and the mapping's
``master_frame = "work"``. The real pipeline (router, watchdog, slave_control on MuJoCo, mapping);
the test is the surgeon's master (a 250 Hz pose and the clutch) and the console. It judges the
slave's measured tip (``slave/arm1/measured_cp``):

1. a master motion along +x (the view's right) moves the tip along the work frame's +x — base
   (0.5, −0.87, 0), 60° from the base x axis — by scale 0.5 × the master's 40 mm;
2. a master motion along +y (the view's up) moves it along the work frame's −y (up the image);
3. a ``jog frame=work axis=x`` moves it along the same direction as 1.

With the endoscope camera running (``camera=True``: the launcher names it to the mapping and to
slave_control) and turned 90° about its view axis by its holder, the work frame is the camera's
view: a ``jog frame=work axis=x`` and a master motion along +x both move the tip to the right in
the picture (along the camera's optical x axis), not along the configured frame's.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from helpers import GoalMaster as Master
from helpers import operator_command, settled_tip
from telesurg.services.camera import pose_matrix, quat_xyzw
from telesurg.services.launcher import default_config_dir
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.config import SITE_FILE
from telesurg.shared.kinematics.transforms import rpy_matrix
from telesurg.shared.messages import CartesianPose, CommandReply, OperatingState
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process

WORK_RPY = (180.0, 0.0, -60.0)
R_WORK = rpy_matrix(WORK_RPY)  # columns: the work frame's x (image right), y (down), z (into) in base


class Seen:
    def __init__(self, node: Node) -> None:
        self.lock = threading.Lock()
        self.tips: list[tuple[float, np.ndarray]] = []
        self.follow = self.lease = False
        self.cam: CartesianPose | None = None
        k = node.keys
        node.subscribe(k.camera("endo", "measured_cp"), CartesianPose, self._cam)
        node.subscribe(k.slave("arm1", "measured_cp"), CartesianPose, self._tip)
        node.subscribe(k.slave("arm1", "operating_state"), OperatingState, self._state)

    def _tip(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            self.tips.append((time.monotonic(), np.array(m.position)))

    def _state(self, m: OperatingState, key: str) -> None:
        with self.lock:
            self.follow, self.lease = m.follow, m.lease_ok

    def _cam(self, m: CartesianPose, key: str) -> None:
        with self.lock:
            self.cam = m

    def settled_tip(self, quiet_mm: float = 0.02, timeout: float = 8.0) -> np.ndarray:
        """The tip once it moved less than ``quiet_mm`` over 0.3 s."""
        return np.asarray(settled_tip(self.lock, self.tips, quiet_mm, timeout))


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def jog_work_x(pipe: Pipeline, seen: Seen, console: Node) -> np.ndarray:
    """``jog frame=work axis=x direction=1`` for 1 s from the console; the tip's settled
    displacement (m), jogged again when a load hold cut it short."""

    def send(name: str, *args: str) -> CommandReply:
        r: CommandReply = operator_command(console, console.keys.command("arm1"), "arm1", name, *args)
        print(f"{name} {' '.join(args)} -> {'accepted' if r.accepted else 'REFUSED'}: {r.reason}")
        return r

    assert send("set_motion_mode", "mode=jog").accepted
    for _ in range(4):
        assert pipe.wait(lambda: seen.lease, 30), "no lease"
        p0 = seen.settled_tip()
        assert send("jog", "frame=work", "axis=x", "direction=1").accepted
        time.sleep(1.0)
        send("stop")
        dj = seen.settled_tip() - p0
        if np.linalg.norm(dj) > 0.01:  # (a load hold cut it short: again)
            break
    print(f"jog work +x → tip {np.round(dj * 1e3, 2)} mm")
    return dj


@pytest.fixture
def site(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[tuple[Pipeline, Master, Seen, Node]]:
    site_dir = tmp_path / "site"
    site_dir.mkdir()
    text = (default_config_dir() / SITE_FILE).read_text()
    fact = f"work_frame_rpy_deg = {list(WORK_RPY)}   # the laparoscope's view (this test)\n"
    (site_dir / SITE_FILE).write_text(text.replace("[site]", "[site]\n" + fact, 1))
    with (
        Pipeline(
            tmp_path / "logs",
            mirror=False,
            impair=False,
            master=False,
            probe=False,
            config_dir=site_dir,
            camera=getattr(request, "param", False),
            overrides={
                "mapping": ['master_frame="work"', "scale=0.5"],
                "slave_control": ["robot.jog_speed_mm_s=20.0"],
            },
        ) as p,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "master_capture") as node,
        Node(BusConfig(connect=[p.spec.endpoint]), "local", "console") as console,
    ):
        if getattr(request, "param", False):
            assert "camera" not in p.site.off, f"the camera did not start: {p.site.off}"
        seen = Seen(node)
        m = Master(node)
        m.start()
        try:
            yield p, m, seen, console
        finally:
            m.stop.set()
            m.join(2)
    for f in sorted((tmp_path / "logs").glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-1500:]}")


def test_master_and_jog_move_the_tip_along_the_work_frame(site: tuple[Pipeline, Master, Seen, Node]) -> None:
    pipe, master, seen, console = site
    assert pipe.wait(lambda: seen.lease and len(seen.tips) > 10, 30), "no lease from the watchdog"

    def engage() -> None:
        for _ in range(5):
            master.clutch = False
            time.sleep(0.3)
            master.clutch = True
            if pipe.wait(lambda: seen.follow, 5):
                return
        raise AssertionError("no engage")

    def move(d: np.ndarray) -> np.ndarray:
        """The master by ``d`` (m); the tip's settled displacement (redone after a load hold)."""
        for _ in range(4):
            p0 = seen.settled_tip()
            master.goal = master.goal + d
            time.sleep(float(np.linalg.norm(d)) / 0.04 + 0.3)
            p1 = seen.settled_tip()
            if seen.follow:
                return p1 - p0
            print("a watchdog hold interrupted the motion (load): engage again")
            engage()
        raise AssertionError("the motion was interrupted four times")

    engage()
    work_x, work_y = R_WORK[:, 0], R_WORK[:, 1]
    dx = move(np.array([0.04, 0.0, 0.0]))
    print(f"master +x 40 mm → tip {np.round(dx * 1e3, 2)} mm; work +x = {np.round(work_x, 3)}")
    assert angle_deg(dx, work_x) < 5.0, f"{angle_deg(dx, work_x):.1f}° from the work frame's +x"
    assert angle_deg(dx, np.array([1.0, 0.0, 0.0])) > 55.0  # not base x
    assert abs(np.linalg.norm(dx) * 1e3 - 20.0) < 2.0  # scale 0.5
    dy = move(np.array([0.0, 0.04, 0.0]))
    print(f"master +y 40 mm → tip {np.round(dy * 1e3, 2)} mm; work −y (image up) = {np.round(-work_y, 3)}")
    assert angle_deg(dy, -work_y) < 5.0, f"{angle_deg(dy, -work_y):.1f}° from the work frame's −y"
    assert abs(np.linalg.norm(dy) * 1e3 - 20.0) < 2.0
    master.clutch = False

    assert pipe.wait(lambda: not seen.follow, 5)
    dj = jog_work_x(pipe, seen, console)
    assert angle_deg(dj, work_x) < 3.0, f"{angle_deg(dj, work_x):.1f}° from the work frame's +x"
    assert angle_deg(dj, dx) < 5.0  # the jog and the master agree on the work frame


@pytest.mark.parametrize("site", [True], indirect=True, ids=["camera"])
def test_with_the_endoscope_camera_the_work_frame_is_its_view(
    site: tuple[Pipeline, Master, Seen, Node],
) -> None:
    pipe, _, seen, console = site  # (master right in the picture: tests/test_camera_mapping_process.py)
    assert pipe.wait(lambda: seen.lease and seen.cam is not None and len(seen.tips) > 10, 60), "no lease"
    holder = console.outlet(console.keys.camera("endo", "servo_cp"), control=False)
    assert seen.cam is not None
    T = pose_matrix(seen.cam)
    T[:3, :3] = T[:3, :3] @ rpy_matrix((0.0, 0.0, 90.0))  # turned 90° about its view axis
    for _ in range(5):  # (the camera renders on a busy host: its pose may come late)
        holder.put(
            CartesianPose(holder.header(), "base", tuple(float(v) for v in T[:3, 3]), quat_xyzw(T[:3, :3]))
        )
        if pipe.wait(lambda: angle_deg(pose_matrix(seen.cam)[:3, 0], T[:3, 0]) < 0.5, 5):  # type: ignore[arg-type]
            break
    else:
        raise AssertionError("the camera did not take the commanded pose")
    cam_x = T[:3, 0]  # right in the picture, base frame
    print(
        f"camera x (image right) in base: {np.round(cam_x, 3)}; configured work x: "
        f"{np.round(R_WORK[:, 0], 3)}"
    )
    assert angle_deg(cam_x, R_WORK[:, 0]) > 30.0  # the two frames differ: the test can tell them apart
    time.sleep(0.5)

    dj = jog_work_x(pipe, seen, console)
    assert angle_deg(dj, cam_x) < 3.0, f"{angle_deg(dj, cam_x):.1f}° from the camera's image right"
