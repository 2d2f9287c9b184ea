"""A LeRobotDataset exported from a live recording, checked against that recording by readers
that are not telesurg's writer: LeRobot's own ``LeRobotDataset`` (the ``lerobot-dataset``
package, in a venv of its own: ``tests/lerobot_reader/``), and pyarrow (the Parquet files) and
PyAV (the MP4), which must read the same rows and frames. Used by
``tests/test_docs_recipes.py`` (docs/learning.md's worked example: a live site with two clutch
presses and the camera at 25 fps, recorded, exported at 10 fps).

What a user of the dataset relies on: one episode per engaged period, each (engaged time × fps
± 1) frames; every row's joints the slave's measured joints at the row's instant; every video
frame the recorded camera frame nearest its row's instant (found by its content among the
recorded frames, independently of the export's own record of its choice, which is checked against
it), captured within one frame period of the row's instant; every action the mapping's recorded
target within 0.01 mm.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.services.record import iter_decoded, open_mcap
from telesurg.shared.messages import CameraImage, CartesianPose, JointState, OperatingState

READER = Path(__file__).parent / "lerobot_reader"
#: the FFmpeg libraries torchcodec loads (Debian 12's packages; .ci/run installs them as root)
FFMPEG_DEB = "libavcodec59 libavformat59 libavutil57 libswscale6 libavdevice59 libavfilter8"


def lerobot_python() -> Path:
    """The Python of the reader's venv (``tests/lerobot_reader/requirements.txt``), made once per
    requirements in the user's cache (about 2 min and 6 GB: torch), under a lock."""
    reqs = READER / "requirements.txt"
    digest = hashlib.sha256(reqs.read_bytes()).hexdigest()[:12]
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "telesurg"
    venv = cache / f"lerobot-reader-{digest}"
    python = venv / "bin" / "python"
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / f"lerobot-reader-{digest}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (venv / ".ready").exists():
            subprocess.run([sys.executable, "-m", "venv", "--clear", str(venv)], check=True)
            r = subprocess.run(
                [str(python), "-m", "pip", "install", "-q", "-r", str(reqs)],
                capture_output=True,
                text=True,
                timeout=1200,
            )
            assert r.returncode == 0, f"the LeRobot reader's venv could not be made:\n{r.stderr[-3000:]}"
            (venv / ".ready").write_text(reqs.read_text())
    return python


