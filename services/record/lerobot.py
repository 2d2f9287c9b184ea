"""``telesurg export --to lerobot``: recordings as one LeRobotDataset (v3.0 layout) for robot learning.

Each engaged period of a recording — the slave's ``operating_state.follow`` true: the mapping
commands it and it tracks — is one episode. Episodes are resampled at ``fps`` on the recording's
own clock (the header stamps, wall clock ns; a camera frame by its ``capture_ns``): frame ``k`` of an
episode is at ``t0 + k / fps`` and holds, for every joint, pose and wrench stream, the **newest
sample stamped at or before it** (zero-order hold: what a policy running at ``fps`` would have seen),
and for every camera the **image captured nearest to it** (the camera runs best-effort, off the
control loops' clock: a newest-earlier image would be up to a camera period old even when the
camera keeps its rate). Each frame's image offset (capture − frame instant) is kept in
``meta/telesurg/image_times.parquet``; the export warns about frames without an image within one
frame period. ``t0`` is the first instant of the engaged period at which every exported stream has
a sample of that period; the episode ends before the follow flag drops.

Features (all float32, SI units, the slave's ``base`` frame):

* ``observation.state`` — the measured joints (``slave/<arm>/measured_js``, rad / m), then the
  measured tip pose (``measured_cp``: x y z in m, quaternion x y z w as the messages carry it);
* ``observation.tip_wrench`` — ``measured_cf`` (N, N·m), when the recording has it;
* ``observation.rcm_error_mm`` — ``operating_state.rcm_error_mm``, when it is not always 0;
* ``observation.images.<cam>`` — the endoscope's frames, one MP4 (H.264) per camera;
* ``action`` — the tip pose the mapping commanded (``slave/<arm>/setpoint_cp``: the master's tip
  moved by the clutch, scale and frame change into the slave's frame; x y z, quaternion x y z w).

Layout (LeRobotDataset v3.0): ``meta/info.json`` (features, fps, paths), ``meta/tasks.parquet``,
``meta/episodes/chunk-000/file-000.parquet`` (per episode: length, tasks, index ranges, video
timestamps, statistics, and the source file and start time), ``meta/stats.json``,
``data/chunk-000/file-000.parquet`` (one row a frame),
``videos/observation.images.<cam>/chunk-000/file-000.mp4`` (every episode's frames in order) and,
telesurg's own, ``meta/telesurg/image_times.parquet`` (per frame and camera: the image's capture time
and its offset from the frame's instant).

The dataset is written into a temporary folder beside ``OUT`` and renamed when complete: bad input
leaves nothing behind.

Example::

    telesurg export run1.mcap run2.mcap --to lerobot dataset/ --fps 30 --camera endo --task "reach"
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import tempfile
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.services.record import iter_decoded, open_mcap, recording_site
from telesurg.shared.errors import TelesurgError
from telesurg.shared.keys import Keys
from telesurg.shared.messages import (
    CameraImage,
    CartesianPose,
    CartesianWrench,
    JointState,
    OperatingState,
)

log = logging.getLogger("telesurg.export")

CODEBASE_VERSION = "v3.0"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
#: per frame and camera: the chosen image's capture time and offset (telesurg's, not LeRobot's)
IMAGE_TIMES_PATH = "meta/telesurg/image_times.parquet"
CHUNKS_SIZE = 1000  # files per chunk folder (LeRobot's default; one file here)
#: the services whose slave/, mapping and camera streams are exported (as the mirror trusts them)
TRUSTED = frozenset({"slave_control", "mapping", "camera"})
POSE_NAMES = ("x", "y", "z", "qx", "qy", "qz", "qw")
WRENCH_NAMES = ("fx", "fy", "fz", "tx", "ty", "tz")
VIDEO_CODEC = "libx264"  # H.264, yuv420p: decodable by PyAV / torchcodec / any player
DEFAULT_TASK = "telesurg teleoperation"
#: ns: the mapping's first target of an engagement precedes the slave's follow flag by at most this
ENGAGE_LEAD_NS = 200_000_000


class DatasetError(TelesurgError, ValueError):
    """The recordings cannot make a dataset (the message says which and why)."""


@dataclass
class Series:
    """One stream's samples in stamp order: times (ns) and values."""

    t: list[int] = field(default_factory=list)
    v: list[Any] = field(default_factory=list)

    def add(self, t: int, v: Any) -> None:
        if self.t and t < self.t[-1]:  # out of order (two paths): keep the order by stamp
            i = bisect_right(self.t, t)
            self.t.insert(i, t)
            self.v.insert(i, v)
        else:
            self.t.append(t)
            self.v.append(v)

    def at(self, t: int) -> int:
        """Index of the newest sample stamped at or before ``t`` (-1: none)."""
        return bisect_right(self.t, t) - 1

    def nearest(self, t: int) -> int:
        """Index of the sample stamped nearest to ``t`` (the earlier of two as near; -1: none)."""
        i = bisect_right(self.t, t)
        if i == 0:
            return 0 if self.t else -1
        if i < len(self.t) and self.t[i] - t < t - self.t[i - 1]:
            return i
        return i - 1


