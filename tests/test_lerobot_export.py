"""``telesurg export --to lerobot``: a made recording (the real Recorder, real JPEG frames) as a
LeRobotDataset v3.0, read back with pyarrow and PyAV (the ``lerobot-dataset`` reader pins PyAV < 16
and cannot install beside telesurg's); and bad input: one line on stderr, exit 1, nothing written.

The live-site version (two clutch engagements of a real site with its camera) is
``tests/test_docs_recipes.py`` (``test_recording_to_dataset_to_a_policy_run_as_written``).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from telesurg.services.record import Recorder
from telesurg.services.record.export import main
from telesurg.shared.messages import (
    CameraImage,
    CartesianPose,
    CartesianWrench,
    Header,
    JointState,
    OperatingState,
)

JOINTS = ("j1", "j2", "j3", "j4", "j5", "j6")
PREFIX = "telesurg/t/"
T0 = 1_800_000_000_000_000_000
MS = 1_000_000
ENGAGED = ((1000, 2500), (3500, 5000))  # ms: the two follow periods


def _jpeg(level: int) -> bytes:
    import simplejpeg

    img = np.full((48, 64, 3), level, dtype=np.uint8)
    return bytes(simplejpeg.encode_jpeg(img, quality=95, colorspace="RGB"))


def make_recording(
    path: Path,
    *,
    engaged: tuple[tuple[int, int], ...] = ENGAGED,
    camera: bool = True,
    camera_ms: Sequence[int] = range(0, 6000, 50),
) -> None:
    """6 s of an arm: joints 250 Hz (j1 = t in s; a look-alike publisher's too), tip and state 50 Hz,
    the mapping's target 50 Hz while engaged (x = 1 + t), the camera captured at ``camera_ms``
    (multiples of 4 ms; default 20 Hz; grey level = capture ms // 50 × 10, at most 250)."""
    seq: dict[str, int] = {}
    captures = set(camera_ms)

    def put(key: str, make: object, t_ms: float, src: str) -> None:
        n = seq.get(key, 0)
        seq[key] = n + 1
        stamp = T0 + round(t_ms * MS)
        msg = make(Header(src, n, stamp))  # type: ignore[operator]
        rec.push(msg.encode(), PREFIX + key, stamp + 100_000)

    with Recorder(path, "t") as rec:
        for t in range(0, 6000, 4):  # ms
            put(
                "slave/arm1/measured_js",
                lambda h, t=t: JointState(h, JOINTS, (t / 1e3,) + (0.0,) * 5),
                t,
                "slave_control",
            )
            if t % 20 == 0:
                put("slave/arm1/measured_js", lambda h: JointState(h, JOINTS, (0.0,) * 6), t, "impostor")
                follow = any(a <= t < b for a, b in engaged)
                put(
                    "slave/arm1/measured_cp",
                    lambda h, t=t: CartesianPose(h, "base", (t / 1e3, 0.0, 0.2)),
                    t,
                    "slave_control",
                )
                put(
                    "slave/arm1/measured_cf",
                    lambda h: CartesianWrench(h, "base", (1.0, 2.0, 3.0)),
                    t,
                    "slave_control",
                )
                put(
                    "slave/arm1/operating_state",
                    lambda h, f=follow: OperatingState(h, "ENABLED", "joint", follow=f, rcm_error_mm=0.5),
                    t,
                    "slave_control",
                )
                if any(a - 5 <= t < b for a, b in engaged):
                    put(
                        "slave/arm1/setpoint_cp",
                        lambda h, t=t: CartesianPose(h, "base", (1.0 + t / 1e3, 0.0, 0.1)),
                        t,
                        "mapping",
                    )
            if camera and t in captures:
                i = t // 50
                put(
                    "camera/endo/image",
                    lambda h, i=i, t=t: CameraImage(
                        h, "endo", T0 + round(t * MS), 64, 48, data=_jpeg(min(250, i * 10))
                    ),
                    t,
                    "camera",
                )


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("lerobot") / "run.mcap"
    make_recording(path)
    return path


def _read_frames(video: Path) -> list[np.ndarray]:
    import av

    with av.open(str(video)) as c:
        return [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]


def test_two_engagements_make_two_episodes_read_back_with_pyarrow_and_pyav(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = tmp_path / "ds"
    assert main([str(recording), "--to", "lerobot", str(out), "--fps", "10", "--task", "reach"]) == 0
    info = json.loads((out / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 10 and info["total_episodes"] == 2
    assert set(info["features"]) >= {
        "observation.state",
        "observation.tip_wrench",
        "observation.rcm_error_mm",
        "observation.images.endo",
        "action",
        "timestamp",
        "frame_index",
        "episode_index",
        "index",
        "task_index",
    }
    assert info["features"]["observation.state"]["shape"] == [13]
    data = pq.read_table(out / info["data_path"].format(chunk_index=0, file_index=0)).to_pydict()
    eps = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    tasks = pq.read_table(out / "meta/tasks.parquet")
    assert tasks.to_pylist() == [{"task_index": 0, "task": "reach"}]
    # as LeRobot reads them (pandas): the tasks indexed by their text, a one-element feature a scalar
    assert tasks.schema.pandas_metadata["index_columns"] == ["task"]
    assert (
        pq.read_schema(out / info["data_path"].format(chunk_index=0, file_index=0))
        .field("observation.rcm_error_mm")
        .type
        == pa.float32()
    )
    # 1.5 s engaged at 10 fps: 15 frames each, frame k at start + k/10 s
    assert [e["length"] for e in eps] == [15, 15]
    assert [e["telesurg/start_ns"] for e in eps] == [T0 + 1000 * MS, T0 + 3500 * MS]
    ep = np.array(data["episode_index"])
    ts = np.array(data["timestamp"])
    state = np.array(data["observation.state"])
    action = np.array(data["action"])
    for e, (a, _b) in zip(eps, ENGAGED, strict=True):
        rows = ep == e["episode_index"]
        t_ms = a + ts[rows] * 1e3
        assert np.allclose(ts[rows], np.arange(15) / 10, atol=1e-6)
        # joints: the newest sample at or before the frame (j1 = t); tip x = t
        assert np.allclose(state[rows, 0], t_ms / 1e3, atol=1e-6)
        assert np.allclose(state[rows, 6], t_ms / 1e3, atol=1e-6)
        assert np.allclose(action[rows, 0], 1.0 + t_ms / 1e3, atol=1e-6)
        assert np.allclose(action[rows, 3:], [0, 0, 0, 1])
    assert np.allclose(np.array(data["observation.tip_wrench"])[:, :3], [1, 2, 3])
    assert np.array(data["index"]).tolist() == list(range(30))
    # the video: 30 frames, each the newest camera frame at or before its row (grey = 10 × 50 ms steps)
    frames = _read_frames(out / "videos/observation.images.endo/chunk-000/file-000.mp4")
    assert len(frames) == 30 and frames[0].shape == (48, 64, 3)
    expect = np.concatenate([np.minimum(250, (a + np.arange(15) * 100) // 50 * 10) for a, _b in ENGAGED])
    got = np.array([f.mean() for f in frames])
    assert np.max(np.abs(got - expect)) < 3, (got, expect)
    assert eps[1]["videos/observation.images.endo/from_timestamp"] == pytest.approx(1.5)
    stats = json.loads((out / "meta/stats.json").read_text())
    assert stats["observation.state"]["count"] == [30]
    assert np.allclose(stats["action"]["min"][:3], action[:, :3].min(axis=0), atol=1e-6)
    assert "wrote" in capsys.readouterr().out


def test_each_frame_gets_the_image_captured_nearest_to_it_and_the_offsets_are_kept(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A 10 Hz camera that captures 28 ms after each frame instant, silent for 0.3 s in the first
    episode: every frame shows the image nearest to it (not the newest earlier one, 72 ms older);
    the frames in the silence are counted (warning, episode metadata, info.json) and each frame's
    offset is in meta/telesurg/image_times.parquet."""
    import pyarrow.parquet as pq

    gap = (1428, 1528, 1628)
    run = tmp_path / "late.mcap"
    make_recording(run, camera_ms=[t for t in range(28, 6000, 100) if t not in gap])
    out = tmp_path / "ds"
    with caplog.at_level("WARNING", logger="telesurg.export"):
        assert main([str(run), "--to", "lerobot", str(out), "--fps", "10"]) == 0
    warned = [r.getMessage() for r in caplog.records if "within one frame period" in r.getMessage()]
    assert len(warned) == 1 and "2 of 15 frames" in warned[0], warned
    times = pq.read_table(out / "meta/telesurg/image_times.parquet").to_pydict()
    assert len(times["index"]) == 30 and set(times["camera"]) == {"endo"}
    eps = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    starts = [e["telesurg/start_ns"] for e in eps]
    frame_ms = np.array(
        [
            (starts[e] - T0) / MS + k * 100
            for e, k in zip(times["episode_index"], times["frame_index"], strict=True)
        ]
    )
    capture_ms = (np.array(times["capture_ns"]) - T0) / MS
    offset = np.array(times["offset_ms"])
    assert np.allclose(capture_ms - frame_ms, offset)
    # outside the silence: the image 28 ms after the frame; in it, the nearest on either side
    silent = {1400: -72.0, 1500: -172.0, 1600: 128.0}
    expect = np.array([silent.get(int(f), 28.0) for f in frame_ms])
    assert np.allclose(offset, expect), (frame_ms, offset)
    frames = _read_frames(out / "videos/observation.images.endo/chunk-000/file-000.mp4")
    got = np.array([f.mean() for f in frames])
    assert np.max(np.abs(got - np.minimum(250, capture_ms // 50 * 10))) < 3
    key = "observation.images.endo"
    assert [e[f"telesurg/images_beyond_one_period/{key}"] for e in eps] == [2, 0]
    assert [e[f"telesurg/max_image_offset_ms/{key}"] for e in eps] == pytest.approx([172.0, 28.0])
    info = json.loads((out / "meta/info.json").read_text())
    assert info["telesurg"]["images"][key] == {
        "max_offset_ms": 172.0,
        "frames_beyond_one_period": 2,
        "per_frame": "meta/telesurg/image_times.parquet",
    }


def test_several_recordings_make_one_dataset(recording: Path, tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    out = tmp_path / "ds"
    assert (
        main([str(recording), str(recording), "--to", "lerobot", str(out), "--fps", "20", "--no-video"]) == 0
    )
    info = json.loads((out / "meta/info.json").read_text())
    assert info["total_episodes"] == 4 and info["total_frames"] == 4 * 30
    assert "observation.images.endo" not in info["features"] and not (out / "videos").exists()
    eps = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [e["dataset_from_index"] for e in eps] == [0, 30, 60, 90]


def _bad(argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> str:
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("telesurg export: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written, no temp left
    return err


def test_bad_input_says_one_line_and_writes_nothing(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = str(tmp_path / "ds")
    rec = str(recording)
    assert "camera 'side'" in _bad([rec, "--to", "lerobot", out, "--camera", "side"], tmp_path, capsys)
    assert "cameras recorded: endo" in _bad(
        [rec, "--to", "lerobot", out, "--camera", "nope"], tmp_path, capsys
    )
    assert "fps must be > 0" in _bad([rec, "--to", "lerobot", out, "--fps", "0"], tmp_path, capsys)
    assert "fps must be > 0" in _bad([rec, "--to", "lerobot", out, "--fps", "-5"], tmp_path, capsys)
    assert "no such recording" in _bad(["nope.mcap", "--to", "lerobot", out], tmp_path, capsys)

    damaged = tmp_path / "damaged.mcap"
    data = recording.read_bytes()
    damaged.write_bytes(data[: len(data) // 3])
    assert "cannot read" in _bad([str(damaged), "--to", "lerobot", out], tmp_path, capsys)
    empty = tmp_path / "empty.mcap"
    with Recorder(empty, "t"):
        pass
    assert "no slave arm" in _bad([str(empty), "--to", "lerobot", out], tmp_path, capsys)
    idle = tmp_path / "idle.mcap"
    make_recording(idle, engaged=(), camera=False)
    assert "no engaged period" in _bad([str(idle), "--to", "lerobot", out], tmp_path, capsys)
    nocam = tmp_path / "nocam.mcap"
    make_recording(nocam, camera=False)
    assert "cameras recorded: none" in _bad(
        [str(nocam), "--to", "lerobot", out, "--camera", "endo"], tmp_path, capsys
    )
    # one damaged file among good ones spoils the whole dataset
    assert "cannot read" in _bad([rec, str(damaged), "--to", "lerobot", out], tmp_path, capsys)
    # an existing folder is never written into
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "mine.txt").write_text("keep")
    assert "exists" in _bad([rec, "--to", "lerobot", out], tmp_path, capsys)
    assert (tmp_path / "ds" / "mine.txt").read_text() == "keep"
