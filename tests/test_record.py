"""Record (MCAP) and replay: unit tests of the file layout and the counts, process tests on a pipeline.

The process tests share one recording (module fixture): a pipeline without its master, the
recorder started, *then* master_capture — so the file begins with the slave at home, before the
first clutch press, and replaying its master streams into a fresh pipeline must reproduce the
slave's motion.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from telesurg.services.record import (
    MESSAGE_ENCODING,
    RECORDING_METADATA,
    SCHEMA_ENCODING,
    Recorder,
    SeqCheck,
    iter_decoded,
    json_schema,
    open_mcap,
    read_metadata,
    read_summary,
)
from telesurg.services.record.replay import EXIT_NEVER_ENGAGED, Response, compare, fell_behind, verdict
from telesurg.shared.messages import (
    MESSAGE_TYPES,
    CartesianPose,
    Header,
    JointSetpoint,
    JointState,
    MasterButtons,
    decode,
)
from telesurg.tools.bench.harness import Pipeline

ROOT = Path(__file__).resolve().parents[1]
PREFIX = "telesurg/t/"
JOINTS = ("j1", "j2", "j3", "j4", "j5", "j6")


# --------------------------------------------------------------------------- unit


def _pose(src: str, seq: int) -> bytes:
    h = Header(src, seq, 1_700_000_000_000_000_000 + seq * 2_000_000)
    return CartesianPose(h, "master", (0.01 * seq, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)).encode()


def test_mcap_is_byte_exact_with_channels_schemas_and_counts(tmp_path: Path) -> None:
    cfg = tmp_path / "mapping.toml"
    cfg.write_text("scale = 0.5\n")
    pushed: list[tuple[str, bytes, int]] = []
    t = 1_800_000_000_000_000_000

    def push(key: str, payload: bytes) -> None:
        nonlocal t
        t += 1_000_000
        pushed.append((PREFIX + key, payload, t))
        rec.push(payload, PREFIX + key, t)

    path = tmp_path / "x.mcap"
    with Recorder(path, "t", attachments=[cfg], info={"note": "unit"}) as rec:
        for seq in (0, 1, 2, 5, 5, 6):  # a gap of two (3, 4 lost) and a duplicate (5)
            push("master/m1/measured_cp", _pose("master_capture", seq))
        for seq in (0, 1):  # a second publisher on the same key: its own sequence
            push("master/m1/measured_cp", _pose("impostor", seq))
        for seq in (0, 2, 1, 3):  # one late message: a gap that is filled, i.e. reordered
            h = Header("master_capture", seq, 1_700_000_000_000_000_000 + seq)
            push("master/m1/buttons", MasterButtons(h, seq > 1, True).encode())
        for seq in range(10):
            h = Header("slave_control", seq, 1_700_000_000_000_000_000 + seq)
            push("slave/arm1/measured_js", JointState(h, JOINTS, (0.1 * seq,) * 6).encode())
        h = Header("mapping", 0, 1_700_000_000_000_000_000)
        push("slave/arm1/servo_jp", JointSetpoint(h, JOINTS, (0.0,) * 6, follow=True).encode())
        push("slave/arm1/servo_jp", b"\xc1 not msgpack")
        summary = rec.close()

    with open_mcap(path) as reader:
        got = list(iter_decoded(reader))
        s = reader.get_summary()
        assert s is not None
        channels = {c.topic: c for c in s.channels.values()}
        schemas = {c.topic: s.schemas[c.schema_id] for c in s.channels.values()}
        meta = read_metadata(reader, RECORDING_METADATA)
        stored = read_summary(reader)
        attachments = list(reader.iter_attachments())
        assert s.statistics is not None and s.statistics.message_count == len(pushed)

    # every payload byte-exact, in order; log time = receive time, publish time = header stamp
    assert [(k, d, lt) for k, lt, _pt, d, _m in got] == pushed
    for _k, lt, pt, d, m in got:
        assert pt == (m.header.stamp_ns if m is not None else lt)
        assert m is None or m.encode() == d
    # one channel per key, msgpack; one schema per type, generated from the dataclass
    assert set(channels) == {k for k, _, _ in pushed}
    assert all(c.message_encoding == MESSAGE_ENCODING for c in channels.values())
    assert {k[len(PREFIX) :]: sc.name for k, sc in schemas.items()} == {
        "master/m1/measured_cp": "telesurg.pose",
        "master/m1/buttons": "telesurg.buttons",
        "slave/arm1/measured_js": "telesurg.joint_state",
        "slave/arm1/servo_jp": "telesurg.servo_jp",
    }
    js = json.loads(schemas[PREFIX + "slave/arm1/measured_js"].data)
    assert all(sc.encoding == SCHEMA_ENCODING for sc in schemas.values())
    assert js["required"] == ["v", "type", "src", "seq", "ts", "name", "position", "velocity", "effort"]
    assert js["properties"]["position"]["items"] == {"type": "number"}
    assert "rad" in js["properties"]["position"]["description"]
    assert meta["site"] == "t" and meta["note"] == "unit"
    assert [(a.name, a.data) for a in attachments] == [(str(cfg), b"scale = 0.5\n")]

    # the counts, as returned and as stored in the file
    assert stored == json.loads(json.dumps(summary))
    cp = stored["master/m1/measured_cp"]
    assert cp["messages"] == 8 and cp["gaps"] == 1 and cp["lost"] == 2 and cp["duplicates"] == 1
    assert cp["sources"]["impostor"] == {
        "messages": 2,
        "gaps": 0,
        "lost": 0,
        "reordered": 0,
        "duplicates": 0,
        "restarts": 0,
    }
    b = stored["master/m1/buttons"]
    assert (b["gaps"], b["lost"], b["reordered"], b["duplicates"]) == (1, 0, 1, 0)
    m = stored["slave/arm1/measured_js"]
    assert (m["messages"], m["gaps"], m["lost"], m["reordered"], m["duplicates"]) == (10, 0, 0, 0, 0)
    assert stored["slave/arm1/servo_jp"]["undecodable"] == 1
    assert stored["slave/arm1/servo_jp"]["types"] == ["servo_jp"]


def test_seq_check_restart_and_late_first() -> None:
    s = SeqCheck()
    for seq in (10, 11, 9, 12, 0, 1, 1):  # 9: older than the first seen; 0: publisher restart
        s.add(seq)
    assert s.counts() == {
        "messages": 7,
        "gaps": 0,
        "lost": 0,
        "reordered": 1,
        "duplicates": 1,
        "restarts": 1,
    }


@pytest.mark.parametrize("tag", sorted(MESSAGE_TYPES))
def test_schema_matches_the_decoder(tag: str) -> None:
    cls = MESSAGE_TYPES[tag]
    schema = json_schema(cls)
    assert set(schema["properties"]) == {"v", "type", "src", "seq", "ts"} | cls.BODY
    assert schema["properties"]["type"]["const"] == tag
    # a default message decodes, and every value has the JSON type the schema gives it
    d = msgpack.unpackb(cls(Header("x", 0, 0)).encode())
    kinds = {"string": str, "boolean": bool, "integer": int, "number": (int, float), "array": list}
    for key, value in d.items():
        prop = schema["properties"][key]
        if "type" in prop:
            assert isinstance(value, kinds[prop["type"]]), (key, value)


def _response(t: np.ndarray, q: np.ndarray, follow: list[tuple[float, bool, str]]) -> Response:
    return Response(("a", "b"), list(t), [tuple(r) for r in q], follow=follow)


def test_compare_reports_per_joint_rms_and_max() -> None:
    t = np.linspace(0.0, 4.0, 401)
    rec = _response(t, np.column_stack([np.sin(t), np.cos(t)]), [(0.5, True, "")])
    tl = t[::3] + 0.001  # sparser, slightly shifted: interpolation, not sample matching
    live = _response(tl, np.column_stack([np.sin(tl), np.cos(tl) + 0.02]), [(0.52, True, "")])
    r = compare(rec, live)
    assert r["samples"] > 390 and r["live_follow_s"] == 0.52 and r["diverged_s"] is None
    assert r["joints"]["a"]["rms_rad"] < 2e-3
    assert abs(r["joints"]["b"]["rms_rad"] - 0.02) < 2e-3
    assert abs(r["max_rad"] - 0.02) < 3e-3
    assert r["full"]["samples"] == r["samples"]
    other = Response(("x", "y"), list(tl), [tuple(r) for r in np.zeros((tl.size, 2))])
    assert compare(rec, other)["samples"] == 0


def test_compare_stops_where_one_run_held() -> None:
    t = np.linspace(0.0, 4.0, 401)
    q = np.column_stack([t, -t])
    rec = _response(t, q, [(0.5, True, "")])
    q_live = q.copy()
    q_live[t > 2.0] = q[t == 2.0]  # the live slave stops at 2 s ...
    live = _response(t, q_live, [(0.5, True, ""), (2.0, False, "lease: HOLD: stale")])  # ... held
    r = compare(rec, live)
    assert r["diverged_s"] == pytest.approx(2.0, abs=0.02)
    assert "live: follow=False" in r["diverged_because"] and "stale" in r["diverged_because"]
    assert r["max_rad"] < 0.03  # up to the hold: the same motion
    assert r["full"]["max_rad"] > 1.9  # afterwards the runs differ by the motion not made


def test_compare_stops_where_the_replay_fell_behind() -> None:
    # 250 Hz sends: on time, one 80 ms hiccup (a single late message), then a 1.3 s stall at 2 s
    t = np.arange(0.0, 4.0, 0.004)
    late = np.full(t.size, 0.2)
    late[250] = 80.0
    stall = (t >= 2.0) & (t < 2.5)
    late[stall] = 1300.0 - (t[stall] - 2.0) * 1e3
    sends = list(zip(t.tolist(), late.tolist(), strict=True))
    behind = fell_behind(sends, 50.0)
    assert behind is not None and behind[0] == pytest.approx(2.0, abs=0.005)
    assert "1300 ms late" in behind[1] and "could not keep pace" in behind[1]
    assert fell_behind(sends[:400], 50.0) is None  # the hiccup alone: still comparable
    tr = np.linspace(0.0, 4.0, 401)
    q = np.column_stack([tr, -tr])
    rec = _response(tr, q, [(0.5, True, "")])
    live = _response(tr, q + np.where(tr > 2.0, 0.5, 0.0)[:, None], [(0.5, True, "")])
    r = compare(rec, live, behind)
    assert r["diverged_s"] == behind[0] and r["diverged_because"] == behind[1]
    assert r["max_rad"] < 1e-9 and r["full"]["max_rad"] > 0.4  # compared only while on time


# --------------------------------------------------------------------------- process


def _wait_alive(p: Pipeline, service: str, timeout: float) -> bool:
    key = p.node.keys.alive(service)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(r.ok is not None for r in p.node.session.liveliness().get(key, timeout=0.5)):
            return True
        time.sleep(0.1)
    return False


def _stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _logs(d: Path) -> None:
    for f in sorted(d.glob("*.log")):
        print(f"--- {f.name}\n{f.read_text()[-2000:]}")


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    tmp = tmp_path_factory.mktemp("record")
    out = tmp / "run.mcap"
    argv = [sys.executable, "-m", "telesurg.services.record", "--out", str(out), "--seconds", "10"]
    argv += ["--attach", str(ROOT / "deploy/local/site.toml")]
    with Pipeline(tmp / "logs", mirror=False, impair=False, master=False, probe=False) as p:
        rec = subprocess.Popen(
            [*argv, "--connect", p.spec.endpoint],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            assert _wait_alive(p, "record", 30), "the recorder never came on the bus"
            p.site.restart("master_capture")  # first start: the master begins once the recorder listens
            text, _ = rec.communicate(timeout=90)
        finally:
            _stop(rec)
    print(text)
    _logs(tmp / "logs")
    assert rec.returncode == 0
    yield out


@pytest.mark.process
def test_record_a_running_pipeline(recording: Path) -> None:
    with open_mcap(recording) as reader:
        summary = read_summary(reader)
        per_key: dict[str, int] = {}
        for topic, *_ in iter_decoded(reader):
            per_key[topic] = per_key.get(topic, 0) + 1
        names = [a.name for a in reader.iter_attachments()]
    for key, row in summary.items():
        print(
            f"{key:<32} {row['messages']:>6} msgs {row['rate_hz']:>7.1f} Hz  gaps {row['gaps']} "
            f"lost {row['lost']} reordered {row['reordered']} dup {row['duplicates']}"
        )
    assert {k.removeprefix("telesurg/local/"): n for k, n in per_key.items()} == {
        k: r["messages"] for k, r in summary.items()
    }
    cp = summary["master/m1/measured_cp"]
    assert cp["messages"] > 1000 and cp["sources"].keys() == {"master_capture"}
    for key in ("master/m1/measured_cp", "master/m1/buttons"):
        r = summary[key]
        assert (r["reordered"], r["duplicates"], r["undecodable"]) == (0, 0, 0), (key, r)
        # the recorder is an observer: the router drops samples for it rather than hold up the
        # master when this 2-core host leaves it behind (11–242 of ~10,000 seen under load, on the
        # code before and after issue #39; counted in the summary); more would be a broken stream
        assert r["lost"] <= 0.03 * r["messages"], (key, r)
    assert summary["slave/arm1/measured_js"]["messages"] > 500
    assert names == [str(ROOT / "deploy/local/site.toml")]


def _recorded(path: Path, key: str) -> list[Any]:
    with open_mcap(path) as reader:
        return [m for t, *_, m in iter_decoded(reader, lambda t: t.endswith(key)) if m is not None]


@pytest.mark.process
def test_replay_reproduces_the_slave_response(recording: Path, tmp_path: Path) -> None:
    counts = {k: len(_recorded(recording, k)) for k in ("master/m1/measured_cp", "master/m1/buttons")}
    # A CPU stall on this 2-core host can make the watchdog hold one run and not the other (the
    # safe response); the comparison stops there. At least 1 s of following must be compared:
    # like a user, replay again (into a fresh pipeline) when a hold, or the replay itself falling
    # behind the recording's timing, cut the comparison short.
    for attempt in range(1, 6):
        out = tmp_path / f"attempt{attempt}"
        report_path, live = out / "diff.json", out / "live.mcap"
        argv = [
            sys.executable,
            "-m",
            "telesurg.services.record.replay",
            str(recording),
            "--json",
            str(report_path),
        ]
        argv += ["--record", str(live)]
        with Pipeline(out / "logs", mirror=False, impair=False, master=False, probe=False) as p:
            r = subprocess.run(
                [*argv, "--connect", p.spec.endpoint],
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=120,
            )
        print(r.stdout, r.stderr[-3000:])
        _logs(out / "logs")
        assert r.returncode == 0
        report = json.loads(report_path.read_text())
        arm = report["arms"]["arm1"]
        assert report["sent"] == counts  # every recorded master message went out once

        # The same clutch press engaged both runs.
        assert arm["recorded_follow_s"] is not None and arm["live_follow_s"] is not None
        assert abs(arm["recorded_follow_s"] - arm["live_follow_s"]) < 0.2
        end = arm["diverged_s"] if arm["diverged_s"] is not None else float("inf")
        print(
            f"attempt {attempt}: compared {arm['span_s']} s, diverged at {arm['diverged_s']}: "
            f"{arm['diverged_because']}"
        )
        if end > arm["recorded_follow_s"] + 1.0:
            break
    assert end > arm["recorded_follow_s"] + 1.0
    t0 = _recorded(recording, "master/m1/measured_cp")[0].header.stamp_ns
    q = np.array(
        [
            m.position
            for m in _recorded(recording, "slave/arm1/measured_js")
            if m.header.source == "slave_control" and 0 <= (m.header.stamp_ns - t0) / 1e9 <= end
        ]
    )
    travel = np.ptp(q, axis=0)
    print("recorded slave travel in the compared window [rad]:", np.round(travel, 4))
    assert travel.max() > 0.02, "the slave barely moved in the compared window: nothing to compare"
    assert set(arm["joints"]) == set(JOINTS) and arm["samples"] > 150
    for name, j in arm["joints"].items():
        print(f"{name}: RMS {j['rms_rad']:.5f} rad, max {j['max_rad']:.5f} rad")
    assert all(j["rms_rad"] < 0.01 for j in arm["joints"].values())
    # what a user sees: the forceps tip of the replayed run against the recorded one
    tip_rms = _tip_rms_mm(recording, live, arm["recorded_follow_s"], end)
    print(f"tip RMS difference replay vs recording over the compared window: {tip_rms:.3f} mm")
    # a busy host delays one run more than the other (0.33 mm measured on an idle one); the
    # changed workspace limit below moves the tip by ~15 mm
    assert tip_rms < 1.0


def _tips(path: Path) -> np.ndarray:
    """(t since the first master sample, x, y, z) of the slave tip, s and m."""
    t0 = _recorded(path, "master/m1/measured_cp")[0].header.stamp_ns
    rows = [
        ((m.header.stamp_ns - t0) / 1e9, *m.position)
        for m in _recorded(path, "slave/arm1/measured_cp")
        if m.header.source == "slave_control"
    ]
    return np.array(rows)


def _tip_rms_mm(recorded: Path, live: Path, t_from: float, t_to: float) -> float:
    a, b = _tips(recorded), _tips(live)
    sel = a[(a[:, 0] >= t_from) & (a[:, 0] <= min(t_to, b[-1, 0]))]
    want = np.stack([np.interp(sel[:, 0], b[:, 0], b[:, i]) for i in (1, 2, 3)], axis=1)
    return float(np.sqrt(np.mean(np.sum((sel[:, 1:] - want) ** 2, axis=1)))) * 1e3


@pytest.mark.process
def test_replay_through_a_changed_limit_shows_the_difference(recording: Path, tmp_path: Path) -> None:
    """The regression-test use: the same recorded session through a pipeline whose workspace
    limit was tightened (y ≤ 5 mm): the replay reports the slave's response as different."""
    report_path = tmp_path / "diff.json"
    argv = [
        sys.executable,
        "-m",
        "telesurg.services.record.replay",
        str(recording),
        "--json",
        str(report_path),
    ]
    argv += ["--max-rms", "0"]  # the difference is the point here: judged below, not by the exit code
    tight = {"mapping": ["workspace_max_mm=[1100.0, 5.0, 800.0]"]}
    with Pipeline(
        tmp_path / "logs", mirror=False, impair=False, master=False, probe=False, overrides=tight
    ) as p:
        r = subprocess.run(
            [*argv, "--connect", p.spec.endpoint], cwd=ROOT, capture_output=True, text=True, timeout=120
        )
    print(r.stdout, r.stderr[-3000:])
    assert r.returncode == 0
    arm = json.loads(report_path.read_text())["arms"]["arm1"]
    worst = max(j["max_rad"] for j in arm["joints"].values())
    print(f"changed limit: largest joint difference {worst:.4f} rad (diverged: {arm['diverged_because']})")
    assert worst > 0.02  # the clamped target shows up (measured 0.044 rad; unchanged runs stay below 0.009)