@dataclass
class Recording:
    """What one recording holds for the dataset."""

    path: Path
    arm: str = ""
    names: tuple[str, ...] = ()
    js: Series = field(default_factory=Series)
    cp: Series = field(default_factory=Series)
    cf: Series = field(default_factory=Series)
    op: Series = field(default_factory=Series)  # (follow, rcm_error_mm)
    target: Series = field(default_factory=Series)
    images: dict[str, Series] = field(default_factory=dict)  # camera → (jpeg bytes, w, h)


def _tasks_table(tasks: list[str]) -> Any:
    """``meta/tasks.parquet``: LeRobot reads it with pandas as a frame indexed by the task's text
    with one column, ``task_index``; the index is declared in the schema's pandas metadata (the
    format pandas writes, https://pandas.pydata.org/docs/development/developer.html)."""
    import pyarrow as pa

    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": tasks})
    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [],
        "columns": [
            {
                "name": "task_index",
                "field_name": "task_index",
                "pandas_type": "int64",
                "numpy_type": "int64",
                "metadata": None,
            },
            {
                "name": "task",
                "field_name": "task",
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": None,
            },
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.3",
    }
    return table.replace_schema_metadata({"pandas": json.dumps(pandas_meta)})


def read_recording(path: Path, arm: str | None) -> Recording:
    """The slave, mapping and camera streams of ``path`` (DatasetError if it has no arm)."""
    rec = Recording(path)
    with open_mcap(path) as reader:
        prefix = Keys(recording_site(reader)).prefix + "/"
        for topic, _lt, _pt, _data, msg in iter_decoded(reader):
            if msg is None or not topic.startswith(prefix) or msg.header.source not in TRUSTED:
                continue
            parts = topic[len(prefix) :].split("/")
            if len(parts) != 3:
                continue
            role, who, stream = parts
            if role == "camera" and stream == "image" and isinstance(msg, CameraImage):
                if msg.encoding == "jpeg":
                    rec.images.setdefault(who, Series()).add(
                        msg.capture_ns or msg.header.stamp_ns, (msg.data, msg.width, msg.height)
                    )
                continue
            if role != "slave":
                continue
            mine = arm is None or who == arm
            if not rec.arm and mine and stream == "measured_js" and isinstance(msg, JointState):
                rec.arm, rec.names = who, msg.names
            if who != (rec.arm or arm):
                continue
            t = msg.header.stamp_ns
            if stream == "measured_js" and isinstance(msg, JointState) and msg.names == rec.names:
                rec.js.add(t, msg.position)
            elif stream == "measured_cp" and isinstance(msg, CartesianPose):
                rec.cp.add(t, (*msg.position, *msg.orientation))
            elif stream == "measured_cf" and isinstance(msg, CartesianWrench):
                rec.cf.add(t, (*msg.force, *msg.torque))
            elif stream == "operating_state" and isinstance(msg, OperatingState):
                rec.op.add(t, (msg.follow, msg.rcm_error_mm))
            elif stream == "setpoint_cp" and isinstance(msg, CartesianPose):
                rec.target.add(t, (*msg.position, *msg.orientation))
    if not rec.arm:
        which = f"arm {arm!r}" if arm else "slave arm"
        raise DatasetError(f"{path}: no {which} measured_js in the recording (empty or not a telesurg site)")
    return rec


