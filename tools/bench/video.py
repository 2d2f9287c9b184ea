"""``telesurg bench video``: the endoscope video's cost and latency, and what it does to the
control path, camera off and on in one run.

Alternating blocks (``--blocks`` each, ``--seconds`` long) of the real pipeline (deploy/local:
master_capture at ``--rate`` → mapping → slave_control, watchdog) without and with the camera
service. Per camera-on block, a subscriber in this process (the surgeon's console stand-in) takes
every frame: fps delivered, the camera's own render and encode time (carried in each frame), the
transport time (arrival − the frame's publish stamp), the JPEG decode time here (simplejpeg), the
frame age capture → arrival (p50/p99), bandwidth, frames dropped by the camera and lost in
sequence. For every block: the control path's one-way latency master → setpoint applied in the
slave's loop (p50/p99, as ``telesurg bench latency``), the slave's and master's deadline misses
(their own counters at exit), CPU % per process (psutil) and the watchdog's holds. The ratio of
the control path's p99 with the camera on to off is the figure of issue #18 (goal ≤ 1.2).

Nothing here asserts a time: the figures are printed and written (``--json``, e.g.
``docs/data/perf/video.json``); docs/video.md discusses them.

Example::

    telesurg bench video --seconds 10 --blocks 2 --json docs/data/perf/video.json
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.tools.bench.machine import machine, now
from telesurg.tools.bench.perf import _overrides, _stats_ms, deadline_misses, watchdog_holds


class FrameProbe:
    """Every frame of ``camera/<cam>/image``, timed on arrival and decoded as a console would."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.rows: list[tuple[int, int, int, float, float, float, int, int, int]] = []

    def on_frame(self, msg: Any, key: str) -> None:
        import simplejpeg

        rx = time.time_ns()
        t0 = time.perf_counter()
        simplejpeg.decode_jpeg(msg.data, colorspace="RGB")
        decode_ms = (time.perf_counter() - t0) * 1e3
        with self.lock:
            self.rows.append(
                (
                    rx,
                    msg.capture_ns,
                    msg.header.stamp_ns,
                    msg.render_ms,
                    msg.encode_ms,
                    decode_ms,
                    len(msg.data),
                    msg.header.seq,
                    msg.dropped,
                )
            )