@pytest.mark.process
def test_to_rerun_without_network(recording: Path, tmp_path: Path) -> None:
    import pyarrow as pa
    from helpers import entity_paths, scalar_counts, text_logs
    from rerun.chunk import RrdReader
    from telesurg.services.mirror.view import joints_path

    rrd = tmp_path / "run.rrd"
    r = subprocess.run(
        [sys.executable, "-m", "telesurg.services.record.replay", str(recording), "--to-rerun", str(rrd)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    print(r.stdout, r.stderr[-2000:])
    assert r.returncode == 0 and rrd.stat().st_size > 0
    # rerun's own reader loads the whole file; every slave joint sample is there once, on both
    # timelines: source_time = the header stamp, receive_time = the recorder's log time
    js = [m for m in _recorded(recording, "slave/arm1/measured_js") if m.header.source == "slave_control"]
    path = joints_path("arm1", "measured")
    assert scalar_counts(rrd)[path] == len(js)
    stamps: list[int] = []
    for chunk in RrdReader(str(rrd)).stream():
        if chunk.entity_path == path and "Scalars:scalars" in chunk.to_record_batch().schema.names:
            batch = chunk.to_record_batch()  # (the series' names and colours: a static chunk)
            assert "receive_time" in batch.schema.names
            stamps += batch.column("source_time").cast(pa.int64()).to_pylist()
    assert sorted(stamps) == sorted(m.header.stamp_ns for m in js)
    assert {
        "/master/m1/tip",
        "/master/m1/clutch",
        "/slave/arm1/tip",
        "/slave/geometry/mh3f",
    } <= entity_paths(rrd)
    logs = text_logs(rrd)
    assert any(p == "/events" and "engage" in text for p, _, text in logs)
    assert any(p == "/safety/arm1/state" for p, _, _ in logs)


def test_undecodable_means_what_the_strict_decoder_rejects(tmp_path: Path) -> None:
    """Valid MessagePack that fails validation (empty source) counts as undecodable too."""
    pose = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)
    good = CartesianPose(Header("master_capture", 0, 1), "master", *pose).encode()
    bad = CartesianPose(Header("", 1, 2), "master", *pose).encode()
    assert decode(good).header.source == "master_capture"
    with Recorder(tmp_path / "x.mcap", "t") as rec:
        rec.push(good, PREFIX + "master/m1/measured_cp", 1)
        rec.push(bad, PREFIX + "master/m1/measured_cp", 2)
        summary = rec.close()
    row = summary["master/m1/measured_cp"]
    assert (row["messages"], row["undecodable"], row["sources"]["master_capture"]["messages"]) == (2, 1, 1)


def test_schema_carries_the_declared_rules() -> None:
    lease = json_schema(MESSAGE_TYPES["lease"])["properties"]
    assert lease["valid_for_ms"]["exclusiveMinimum"] == 0 and lease["valid_for_ms"]["maximum"] == 10_000
    assert lease["arm"]["minLength"] == 1 and "ms" in lease["valid_for_ms"]["description"]
    state = json_schema(MESSAGE_TYPES["safety_state"])["properties"]["state"]
    assert state["enum"] == ["DEGRADED", "ESTOP", "HOLD", "OK"]
    names = json_schema(MESSAGE_TYPES["servo_jp"])["properties"]["name"]
    assert (names["minItems"], names["maxItems"], names["uniqueItems"]) == (1, 32, True)


# --------------------------------------------------------------------------- replay pre-flight


def _replay(recording: Path, endpoint: str, *extra: str) -> subprocess.CompletedProcess[str]:
    argv = [sys.executable, "-m", "telesurg.services.record.replay", str(recording), *extra]
    r = subprocess.run([*argv, "--connect", endpoint], cwd=ROOT, capture_output=True, text=True, timeout=120)
    print(r.stdout, r.stderr[-3000:])
    return r


def _trim(src: Path, dst: Path, from_log_ns: int) -> None:
    """Copy the recording from ``from_log_ns`` on (schemas, channels, metadata and attachments as
    they are): a recording that starts in the middle of a session."""
    from mcap.writer import Writer

    with open_mcap(src) as reader, dst.open("wb") as f:
        summary = reader.get_summary()
        assert summary is not None
        w = Writer(f)
        header = reader.get_header()
        w.start(header.profile, header.library)
        schemas = {0: 0} | {
            sid: w.register_schema(sc.name, sc.encoding, sc.data) for sid, sc in summary.schemas.items()
        }
        ids = {
            cid: w.register_channel(ch.topic, ch.message_encoding, schemas[ch.schema_id], ch.metadata)
            for cid, ch in summary.channels.items()
        }
        for m in reader.iter_metadata():
            w.add_metadata(m.name, m.metadata)
        for _schema, ch, msg in reader.iter_messages(log_time_order=True):
            if msg.log_time >= from_log_ns:
                w.add_message(ids[ch.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
        w.finish()


def test_verdict_names_a_replay_that_never_engaged() -> None:
    arm = {"recorded_follow_s": 1.0, "live_follow_s": None, "samples": 0, "rms_max_rad": None}
    code, why = verdict({"arms": {"arm1": arm}}, 0.02)
    assert code == EXIT_NEVER_ENGAGED and "never engaged (arm1)" in why
    arm |= {"live_follow_s": 1.1, "samples": 300, "rms_max_rad": 0.03}
    assert verdict({"arms": {"arm1": arm}}, 0.02)[0] == 3
    assert verdict({"arms": {"arm1": arm}}, 0.05) == (0, "")
    assert verdict({"arms": {"arm1": arm}}, 0.0) == (0, "")  # --max-rms 0: off


@pytest.mark.process
def test_replay_refuses_a_site_where_master_capture_runs(recording: Path, tmp_path: Path) -> None:
    with Pipeline(tmp_path / "logs", mirror=False, impair=False, master=True, probe=True) as p:
        assert p.wait(lambda: bool(p.p.tips().size), 30)
        n_before = len(p.p.tips())
        r = _replay(recording, p.spec.endpoint)
        assert r.returncode == 2
        assert "master_capture is alive on site 'local'" in r.stderr
        assert "replaying" not in r.stderr  # refused before anything was published
        time.sleep(0.3)
        assert len(p.p.tips()) > n_before  # the site goes on as it was


@pytest.mark.process
def test_replay_of_a_recording_that_starts_with_the_pedal_held_engages(
    recording: Path, tmp_path: Path
) -> None:
    with open_mcap(recording) as reader:
        press = next(
            lt
            for _t, lt, _pt, _d, m in iter_decoded(reader, lambda t: t.endswith("master/m1/buttons"))
            if isinstance(m, MasterButtons) and m.clutch
        )
    held = tmp_path / "held.mcap"
    _trim(recording, held, press + 200_000_000)  # 0.2 s into the first press
    with open_mcap(held) as reader:
        first = next(m for *_, m in iter_decoded(reader, lambda t: t.endswith("/buttons")))
    assert isinstance(first, MasterButtons) and first.clutch  # the file starts held
    report_path = tmp_path / "diff.json"
    with Pipeline(tmp_path / "logs", mirror=False, impair=False, master=False, probe=False) as p:
        r = _replay(held, p.spec.endpoint, "--json", str(report_path), "--max-rms", "0")
    assert r.returncode == 0
    assert "starts with the clutch pedal held" in r.stderr
    report = json.loads(report_path.read_text())
    assert report["synthesized_release"] == ["master/m1/buttons"]
    assert report["arms"]["arm1"]["live_follow_s"] is not None  # it engaged


@pytest.mark.process
def test_replay_that_never_engages_exits_non_zero(recording: Path, tmp_path: Path) -> None:
    report_path = tmp_path / "diff.json"
    with Pipeline(tmp_path / "logs", mirror=False, impair=False, master=False, probe=True) as p:
        assert p.wait(lambda: p.p.safety_state() != "", 30)
        p.estop("estop")  # latched: every engage the replay tries is refused
        assert p.wait(lambda: p.p.safety_state() == "ESTOP", 5)
        r = _replay(recording, p.spec.endpoint, "--json", str(report_path))
    assert r.returncode == EXIT_NEVER_ENGAGED
    assert "never engaged" in r.stderr
    report = json.loads(report_path.read_text())
    assert report["arms"]["arm1"]["live_follow_s"] is None
    assert report["verdict"]["exit"] == EXIT_NEVER_ENGAGED