def engaged_periods(op: Series) -> list[tuple[int, int]]:
    """[start, end) ns of each run of ``follow`` true (an open run ends at the last state)."""
    out: list[tuple[int, int]] = []
    start: int | None = None
    for t, (follow, _rcm) in zip(op.t, op.v, strict=True):
        if follow and start is None:
            start = t
        elif not follow and start is not None:
            out.append((start, t))
            start = None
    if start is not None and op.t and op.t[-1] > start:
        out.append((start, op.t[-1]))
    return out


@dataclass
class Episode:
    """One resampled episode: frame times and the rows of each feature."""

    source: Path
    start_ns: int
    times_ns: np.ndarray  # (n,) the frames' instants on the recording's clock
    columns: dict[str, np.ndarray]  # feature → (n, dim) float32
    frames: dict[str, list[int]]  # camera → index into the recording's images, per frame
    # camera → per frame: its image's capture time − the frame's instant (ms; < 0: older)
    image_offset_ms: dict[str, np.ndarray] = field(default_factory=dict)


def episodes_of(
    rec: Recording, fps: float, cameras: Sequence[str], with_cf: bool, with_rcm: bool
) -> list[Episode]:
    """The recording's engaged periods resampled at ``fps`` (see the module doc)."""
    period_ns = 1e9 / fps
    streams: list[Series] = [rec.js, rec.cp, rec.target] + [rec.images[c] for c in cameras]
    if with_cf:
        streams.append(rec.cf)
    out = []
    prev_off = 0
    for on, off in engaged_periods(rec.op):
        # the first instant every stream has a sample: the measured streams' first ever (a held
        # sample from before the engage is what the slave measured then), the mapping's target's
        # first of this engagement (it may precede the slave's follow flag by a few ms)
        lower = max(prev_off, on - ENGAGE_LEAD_NS)
        prev_off = off
        i = bisect_right(rec.target.t, lower)
        if i >= len(rec.target.t) or not all(s.t for s in streams):
            continue
        firsts = [on, rec.target.t[i]] + [s.t[0] for s in streams if s is not rec.target]
        t0 = max(firsts)
        n = math.floor((off - 1 - t0) / period_ns) + 1 if off > t0 else 0
        if n <= 0:
            continue
        times = t0 + np.round(np.arange(n) * period_ns).astype(np.int64)
        cols: dict[str, np.ndarray] = {}
        js_i = [rec.js.at(int(t)) for t in times]
        cp_i = [rec.cp.at(int(t)) for t in times]
        cols["observation.state"] = np.array(
            [(*rec.js.v[a], *rec.cp.v[b]) for a, b in zip(js_i, cp_i, strict=True)], dtype=np.float32
        )
        if with_cf:
            cols["observation.tip_wrench"] = np.array(
                [rec.cf.v[rec.cf.at(int(t))] for t in times], dtype=np.float32
            )
        if with_rcm:
            cols["observation.rcm_error_mm"] = np.array(
                [[rec.op.v[rec.op.at(int(t))][1]] for t in times], dtype=np.float32
            )
        cols["action"] = np.array([rec.target.v[rec.target.at(int(t))] for t in times], dtype=np.float32)
        frames = {c: [rec.images[c].nearest(int(t)) for t in times] for c in cameras}
        offsets = {
            c: np.array([(rec.images[c].t[i] - int(t)) / 1e6 for t, i in zip(times, frames[c], strict=True)])
            for c in cameras
        }
        for c, offset in offsets.items():
            late = int(np.count_nonzero(np.abs(offset) > 1e3 / fps))
            if late:
                log.warning(
                    "%s: camera %s: %d of %d frames of the episode at %d ns have no image within one "
                    "frame period (%.0f ms; up to %.0f ms off): a starved camera, or --fps above its rate",
                    rec.path,
                    c,
                    late,
                    n,
                    t0,
                    1e3 / fps,
                    float(np.abs(offset).max()),
                )
        out.append(Episode(rec.path, int(t0), times, cols, frames, offsets))
    return out