def _block(camera: bool, a: argparse.Namespace, tmp: Path, k: int) -> dict[str, Any]:
    psutil: Any = importlib.import_module("psutil")  # (no type stubs)
    from telesurg.shared.messages import CameraImage
    from telesurg.tools.bench.harness import Pipeline

    npy = tmp / f"applied{k}.npy"
    extra: dict[str, list[str]] = {"slave_control": [f"latency_log={json.dumps(str(npy))}"]}
    if camera:
        extra["camera"] = [f"fps={a.fps}", f"width={a.width}", f"height={a.height}"]
    overrides = _overrides(a.rate, None, **extra)
    logs = tmp / f"logs{k}"
    probe = FrameProbe()
    with Pipeline(logs, mirror=False, impair=False, probe=False, overrides=overrides, camera=camera) as p:
        if camera:
            assert p._node is not None
            p._node.subscribe(p._node.keys.camera("endo", "image"), CameraImage, probe.on_frame)
        started = camera and "camera" not in p.site.off
        load0 = os.getloadavg()[0]
        procs = {n: psutil.Process(pr.pid) for n, pr in p.site.procs.items()}
        procs["bench (frame subscriber)"] = psutil.Process(os.getpid())
        time.sleep(1.0)  # engaged (pedal from 0.5 s), frames flowing
        with probe.lock:
            probe.rows.clear()
        for pr in procs.values():
            pr.cpu_percent(None)
        time.sleep(a.seconds)
        cpu = {n: round(pr.cpu_percent(None), 1) for n, pr in procs.items()}
        with probe.lock:
            rows = np.array(probe.rows, dtype=float) if probe.rows else np.zeros((0, 9))
        t_stop = time.time()
        p.close()
    applied: np.ndarray = np.load(npy)
    applied = applied[(applied[:, 0] > 0) & (applied[:, 1] > 0)]
    applied = applied[len(applied) // 5 :]  # the start-up transient
    text = {f.stem: f.read_text() for f in logs.glob("*.log")}
    misses = deadline_misses(text)
    out: dict[str, Any] = {
        "camera": camera,
        "camera_started": started,  # False: it did not come up within 30 s (this block is left out)
        "load_avg_1min": [round(load0, 2), round(os.getloadavg()[0], 2)],  # host load at start / end
        "control_end_to_end": _stats_ms(applied[:, 2] - applied[:, 0]),
        "deadline_misses": misses,
        "cpu_pct": cpu,
        "watchdog_holds": len(watchdog_holds(text.get("watchdog", ""), t_stop)),
        "watchdog_hold_causes": watchdog_holds(text.get("watchdog", ""), t_stop),
    }
    if camera and len(rows):
        span_s = (rows[-1, 0] - rows[0, 0]) / 1e9 if len(rows) > 1 else a.seconds
        seqs = rows[:, 7]
        out["video"] = {
            "frames": len(rows),
            "fps_delivered": round(len(rows) / a.seconds, 2),
            "render_ms": _stats_ms(rows[:, 3] * 1e6),
            "encode_ms": _stats_ms(rows[:, 4] * 1e6),
            "transport_ms": _stats_ms(rows[:, 0] - rows[:, 2]),
            "decode_ms": _stats_ms(rows[:, 5] * 1e6),
            "age_ms": _stats_ms(rows[:, 0] - rows[:, 1]),
            "bytes_per_frame_mean": round(float(rows[:, 6].mean()), 1),
            "bandwidth_kbit_s": round(float(rows[:, 6].sum()) * 8 / 1e3 / max(span_s, 1e-9), 1),
            "dropped_by_camera": int(rows[-1, 8] - rows[0, 8]),
            "lost_in_sequence": int(seqs[-1] - seqs[0] + 1 - len(np.unique(seqs))),
        }
    return out


def _print(res: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    con = Console()
    t = Table(title="control path, master → setpoint applied (ms)")
    for c in ("block", "camera", "n", "p50", "p99", "slave miss %", "master miss %", "holds", "load"):
        t.add_column(c, justify="right")
    for i, b in enumerate(res["blocks"]):
        e, mi = b["control_end_to_end"], b["deadline_misses"]
        t.add_row(
            str(i),
            ("on" if b["camera_started"] else "failed") if b["camera"] else "off",
            str(e.get("n", 0)),
            f"{e.get('p50', float('nan')):.3f}",
            f"{e.get('p99', float('nan')):.3f}",
            str(mi.get("slave_control", {}).get("miss_pct", "")),
            str(mi.get("master_capture", {}).get("miss_pct", "")),
            str(b["watchdog_holds"]),
            f"{b['load_avg_1min'][0]:.1f}",
        )
    con.print(t)
    v = res.get("video")
    if v:
        t = Table(title=f"video {res['width']}x{res['height']} at {res['fps']:g} fps configured")
        t.add_column("")
        for c in ("p50 ms", "p99 ms", "max ms"):
            t.add_column(c, justify="right")
        for name in ("render_ms", "encode_ms", "transport_ms", "decode_ms", "age_ms"):
            s = v[name]
            t.add_row(name[:-3], *(f"{s.get(x, float('nan')):.2f}" for x in ("p50", "p99", "max")))
        con.print(t)
        print(
            f"fps delivered {v['fps_delivered']}, {v['bytes_per_frame_mean']:.0f} B/frame, "
            f"{v['bandwidth_kbit_s']:.0f} kbit/s, dropped by the camera {v['dropped_by_camera']}, "
            f"lost in sequence {v['lost_in_sequence']}"
        )
    print("CPU % per process (camera on, last block):", res.get("cpu_pct_camera_on"))
    print(
        f"control-path p99 camera on / off: × {res['p99_ratio_on_off']} "
        f"(p50 × {res['p50_ratio_on_off']}; goal p99 ≤ × 1.2)"
    )


def run(a: argparse.Namespace) -> dict[str, Any]:
    res: dict[str, Any] = {
        "rate_hz": a.rate,
        "seconds_per_block": a.seconds,
        "blocks_each": a.blocks,
        "fps": a.fps,
        "width": a.width,
        "height": a.height,
        "blocks": [],
    }
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        k = 0
        for _ in range(a.blocks):
            for camera in (False, True):
                res["blocks"].append(_block(camera, a, tmp, k))
                k += 1
    on = [b for b in res["blocks"] if b["camera"] and b["camera_started"]]
    off = [b for b in res["blocks"] if not b["camera"]]

    def mean(blocks: list[dict[str, Any]], q: str) -> float:
        return float(np.mean([b["control_end_to_end"].get(q, np.nan) for b in blocks]))

    for q in ("p50", "p99"):
        res[f"control_{q}_ms_camera_off"] = round(mean(off, q), 4)
        res[f"control_{q}_ms_camera_on"] = round(mean(on, q), 4)
        res[f"{q}_ratio_on_off"] = round(mean(on, q) / mean(off, q), 3)
    videos = [b["video"] for b in on if "video" in b]
    if videos:
        res["video"] = videos[-1]
        res["video"]["fps_delivered_mean"] = round(float(np.mean([v["fps_delivered"] for v in videos])), 2)
    res["cpu_pct_camera_on"] = on[-1]["cpu_pct"] if on else {}
    res["cpu_pct_camera_off"] = off[-1]["cpu_pct"] if off else {}
    _print(res)
    return res


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bench video``."""
    ap = argparse.ArgumentParser(prog="telesurg bench video", description=__doc__)
    ap.add_argument("--json", type=Path, help="write the figures here (e.g. docs/data/perf/video.json)")
    ap.add_argument("--rate", type=float, default=1000.0, help="master rate, Hz (default 1000)")
    ap.add_argument("--seconds", type=float, default=10.0, help="length of each block, s")
    ap.add_argument("--blocks", type=int, default=2, help="camera-off / camera-on blocks, each")
    ap.add_argument("--fps", type=float, default=12.0, help="camera frame rate (default: the service's 12)")
    ap.add_argument("--width", type=int, default=320, help="px")
    ap.add_argument("--height", type=int, default=240, help="px")
    a = ap.parse_args(argv)
    res = run(a)
    res["date"], res["machine"] = now(), machine()
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(res, indent=2) + "\n")
    return 0