def read_with_lerobot(out: Path) -> dict[str, Any]:
    """The dataset ``out`` as LeRobot's ``LeRobotDataset`` gives it, item by item
    (``tests/lerobot_reader/read.py``): ``meta`` (episodes, frames, fps, tasks, lengths) and arrays."""
    python = lerobot_python()
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "read.npz"
        r = subprocess.run(
            [str(python), str(READER / "read.py"), str(out), str(npz)],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert "libavutil" not in r.stderr, (
            f"torchcodec needs the system's FFmpeg: apt-get install {FFMPEG_DEB}"
        )
        assert r.returncode == 0, f"LeRobotDataset could not read the dataset:\n{r.stderr[-4000:]}"
        with np.load(npz) as z:
            got = {k: z[k] for k in z.files}
    got["meta"] = json.loads(str(got["meta"]))
    return got


def _recorded(run: Path) -> dict[str, list[tuple[int, object]]]:
    """topic (relative) → [(stamp ns, message)] of the trusted publishers."""
    got: dict[str, list[tuple[int, object]]] = {}
    with open_mcap(run) as reader:
        for topic, _lt, _pt, _d, msg in iter_decoded(reader):
            if msg is None or msg.header.source not in ("slave_control", "mapping", "camera"):
                continue
            t = msg.capture_ns if isinstance(msg, CameraImage) and msg.capture_ns else msg.header.stamp_ns
            got.setdefault(topic.split("/", 2)[2], []).append((t, msg))
    return got


def _at(series: list[tuple[int, object]], t: int) -> tuple[int, object]:
    times = [s for s, _ in series]
    i = int(np.searchsorted(times, t, side="right")) - 1
    assert i >= 0
    return series[i]


def check_dataset(run: Path, out: Path, fps: float) -> dict[str, float]:
    """Assert what the module doc says of the dataset ``out`` made from ``run``; the figures."""
    import av
    import pyarrow.parquet as pq
    import simplejpeg

    rec = _recorded(run)
    js = sorted((t, m) for t, m in rec["slave/arm1/measured_js"] if isinstance(m, JointState))
    target = sorted((t, m) for t, m in rec["slave/arm1/setpoint_cp"] if isinstance(m, CartesianPose))
    images = sorted((t, m) for t, m in rec.get("camera/endo/image", []) if isinstance(m, CameraImage))
    states = sorted((t, m) for t, m in rec["slave/arm1/operating_state"] if isinstance(m, OperatingState))
    # the engaged periods, from the slave's follow flag as recorded
    periods, on = [], None
    for t, m in states:
        if m.follow and on is None:
            on = t
        elif not m.follow and on is not None:
            periods.append((on, t))
            on = None
    assert len(periods) == 2, f"expected the two clutch presses to engage twice: {periods}"
    cameras = bool(images)

    info = json.loads((out / "meta/info.json").read_text())
    data = pq.read_table(out / info["data_path"].format(chunk_index=0, file_index=0)).to_pydict()
    eps = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert info["total_episodes"] == 2 and len(eps) == 2 and info["fps"] == fps
    assert ("observation.images.endo" in info["features"]) == cameras
    ep_col = np.array(data["episode_index"])
    ts = np.array(data["timestamp"], dtype=float)
    state = np.array(data["observation.state"], dtype=float)
    action = np.array(data["action"], dtype=float)
    frames: list[np.ndarray] = []
    if cameras:
        video = out / info["video_path"].format(
            video_key="observation.images.endo", chunk_index=0, file_index=0
        )
        with av.open(str(video)) as c:
            frames = [f.to_ndarray(format="rgb24").astype(np.float32) for f in c.decode(video=0)]
        assert len(frames) == info["total_frames"]
    # LeRobot's own reader: the same episodes, rows and frames (its video decoder, torchcodec,
    # seeks each frame by the row's timestamp); what follows checks its rows
    lr = read_with_lerobot(out)
    meta = lr["meta"]
    assert meta["num_episodes"] == 2 and meta["num_frames"] == len(ts) and meta["fps"] == fps, meta
    assert meta["lengths"] == [int(np.count_nonzero(ep_col == e["episode_index"])) for e in eps], meta
    assert meta["start_ns"] == [e["telesurg/start_ns"] for e in eps], meta
    assert len(meta["tasks"]) == 1 and meta["tasks"][0], f"LeRobot found no task text: {meta['tasks']}"
    assert np.array_equal(lr["episode_index"], ep_col) and np.array_equal(lr["index"], data["index"])
    assert np.allclose(lr["timestamp"], ts, atol=1e-6)
    assert np.array_equal(lr["state"], state.astype(np.float32)), "LeRobot reads other joint states"
    assert np.array_equal(lr["action"], action.astype(np.float32)), "LeRobot reads other actions"
    state, action = lr["state"].astype(float), lr["action"].astype(float)
    if cameras:
        lr_frames = lr["frames/observation.images.endo"].astype(np.float32)
        assert lr_frames.shape == (len(frames), *frames[0].shape), lr_frames.shape
        # the same picture as PyAV's sequential decode (LeRobot rounds through float in [0, 1])
        diff = max(float(np.abs(a - b).mean()) for a, b in zip(lr_frames, frames, strict=True))
        assert diff < 1.0, f"LeRobot decodes other frames than PyAV (mean |Δ| up to {diff:.2f} levels)"
        frames = list(lr_frames)
    print(
        f"LeRobotDataset: {meta['num_episodes']} episodes, {meta['num_frames']} frames at "
        f"{meta['fps']:g} fps, lengths {meta['lengths']}, task {meta['tasks'][0]!r}"
    )
    decoded = [simplejpeg.decode_jpeg(m.data, colorspace="RGB").astype(np.float32) for _t, m in images]
    image_t = np.array([t for t, _m in images], dtype=np.int64)
    chosen: dict[int, int] = {}  # dataset index → capture ns of the image the export says it took
    if cameras:
        times = pq.read_table(out / "meta/telesurg/image_times.parquet").to_pydict()
        chosen = dict(zip(times["index"], times["capture_ns"], strict=True))
    period_ns = 1e9 / fps
    worst_video = worst_state = worst_action = 0.0
    offsets: list[float] = []  # ms: each frame's image capture − the frame's instant
    gaps = 0  # rows with no camera frame within one frame period of their instant
    for e, (a, b) in zip(eps, periods, strict=True):
        rows = np.flatnonzero(ep_col == e["episode_index"])
        duration = (b - a) / 1e9
        print(f"episode {e['episode_index']}: engaged {duration:.2f} s, {len(rows)} frames at {fps:g} fps")
        assert abs(len(rows) - duration * fps) <= 1, (len(rows), duration)
        start = e["telesurg/start_ns"]
        assert a <= start < a + period_ns
        for r in rows:
            t = start + round(ts[r] * 1e9)
            # the state: the measured joints the slave had at the frame's instant
            t_js, m_js = _at(js, t)
            assert np.allclose(state[r, :6], m_js.position, atol=1e-6)  # type: ignore[attr-defined]
            worst_state = max(worst_state, (t - t_js) / 1e6)
            # the action: the mapping's target at the frame's instant, within 0.01 mm
            _t_tg, m_tg = _at(target, t)
            err = float(np.linalg.norm(action[r, :3] - np.array(m_tg.position)))  # type: ignore[attr-defined]
            worst_action = max(worst_action, err * 1e3)
            if not cameras:
                continue
            # the video frame: the recorded camera frames nearest in content, among those captured
            # within 1 s of the row (indistinguishable ones: a still or slow arm, whose neighbouring
            # frames differ by less than the video codec's own error, so within 10 % of the best
            # match's error); the nearest in time of them was captured within one frame period of
            # the row's instant
            f = frames[r]
            near = np.flatnonzero(np.abs(image_t - t) < 1e9)
            mse = np.array([np.mean((f - decoded[i]) ** 2) for i in near])
            close = near[mse <= 1.1 * mse.min() + 0.5]
            i = min(close, key=lambda i: abs(t - image_t[i]))
            offset = (image_t[i] - t) / 1e6
            assert chosen[int(data["index"][r])] in image_t[close]  # the export's record is true
            if abs(offset) >= period_ns / 1e6 and not np.any(np.abs(image_t - t) < period_ns):
                gaps += 1  # the camera sent nothing within a frame period (reported, then failed)
            offsets.append(offset)
            worst_video = max(worst_video, abs(offset))
    video = ""
    if offsets:
        o = np.array(offsets)
        video = (
            f"video frames captured {o.min():+.1f} … {o.max():+.1f} ms from their rows' instants "
            f"(|offset| ≤ {worst_video:.1f} ms, median {np.median(np.abs(o)):.1f} ms; "
            f"{gaps} of {len(o)} rows in a camera gap longer than a frame period, "
            f"{period_ns / 1e6:.0f} ms), "
        )
    print(
        f"alignment: joint state ≤ {worst_state:.1f} ms before the frame, {video}"
        f"action ≤ {worst_action:.5f} mm from the recorded target"
    )
    assert worst_state < period_ns / 1e6
    assert gaps == 0, f"{gaps} rows with no camera frame within one frame period"
    assert worst_video < period_ns / 1e6, "video frames not within one frame period"
    assert worst_action < 0.01
    return {"state_ms": worst_state, "video_ms": worst_video, "action_mm": worst_action}
