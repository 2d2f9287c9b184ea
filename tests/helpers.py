"""Helpers only the tests use (imported as ``from helpers import ...``; ``tests/`` is on the path).

* .rrd readers — what the mirror wrote, read back with rerun's own chunk reader;
* :func:`clutch_flags` — the bench's clutch schedule as ``--set`` flags for a launched site;
* :class:`MasterHand` — a master publishing its pose and clutch at 250 Hz (process tests);
  :class:`GoalMaster` moves it smoothly to a goal; :func:`settled_tip` waits for the slave's tip;
* headless Debian chromium driven over the DevTools protocol on a pipe (:func:`chromium`,
  :class:`DevTools`, :func:`screenshot`): the viewer and web console browser tests.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared.messages import CartesianPose, Header, MasterButtons
from telesurg.tools.bench.harness import BENCH_CLUTCH

#: header of the messages the tests hand to a mapping's callbacks
TEST_HEADER = Header("test", 0, 0)


def run_unprivileged(imports: str, body: str) -> subprocess.CompletedProcess[str]:
    """Run the Python lines ``imports`` (as root: the interpreter may live in root's home), then
    ``body`` as "nobody" when the tests run as root (dropping every capability with it), else as
    this user, in a new interpreter; exit code and output returned."""
    code = f"import os, sys\n{imports}\nos.setuid(65534) if os.getuid() == 0 else None\n{body}"
    root = Path(__file__).resolve().parents[1]
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=root)


def autogroup(pid: int | str) -> str:
    """The name of ``pid``'s scheduler autogroup (``/autogroup-123``). The file is empty for a
    process in the root autogroup (no new session since boot, as under some CI runners' init)."""
    return (Path(f"/proc/{pid}/autogroup").read_text().split() or ["(root autogroup)"])[0]


@contextlib.contextmanager
def held_port() -> Iterator[int]:
    """A loopback TCP port something listens on for the block (what a second site meets)."""
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        yield holder.getsockname()[1]


def clutch_flags() -> list[str]:
    """``--set`` flags for ``telesurg up`` / ``demo`` / ``deploy/console.sh`` that give the
    site's scripted master the bench's clutch schedule (a hold ends one engagement, not a run)."""
    return [arg for item in BENCH_CLUTCH for arg in ("--set", f"master_capture.{item}")]


def _chunks(path: str | Path) -> Any:
    from rerun.chunk import RrdReader

    return RrdReader(str(path)).stream()


def entity_paths(path: str | Path) -> set[str]:
    """Every entity path with data in the first recording of an .rrd (properties excluded)."""
    return {c.entity_path for c in _chunks(path) if not c.entity_path.startswith("/__")}


def scalar_counts(path: str | Path) -> dict[str, int]:
    """Number of Scalars rows per entity path in an .rrd."""
    counts: dict[str, int] = {}
    for c in _chunks(path):
        names = c.to_record_batch().schema.names
        if any(n.startswith("Scalars:") for n in names):
            counts[c.entity_path] = counts.get(c.entity_path, 0) + c.num_rows
    return counts


def scalar_rows(path: str | Path, entity: str) -> list[list[float]]:
    """The Scalars rows of one entity of an .rrd (a row: one value per series), in file order."""
    rows: list[list[float]] = []
    for c in _chunks(path):
        if c.entity_path == entity:
            batch = c.to_record_batch()
            if "Scalars:scalars" in batch.schema.names:
                rows += [list(r) for r in batch.column("Scalars:scalars").to_pylist() if r is not None]
    return rows


def drawn_body_poses(path: str | Path, spec: Any) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Where the mirror drew each body of robot ``spec`` (a registry entry): per drawn frame (a row of
    ``/slave/geometry/<robot>``, every primitive posed in the world frame) the body's pose worked
    back from its first primitive, by body name: ``[(position (3,), rotation matrix (3, 3)), ...]`` in
    file order."""
    from telesurg.services.mirror.geometry import RobotGeometry, quat_matrix
    from telesurg.services.mirror.view import geometry_path

    geo = RobotGeometry.load(spec)
    columns = {  # kind → (archetype, the column of its placement)
        "box": ("Boxes3D", "centers"),
        "ellipsoid": ("Ellipsoids3D", "centers"),
        "cylinder": ("Cylinders3D", "centers"),
        "capsule": ("Capsules3D", "translations"),  # rerun's: an end, not the centre
    }
    first: dict[str, tuple[str, int]] = {}  # body → (kind, index in geo.primitives[kind])
    for kind, prims in geo.primitives.items():
        for i, prim in enumerate(prims):
            body = next(b.name for b in geo.bodies if b.index == int(geo.model.geom_bodyid[prim.geom]))
            first.setdefault(body, (kind, i))
    out: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for c in _chunks(path):
        if c.entity_path != geometry_path(spec.name):
            continue
        batch = c.to_record_batch()
        names = batch.schema.names
        got = {
            kind: (
                batch.column(f"{arch}:{field}").to_pylist(),
                batch.column(f"{arch}:quaternions").to_pylist(),
            )
            for kind, (arch, field) in columns.items()
            if f"{arch}:{field}" in names and f"{arch}:quaternions" in names
        }
        for row in range(batch.num_rows):
            for body, (kind, i) in first.items():
                if kind not in got or got[kind][0][row] is None:
                    continue
                prim = geo.primitives[kind][i]
                rot = quat_matrix(np.roll(np.array(got[kind][1][row][i], float), 1))  # rerun: x y z w
                at = np.array(got[kind][0][row][i], float)
                if kind == "capsule":
                    at = at + 0.5 * prim.size[1] * rot[:, 2]
                body_rot = rot @ quat_matrix(prim.quat).T
                out.setdefault(body, []).append((at - body_rot @ prim.center, body_rot))
    return out


def series_names(path: str | Path, entity: str) -> list[str]:
    """The series names (static ``SeriesLines:names``) of one entity of an .rrd, the last logged."""
    names: list[str] = []
    for c in _chunks(path):
        if c.entity_path == entity:
            batch = c.to_record_batch()
            if "SeriesLines:names" in batch.schema.names:
                names = [str(n) for n in batch.column("SeriesLines:names").to_pylist()[-1]]
    return names


def text_logs(path: str | Path) -> list[tuple[str, str, str]]:
    """``(entity_path, level, text)`` of every TextLog row in an .rrd, in file order."""
    out: list[tuple[str, str, str]] = []
    for c in _chunks(path):
        batch = c.to_record_batch()
        names = batch.schema.names
        if "TextLog:text" not in names:
            continue
        texts = batch.column("TextLog:text").to_pylist()
        levels = (
            batch.column("TextLog:level").to_pylist() if "TextLog:level" in names else [None] * len(texts)
        )
        for t, lv in zip(texts, levels, strict=True):
            for i, line in enumerate(t or []):
                level = lv[i] if lv and i < len(lv) else ""
                out.append((c.entity_path, str(level or ""), str(line)))
    return out


class MasterHand(threading.Thread):
    """The surgeon's master on the bus, as a process test plays it: ``master/<m>/measured_cp`` and
    ``buttons`` at ``rate`` Hz from its own thread, the clutch held while :attr:`clutch` is true.
    The pose is :meth:`position` at each tick (a subclass draws its path there; the default
    rests at the origin); set :attr:`stop` to end it."""

    def __init__(self, node: Any, master: str = "m1", rate: float = 250.0) -> None:
        super().__init__(daemon=True)
        self.clutch, self.stop, self.rate = False, threading.Event(), rate
        self.pose = node.outlet(node.keys.master(master, "measured_cp"))
        self.buttons = node.outlet(node.keys.master(master, "buttons"))

    def position(self, now: float) -> tuple[float, float, float]:
        """The master's position (m) at ``now`` (``time.monotonic()``)."""
        return (0.0, 0.0, 0.0)

    def run(self) -> None:
        start, n = time.monotonic(), 0
        while not self.stop.is_set():
            p = self.position(time.monotonic())
            self.buttons.put(MasterButtons(self.buttons.header(), self.clutch, True))
            self.pose.put(CartesianPose(self.pose.header(), "master", p, (0.0, 0.0, 0.0, 1.0)))
            n += 1
            self.stop.wait(max(0.0, start + n / self.rate - time.monotonic()))


class GoalMaster(MasterHand):
    """A surgeon's hand that moves the master smoothly to :attr:`goal` (m, at most 40 mm/s: a
    hand, not a jump), 250 Hz."""

    def __init__(self, node: Any) -> None:
        super().__init__(node)
        self.p, self.goal = np.zeros(3), np.zeros(3)

    def position(self, now: float) -> tuple[float, float, float]:
        step = self.goal - self.p
        self.p = self.p + step * min(1.0, 0.16e-3 / max(float(np.linalg.norm(step)), 1e-12))
        return (float(self.p[0]), float(self.p[1]), float(self.p[2]))


class SwingingArm(threading.Thread):
    """The slave's ``measured_js`` at 100 Hz, j1 swinging ±0.4 rad about the home pose (the
    browser viewer tests' live stream); ``stop`` ends it."""

    def __init__(self, node: Any, profile: Any) -> None:
        super().__init__(daemon=True)
        self.stop = threading.Event()
        self.js = node.outlet(node.keys.slave("arm1", "measured_js"), control=False)
        self.names, self.home = profile.joint_names, np.asarray(profile.home, np.float64)

    def run(self) -> None:
        from telesurg.shared.messages import JointState

        t0 = time.monotonic()
        while not self.stop.is_set():
            q = self.home.copy()
            q[0] += 0.4 * np.sin(0.5 * (time.monotonic() - t0))
            self.js.put(JointState(self.js.header(), self.names, tuple(q)))
            time.sleep(0.01)


def settled_tip(
    lock: threading.Lock, tips: list[tuple[float, Any]], quiet_mm: float = 0.02, timeout: float = 8.0
) -> Any:
    """The newest of ``tips`` ((monotonic s, position m) samples appended under ``lock``) once
    the tip moved less than ``quiet_mm`` over 0.3 s, or after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        t = time.monotonic()
        time.sleep(0.3)
        with lock:
            pts = np.array([p for s, p in tips if s >= t])
        if len(pts) > 5 and np.ptp(pts, axis=0).max() * 1e3 < quiet_mm:
            break
    with lock:
        return tips[-1][1].copy()


def wait_first(lock: Any, site: Any, pred: Callable[[], float | None], timeout: float) -> float | None:
    """Poll ``pred()`` under ``lock`` every 50 ms until it gives a time (returned) or ``timeout`` s
    pass (None); a dead service of ``site`` fails at once."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with lock:
            t = pred()
        if t is not None:
            return float(t)
        assert not site.dead(), f"a service died: {site.dead()}"
        time.sleep(0.05)
    return None


def feed_master(arm: Any, p: tuple[float, float, float], clutch: bool) -> None:
    """One master sample into a mapping pair (``telesurg.services.mapping.Pair``) as its
    zenoh callbacks would deliver it: the buttons, then the pose at ``p`` (m), then one
    ``process()`` of the mapping loop."""
    arm.on_buttons(MasterButtons(TEST_HEADER, clutch, True), "")
    arm.on_master(CartesianPose(TEST_HEADER, "master", p), "")
    arm.process()


# --------------------------------------------------------------------------- chromium over DevTools
# (the benches' browser, tools/bench/browser.py; re-exported for the tests)
from telesurg.tools.bench.browser import (  # noqa: E402
    CHROMIUM,
    CHROMIUM_FLAGS,
    WINDOW,
    DevTools,
    chromium,
    screenshot,
)

__all__ = ["CHROMIUM", "CHROMIUM_FLAGS", "WINDOW", "DevTools", "chromium", "screenshot"]

_operator_seq: dict[str, Any] = {}


def operator_command(node: Any, key: str, arm: str, name: str, *args: str, confirm: bool = True) -> Any:
    """Send one operator command as ``node``'s service id (open it as ``console``: only the
    operator console may command, shared/authority.py) and return the reply; ``confirm``: answer a
    ``confirm required`` reply with its token, as an operator who says yes."""
    from telesurg.shared.messages import Command, CommandReply, Sequencer

    seq = _operator_seq.setdefault(node.service, Sequencer(node.service))
    r = node.request(key, Command(seq.next(), arm, name, args), CommandReply, 5.0)
    if confirm and r.confirm:
        r = node.request(
            key, Command(seq.next(), arm, name, (*args, f"confirm={r.confirm}")), CommandReply, 5.0
        )
    return r


def hue_pixels(png: bytes, rgb: tuple[int, int, int], box: tuple[int, int, int, int]) -> int:
    """Pixels inside ``box`` (x0, y0, x1, y1) of the hue of ``rgb`` (±6 %), saturated and not dark
    (shading changes the brightness of a lit surface, not its hue)."""
    import colorsys
    import io

    from PIL import Image

    hsv = np.asarray(Image.open(io.BytesIO(png)).convert("HSV"), dtype=np.int32)
    x0, y0, x1, y1 = box
    region = hsv[y0:y1, x0:x1]
    h = colorsys.rgb_to_hsv(*(c / 255 for c in rgb))[0] * 255
    dh = np.abs(region[..., 0] - h)
    dh = np.minimum(dh, 256 - dh)
    return int(((dh <= 16) & (region[..., 1] >= 100) & (region[..., 2] >= 50)).sum())