def _stats(x: np.ndarray) -> dict[str, list[Any]]:
    """min, max, mean, std and count of (n, dim) rows, per dimension."""
    x = x.astype(np.float64)
    return {
        "min": x.min(axis=0).tolist(),
        "max": x.max(axis=0).tolist(),
        "mean": x.mean(axis=0).tolist(),
        "std": x.std(axis=0).tolist(),
        "count": [int(x.shape[0])],
    }


def _image_stats(sums: np.ndarray, sq: np.ndarray, lo: np.ndarray, hi: np.ndarray, n: int) -> dict[str, Any]:
    """Per-channel statistics of RGB images scaled to [0, 1], shaped (3, 1, 1) as LeRobot keeps them."""
    mean = sums / n
    std = np.sqrt(np.maximum(sq / n - mean**2, 0.0))

    def c(v: np.ndarray) -> list[Any]:
        return [[[float(a)]] for a in v]

    return {"min": c(lo), "max": c(hi), "mean": c(mean), "std": c(std), "count": [n]}


def _merge_stats(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Statistics of the union of episodes from each episode's (pooled mean and variance)."""
    n = np.array([p["count"][0] for p in parts], dtype=np.float64)
    mean = np.array([p["mean"] for p in parts], dtype=np.float64)
    var = np.array([p["std"] for p in parts], dtype=np.float64) ** 2
    w = n.reshape((-1,) + (1,) * (mean.ndim - 1)) / n.sum()
    m = (w * mean).sum(axis=0)
    v = (w * (var + (mean - m) ** 2)).sum(axis=0)
    return {
        "min": np.min(np.array([p["min"] for p in parts]), axis=0).tolist(),
        "max": np.max(np.array([p["max"] for p in parts]), axis=0).tolist(),
        "mean": m.tolist(),
        "std": np.sqrt(v).tolist(),
        "count": [int(n.sum())],
    }


def _decode_jpeg(data: bytes) -> np.ndarray:
    import simplejpeg

    img: np.ndarray = simplejpeg.decode_jpeg(data, colorspace="RGB")
    return img


def to_lerobot(
    sources: Sequence[str | Path],
    out: str | Path,
    *,
    fps: float = 30.0,
    cameras: Sequence[str] | None = None,
    task: str = DEFAULT_TASK,
    arm: str | None = None,
) -> dict[str, Any]:
    """Write the dataset folder ``out`` from the recordings ``sources``; a summary.

    Args:
        fps: frames a second of the dataset (> 0).
        cameras: cameras to export as videos; None = every camera the first recording has
            (none if it has none); each named camera must be in every recording.
        task: the task text of every episode.
        arm: the slave arm (None: the first arm with joint states).

    Raises:
        DatasetError: bad input (nothing is written).
    """
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as e:
        raise DatasetError(
            f"--to lerobot needs the 'learn' extra ({e}): pip install 'telesurg[learn]'"
        ) from e
    if not (fps > 0 and math.isfinite(fps)):
        raise DatasetError(f"fps must be > 0 (got {fps:g})")
    out = Path(out)
    if out.exists():
        raise DatasetError(f"{out} exists: choose a new folder (a dataset is never merged into another)")
    if not sources:
        raise DatasetError("no recording given")
    recs: list[Recording] = []
    for src in sources:
        p = Path(src)
        if not p.is_file():
            raise DatasetError(f"no such recording: {p}")
        try:
            recs.append(read_recording(p, arm))
        except DatasetError:
            raise
        except Exception as e:  # a damaged file: say which and why
            raise DatasetError(f"cannot read {p}: {type(e).__name__}: {e}") from e
    first = recs[0]
    cams = sorted(first.images) if cameras is None else list(dict.fromkeys(cameras))
    for r in recs:
        if r.names != first.names or r.arm != first.arm:
            raise DatasetError(
                f"{r.path}: arm {r.arm} {list(r.names)} differs from "
                f"{first.path}'s {first.arm} {list(first.names)}"
            )
        for c in cams:
            if c not in r.images:
                have = ", ".join(sorted(r.images)) or "none"
                raise DatasetError(f"{r.path}: no frames of camera {c!r} (cameras recorded: {have})")
        if not r.js.t or not r.cp.t:
            raise DatasetError(f"{r.path}: no measured joints or tip pose of arm {r.arm}")
    with_cf = all(r.cf.t for r in recs)
    with_rcm = any(v[1] != 0.0 for r in recs for v in r.op.v)
    episodes: list[Episode] = []
    for r in recs:
        eps = episodes_of(r, fps, cams, with_cf, with_rcm)
        if not eps:
            raise DatasetError(
                f"{r.path}: no engaged period (the slave never followed the master with a commanded "
                f"target{' and camera frames' if cams else ''})"
            )
        episodes.extend(eps)
    sizes = {c: first.images[c].v[0][1:] for c in cams}
    for r in recs:
        for c in cams:
            if r.images[c].v[0][1:] != sizes[c]:
                raise DatasetError(f"{r.path}: camera {c} is {r.images[c].v[0][1:]}, not {sizes[c]}")

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent))
    try:
        summary = _write(tmp, recs, episodes, fps, cams, sizes, task, pa, pq)
        os.rename(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    log.info("wrote %s: %d episodes, %d frames", out, summary["episodes"], summary["frames"])
    return summary


def _write(
    root: Path,
    recs: list[Recording],
    episodes: list[Episode],
    fps: float,
    cams: list[str],
    sizes: dict[str, tuple[int, int]],
    task: str,
    pa: Any,
    pq: Any,
) -> dict[str, Any]:
    """Write the whole dataset under ``root``; a summary."""
    import av

    first = recs[0]
    names = list(first.names)
    state_names = names + [f"tip.{n}" for n in POSE_NAMES]
    features: dict[str, dict[str, Any]] = {
        "observation.state": {"dtype": "float32", "shape": [len(state_names)], "names": state_names},
    }
    vector_keys = ["observation.state"]
    if "observation.tip_wrench" in episodes[0].columns:
        features["observation.tip_wrench"] = {"dtype": "float32", "shape": [6], "names": list(WRENCH_NAMES)}
        vector_keys.append("observation.tip_wrench")
    if "observation.rcm_error_mm" in episodes[0].columns:
        features["observation.rcm_error_mm"] = {"dtype": "float32", "shape": [1], "names": ["rcm_error_mm"]}
        vector_keys.append("observation.rcm_error_mm")
    features["action"] = {"dtype": "float32", "shape": [7], "names": [f"target.{n}" for n in POSE_NAMES]}
    vector_keys.append("action")
    for c in cams:
        w, h = sizes[c]
        features[f"observation.images.{c}"] = {
            "dtype": "video",
            "shape": [h, w, 3],
            "names": ["height", "width", "channels"],
            "info": {
                "video.height": h,
                "video.width": w,
                "video.codec": "h264",
                "video.pix_fmt": "yuv420p",
                "video.is_depth_map": False,
                "video.fps": fps,
                "video.channels": 3,
                "has_audio": False,
            },
        }
    for k in ("timestamp",):
        features[k] = {"dtype": "float32", "shape": [1], "names": None}
    for k in ("frame_index", "episode_index", "index", "task_index"):
        features[k] = {"dtype": "int64", "shape": [1], "names": None}

    # -- videos: every episode's frames, in order, one file a camera
    video_ranges: dict[str, list[tuple[float, float]]] = {c: [] for c in cams}
    image_stats: dict[str, list[dict[str, Any]]] = {c: [] for c in cams}
    for c in cams:
        w, h = sizes[c]
        path = root / VIDEO_PATH.format(video_key=f"observation.images.{c}", chunk_index=0, file_index=0)
        path.parent.mkdir(parents=True, exist_ok=True)
        rate = _rate(fps)
        with av.open(str(path), "w") as container:
            stream: Any = container.add_stream(VIDEO_CODEC, rate=rate)
            stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
            stream.options = {"crf": "18", "g": "2", "preset": "veryfast"}
            pts = 0
            for ep in episodes:
                rec = next(r for r in recs if r.path == ep.source)
                series = rec.images[c]
                cache: dict[int, np.ndarray] = {}
                n = len(ep.times_ns)
                sums, sq = np.zeros(3), np.zeros(3)
                lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
                start = pts / fps
                for i in ep.frames[c]:
                    if i not in cache:
                        cache.clear()
                        cache[i] = _decode_jpeg(series.v[i][0])
                    img = cache[i]
                    f = img.reshape(-1, 3).astype(np.float64) / 255.0
                    sums += f.mean(axis=0)
                    sq += (f**2).mean(axis=0)
                    lo, hi = np.minimum(lo, f.min(axis=0)), np.maximum(hi, f.max(axis=0))
                    frame = av.VideoFrame.from_ndarray(img, format="rgb24")
                    frame.pts = pts
                    for packet in stream.encode(frame):
                        container.mux(packet)
                    pts += 1
                video_ranges[c].append((start, pts / fps))
                image_stats[c].append(_image_stats(sums, sq, lo, hi, n))
            for packet in stream.encode():
                container.mux(packet)

    # -- frames
    rows: dict[str, list[Any]] = {k: [] for k in features if features[k]["dtype"] != "video"}
    index = 0
    ep_rows: list[dict[str, Any]] = []
    all_stats: dict[str, list[dict[str, Any]]] = {k: [] for k in features}
    for e, ep in enumerate(episodes):
        n = len(ep.times_ns)
        ts = ((ep.times_ns - ep.start_ns) / 1e9).astype(np.float32)
        for k in vector_keys:
            rows[k].extend(ep.columns[k].tolist())
        rows["timestamp"].extend(ts.tolist())
        rows["frame_index"].extend(range(n))
        rows["episode_index"].extend([e] * n)
        rows["index"].extend(range(index, index + n))
        rows["task_index"].extend([0] * n)
        stats = {k: _stats(ep.columns[k]) for k in vector_keys}
        stats["timestamp"] = _stats(ts.reshape(-1, 1))
        stats["frame_index"] = _stats(np.arange(n).reshape(-1, 1))
        stats["episode_index"] = _stats(np.full((n, 1), e))
        stats["index"] = _stats(np.arange(index, index + n).reshape(-1, 1))
        stats["task_index"] = _stats(np.zeros((n, 1)))
        for c in cams:
            stats[f"observation.images.{c}"] = image_stats[c][e]
        for k, s in stats.items():
            all_stats[k].append(s)
        row: dict[str, Any] = {
            "episode_index": e,
            "tasks": [task],
            "length": n,
            "data/chunk_index": 0,
            "data/file_index": 0,
            "dataset_from_index": index,
            "dataset_to_index": index + n,
        }
        for c in cams:
            key = f"observation.images.{c}"
            row[f"videos/{key}/chunk_index"] = 0
            row[f"videos/{key}/file_index"] = 0
            row[f"videos/{key}/from_timestamp"] = video_ranges[c][e][0]
            row[f"videos/{key}/to_timestamp"] = video_ranges[c][e][1]
        row["meta/episodes/chunk_index"] = 0
        row["meta/episodes/file_index"] = 0
        for k, s in stats.items():
            for name, value in s.items():
                row[f"stats/{k}/{name}"] = value
        for c in cams:
            off = np.abs(ep.image_offset_ms[c])
            row[f"telesurg/max_image_offset_ms/observation.images.{c}"] = float(off.max())
            row[f"telesurg/images_beyond_one_period/observation.images.{c}"] = int(
                np.count_nonzero(off > 1e3 / fps)
            )
        row["telesurg/source"] = str(ep.source)
        row["telesurg/start_ns"] = ep.start_ns
        ep_rows.append(row)
        index += n

    def column(k: str) -> Any:
        f = features[k]
        if f["dtype"] == "int64":
            return pa.array(rows[k], type=pa.int64())
        if k == "timestamp":
            return pa.array(rows[k], type=pa.float32())
        if f["shape"] == [1]:  # LeRobot stores a one-element feature as a scalar column
            return pa.array([v[0] for v in rows[k]], type=pa.float32())
        return pa.array(rows[k], type=pa.list_(pa.float32(), f["shape"][0]))

    data_path = root / DATA_PATH.format(chunk_index=0, file_index=0)
    data_path.parent.mkdir(parents=True)
    pq.write_table(pa.table({k: column(k) for k in rows}), data_path)
    ep_path = root / EPISODES_PATH
    ep_path.parent.mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(ep_rows), ep_path)
    pq.write_table(_tasks_table([task]), root / "meta/tasks.parquet")
    if cams:  # per frame and camera: the image's capture time and its offset from the frame
        t_rows: dict[str, list[Any]] = {
            k: [] for k in ("index", "episode_index", "frame_index", "camera", "capture_ns", "offset_ms")
        }
        first_index = 0
        for e, ep in enumerate(episodes):
            n = len(ep.times_ns)
            rec = next(r for r in recs if r.path == ep.source)
            for c in cams:
                t_rows["index"].extend(range(first_index, first_index + n))
                t_rows["episode_index"].extend([e] * n)
                t_rows["frame_index"].extend(range(n))
                t_rows["camera"].extend([c] * n)
                t_rows["capture_ns"].extend(rec.images[c].t[i] for i in ep.frames[c])
                t_rows["offset_ms"].extend(ep.image_offset_ms[c].tolist())
            first_index += n
        (root / IMAGE_TIMES_PATH).parent.mkdir(parents=True)
        pq.write_table(pa.table(t_rows), root / IMAGE_TIMES_PATH)
    image_figures = {
        c: (
            float(max(np.abs(ep.image_offset_ms[c]).max() for ep in episodes)),
            sum(int(np.count_nonzero(np.abs(ep.image_offset_ms[c]) > 1e3 / fps)) for ep in episodes),
        )
        for c in cams
    }
    stats_all = {k: _merge_stats(v) for k, v in all_stats.items() if v}
    (root / "meta/stats.json").write_text(json.dumps(stats_all, indent=2) + "\n")

    def mb(folder: str) -> float:
        files = list((root / folder).rglob("*")) if (root / folder).exists() else []
        return round(sum(f.stat().st_size for f in files if f.is_file()) / 1e6, 3)

    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": _robot_type(first),
        "total_episodes": len(episodes),
        "total_frames": index,
        "total_tasks": 1,
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": mb("data"),
        "video_files_size_in_mb": mb("videos"),
        "fps": fps,
        "splits": {"train": f"0:{len(episodes)}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if cams else None,
        "features": features,
        "telesurg": {
            "arm": first.arm,
            "sources": [str(r.path) for r in recs],
            "frame": "base (the slave robot's base frame, the MuJoCo scene's world); m, rad, N, N·m",
            "alignment": (
                "frame k of an episode is at start_ns + k/fps on the recording's clock (header "
                "stamps; camera frames by capture_ns); each state, wrench and action feature holds "
                "the newest sample stamped at or before it (zero-order hold), each image is the "
                "camera frame captured nearest to it; an episode is one run of the slave's "
                "operating_state.follow, from the first instant every stream has a sample of it"
            ),
            "images": {
                f"observation.images.{c}": {
                    "max_offset_ms": round(worst, 3),
                    "frames_beyond_one_period": late,
                    "per_frame": IMAGE_TIMES_PATH,
                }
                for c, (worst, late) in image_figures.items()
            },
            "action": "slave/<arm>/setpoint_cp: the tip pose the mapping commanded (x y z, qx qy qz qw)",
        },
    }
    (root / "meta/info.json").write_text(json.dumps(info, indent=2) + "\n")
    summary: dict[str, Any] = {"episodes": len(episodes), "frames": index, "cameras": cams, "fps": fps}
    for c, (worst, late) in image_figures.items():
        summary[f"images {c}"] = (
            f"within {worst:.1f} ms of their frames, {late} beyond one frame period ({1e3 / fps:.0f} ms)"
        )
    return summary


def _rate(fps: float) -> Any:
    """The video stream's frame rate as a fraction (PyAV wants a rational)."""
    from fractions import Fraction

    return Fraction(fps).limit_denominator(1001)


def _robot_type(rec: Recording) -> str:
    from telesurg.shared import robots

    with contextlib.suppress(Exception):
        found = robots.recognise(rec.arm, rec.names)
        if found is not None:
            return found[0].name
    return "unknown"
