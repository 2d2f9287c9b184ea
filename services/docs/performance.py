"""``telesurg docs performance``: docs/performance.md, the current results of the benches.

Each :class:`Result` names a committed JSON file under ``docs/data/`` and the command that wrote
it; the page is a table of the figures read from those files, one row per result, with the
command beside them. A result file that is missing or lacks a figure fails the generation.
tests/test_docs.py fails when the committed page differs from what this writes.

Example::

    telesurg docs performance                 # rewrite docs/performance.md
    telesurg docs performance --check         # exit 1 if docs/performance.md is out of date
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: docs/ of the checkout (beside shared/ and services/).
DOCS = Path(__file__).resolve().parents[2] / "docs"
DEFAULT_OUT = DOCS / "performance.md"
TEMPLATE = Path(__file__).with_name("performance.template.md")
PLACEHOLDER = "<!-- generated: results -->"

Figures = Callable[[dict[str, Any]], str]


@dataclass(frozen=True)
class Result:
    """One row: what was measured, the figures read from ``data`` (a path under docs/), the command
    that wrote it, and where the goal it answers is judged."""

    what: str
    data: str
    command: str
    figures: Figures
    date: str = ""  # when the file records none: the date its name carries


def _q(d: dict[str, Any], *keys: str, unit: str = "ms") -> str:
    return ", ".join(f"{k} {d[k]:.3g} {unit}" for k in keys)


def _latency(d: dict[str, Any]) -> str:
    relay, pipe = d["relay"]["end_to_end"], d["pipeline"]["end_to_end"]
    out = (
        f"bare relay p50 {relay['p50']:.2f} / p99 {relay['p99']:.2f} ms; pipeline master → slave "
        f"p50 {pipe['p50']:.2f} / p99 {pipe['p99']:.2f} ms "
        f"(× {d['ratio_p50']:.1f} / × {d['ratio_p99']:.1f}); "
        f"{d['pipeline_watchdog_holds']} HOLD"
    )
    for load, ld in d.get("loaded", {}).items():
        lp = ld["pipeline"]["end_to_end"]
        out += (
            f"; under `{load}`: pipeline p50 {lp['p50']:.2f} / p99 {lp['p99']:.2f} ms "
            f"(p99 × {ld['pipeline_p99_vs_idle']:.2f} the idle one), {ld['pipeline_watchdog_holds']} HOLD"
        )
    return out


def _misses(d: dict[str, Any]) -> str:
    m = d["deadline_misses"]
    slave, master = m["slave_control"]["miss_pct"], m["master_capture"]["miss_pct"]
    return f"deadline misses slave {slave} %, master {master} %"


def _soak(d: dict[str, Any]) -> str:
    out = f"{_misses(d)}; CPU {d['cpu_total_pct']:.0f} % of one core (5 services)"
    if d.get("recorder"):
        streams = d["streams"]
        lost = sum(s["lost"] + s["reordered"] + s["duplicates"] for s in streams.values())
        out += f", recorder {d['recorder']['cpu_pct']:.0f} %"
        out += f"; {len(streams)} streams, {lost} lost/reordered/duplicated"
    out += f"; {d['watchdog_holds']} HOLD"
    for load, ld in d.get("loaded", {}).items():
        out += f"; under `{load}`: {_misses(ld)}, {ld['watchdog_holds']} HOLD"
    return out


def _arms(d: dict[str, Any]) -> str:
    rows = []
    for r in d["rows"]:
        e = r["end_to_end_ms"]
        slave = r["deadline_misses"].get("slave_control", {}).get("miss_pct", "-")
        rows.append(
            f"{r['arms']} arm{'s' if r['arms'] > 1 else ''}: CPU {r['cpu_total_pct']:.0f} %, slave misses "
            f"{slave} %, {r['watchdog_holds']} HOLD, master → slave p50 {e['p50']:.2f} / p99 "
            f"{e['p99']:.2f} ms (relay × {r['ratio_p50']:.1f} / × {r['ratio_p99']:.1f})"
        )
    slope = d["cpu_per_added_arm_pct"]
    return (
        "; ".join(rows)
        + (f"; each arm beyond the first {slope:.0f} % of a core" if slope is not None else "")
        + (
            f"; the 2 cores saturated from {d['saturated_from_arms']} arm(s)"
            if d.get("saturated_from_arms")
            else ""
        )
        + f"; largest N without a HOLD or 0.1 % misses: {d['largest_arms_without_misses']}"
    )


def _ik(d: dict[str, Any]) -> str:
    g = d["generic"]
    return (
        f"trocar IK {d['trocar_ik']['us_per_call']:.0f} µs/call ({d['trocar_ik']['batch_solves_per_s']:,} "
        f"batch solves/s), 6-axis IK {d['ik_6axis']['us_per_call']:.0f} µs, "
        f"VIP {d['vip_ik']['us_per_call']:.0f} µs, "
        f"PLAS map step {d['plas_map_step']['us_per_call']:.0f} µs; generic ({g['name'].split()[0]}) "
        f"{g['us_per_call']:.0f} µs: × {d['speedup_trocar_vs_generic']:.1f}"
    )


def _sim(d: dict[str, Any]) -> str:
    robots = [k for k, v in d.items() if isinstance(v, dict) and "realtime_factor" in v]
    return ", ".join(f"{r} × {d[r]['realtime_factor']:.0f} real time ({d[r]['dof']} DoF)" for r in robots)


def _decode(d: dict[str, Any]) -> str:
    return "; ".join(
        f"{v['type']} decode {v['decode_us']:.1f} / encode {v['encode_us']:.1f} µs"
        for v in list(d["messages"].values())[:4]
    )


def _auth(d: dict[str, Any]) -> str:
    sp = next(iter(d["messages"].values()))
    return (
        f"{sp['type']}: HMAC sign {sp['hmac_sign_us']:.1f} / verify {sp['hmac_verify_us']:.1f} µs, "
        f"two-host link sign {sp['link_sign_us']:.1f} / verify {sp['link_verify_us']:.1f} µs, "
        f"Ed25519 sign {sp['ed25519_sign_us']:.0f} / verify {sp['ed25519_verify_us']:.0f} µs; "
        f"decode {sp['decode_us']:.1f} µs"
    )


def _video(d: dict[str, Any]) -> str:
    v = d["video"]
    return (
        f"{v['fps_delivered']:.1f} fps of {d['fps']:.0f}, {d['width']}×{d['height']}; render p50 "
        f"{v['render_ms']['p50']:.1f} ms, frame age p50 {v['age_ms']['p50']:.1f} / "
        f"max {v['age_ms']['max']:.1f} ms, "
        f"{v['bandwidth_kbit_s']:.0f} kbit/s; control p99 camera on / off × {d['p99_ratio_on_off']:.2f}"
    )


def _gym(d: dict[str, Any]) -> str:
    rows = []
    for env_id, e in d["environments"].items():
        c = e["step_ms"]
        name = env_id.split("/")[-1]
        rows.append(f"{name} {c['min']:.2f} / {c['median']:.2f} / {c['max']:.2f} ms")
    return f"one step (10 ms simulated), min / median / max of {d['runs']} runs: " + "; ".join(rows)


def _viewer(d: dict[str, Any]) -> str:
    lag, wd = d["lag_s"], d["watchdog"]["arm1"]
    return (
        f"{d['window'][0]}×{d['window'][1]} ({d.get('gl') or 'swiftshader'}): lag behind live p50 "
        f"{lag['p50']:.2f} / p90 {lag['p90']:.2f} s, {lag['share_under_1s']:.0%} under 1 s, "
        f"{d['fps']['median']:.1f} frames/s; {wd['HOLD']} HOLD"
    )


def _ingest(d: dict[str, Any]) -> str:
    return (
        f"{d['kind']} at {d['rate_hz']:.0f} Hz: {d['taken_in_hz']:.1f} taken in a second, lag p50 "
        f"{d['lag_p50_s']:.2f} s, {d['fps_median']:.1f} frames/s"
    )


def _links(d: dict[str, Any]) -> str:
    return "; ".join(
        f"{link}: CPU {m['cpu']:.2f} core, p50 {m['p50_ms']:.2f} / p99 {m['p99_ms']:.2f} ms"
        for link, m in d["median"].items()
    )


def _wakeup(d: dict[str, Any]) -> str:
    return "; ".join(
        f"{load}: kernel slice p99 {v['kernel']['p99']:.0f} µs, "
        f"{d['slice_us']:.0f} µs slice p99 {v['asked']['p99']:.0f} µs"
        for load, v in d["lateness_us"].items()
    )


def _memory(d: dict[str, Any]) -> str:
    return f"{d['seconds']:.0f} s, after {d['warmup_s']:.0f} s warm-up: " + ", ".join(
        f"{p} {v['after_warmup_mb']:.0f} → {v['end_mb']:.0f} MB" for p, v in d["processes"].items()
    )


def _flood(d: dict[str, Any]) -> str:
    rss = {p: v["after_minus_before"] for p, v in d["rss_mb"].items() if v["after_minus_before"] is not None}
    return (
        f"{d['message_bytes'] // 2**20} MiB messages for {d['seconds']:.0f} s from a refused identity: "
        f"{d['holds_during_flood']} HOLD entries during it, {d['holds_quiet_window_before']} in the quiet "
        f"window before (a busy host); the flooder's link cut {d['link_cuts_flood']} times; "
        f"RSS {d['after_s']:.0f} s after: " + ", ".join(f"{p} {v:+.1f} MB" for p, v in rss.items())
    )


def _faults(d: dict[str, Any]) -> str:
    rows = d["rows"]
    held = [r for r in rows if r["expect"] == "hold"]
    worst = max(r["motion_after_detect_mm"] or 0.0 for r in held)
    detect = max(r["detect_ms"] or 0.0 for r in held)
    return (
        f"{sum(r['ok'] for r in rows)} of {len(rows)} faults handled as expected; holds detected within "
        f"{detect:.0f} ms, at most {worst:.2f} mm of motion after"
    )


def _fuzz(d: dict[str, Any]) -> str:
    return (
        f"{d['sent']:,} malformed messages, {d['crashes']} crashes, rejections as predicted: "
        f"{'yes' if d['counts_match'] else 'no'}; "
        f"{d['joint_samples_outside_limits']} joint samples outside the limits"
    )


def _attack(d: dict[str, Any]) -> str:
    rows = d["rows"]
    moved = max((r.get("motion_mm") or 0.0) for r in rows)
    ok = sum(r["ok"] for r in rows)
    return f"{ok} of {len(rows)} cases refused as expected; largest motion {moved:.1f} mm"


def _webconsole(d: dict[str, Any]) -> str:
    m, q, g = d["mouse"], d["quiet"], d["glass"]
    return (
        f"mouse → servo_jp p50 {m['latency_p50_ms']:.1f} / p99 {m['latency_p99_ms']:.1f} ms, e-stop "
        f"{m['estop_ms']:.0f} ms; page closed → HOLD {q['close_to_hold_ms']:.0f} ms; glass to glass p50 "
        f"{g['glass_to_glass_ms_p50']:.0f} ms"
        + (
            f"; predictive overlay ahead of the picture by {o['lead_ms']:.0f} ms "
            f"(page says {o['stated_ms']:.0f})"
            if (o := d.get("overlay"))
            else ""
        )
    )


P = "docs/data/perf"
RESULTS: tuple[Result, ...] = (
    Result(
        "Latency, 1 kHz, idle and beside two busy programs",
        f"{P}/latency-cpu2-1205-clean-1.json",
        "telesurg bench latency --rate 1000 --seconds 10 --blocks 4 --load cpu:2 "
        f"--json {P}/latency-cpu2-1205-clean-1.json",
        _latency,
    ),
    Result(
        "Latency, 250 Hz",
        f"{P}/latency-250.json",
        f"telesurg bench latency --rate 250 --seconds 5 --blocks 2 --json {P}/latency-250.json",
        _latency,
    ),
    Result(
        "Soak, 60 s at 1 kHz, recorder on the bus",
        f"{P}/soak.json",
        f"telesurg bench soak --rate 1000 --seconds 60 --json {P}/soak.json",
        _soak,
    ),
    Result(
        "Soak, idle and beside two busy programs",
        f"{P}/soak-cpu2-1205-clean.json",
        "telesurg bench soak --rate 1000 --seconds 60 --no-record --load cpu:2 "
        f"--json {P}/soak-cpu2-1205-clean.json",
        _soak,
    ),
    Result(
        "Arms at 1 kHz: a robot of N MH3F arms, one site",
        f"{P}/arms.json",
        f"telesurg bench arms --arms 1,2,3,4 --rate 1000 --seconds 20 --json {P}/arms.json",
        _arms,
    ),
    Result("Inverse kinematics", f"{P}/ik.json", f"telesurg bench ik --n 1000 --json {P}/ik.json", _ik),
    Result("MuJoCo, unpaced", f"{P}/sim.json", f"telesurg bench sim --seconds 3 --json {P}/sim.json", _sim),
    Result(
        "Gymnasium environments, no rendering",
        f"{P}/gym.json",
        f"telesurg bench gym --steps 2000 --runs 5 --json {P}/gym.json",
        _gym,
    ),
    Result(
        "Strict decode / encode",
        f"{P}/decode.json",
        f"telesurg bench decode --n 20000 --repeat 30 --json {P}/decode.json",
        _decode,
    ),
    Result(
        "Message authentication",
        f"{P}/auth.json",
        f"telesurg bench auth --n 2000 --repeat 60 --json {P}/auth.json",
        _auth,
    ),
    Result(
        "Endoscope video",
        f"{P}/video.json",
        f"telesurg bench video --rate 1000 --seconds 10 --blocks 2 --json {P}/video.json",
        _video,
    ),
    Result(
        "Web console (browser masters, video)",
        f"{P}/webconsole.json",
        f"TELESURG_PERF_DIR={P} .venv/bin/pytest tests/test_web_console.py",
        _webconsole,
    ),
    Result(
        "rerun web viewer in Chromium during the demo",
        f"{P}/viewer-1205d-llvmpipe-1280x720.json",
        "telesurg bench viewer --seconds 100 --window 1280x720 --gl llvmpipe "
        f"--json {P}/viewer-1205d-llvmpipe-1280x720.json",
        _viewer,
    ),
    Result(
        "rerun web viewer in Chromium during the demo",
        f"{P}/viewer-1205d-800x450-1.json",
        f"telesurg bench viewer --seconds 100 --window 800x450 --json {P}/viewer-1205d-800x450-1.json",
        _viewer,
    ),
    Result(
        "What the web viewer takes in: named-frame poses",
        f"{P}/ingest-1205-poses-30hz.json",
        f"telesurg bench ingest --kind poses --rate 30 --json {P}/ingest-1205-poses-30hz.json",
        _ingest,
    ),
    Result(
        "What the web viewer takes in: posed primitives",
        f"{P}/ingest-1205-primitives-30hz.json",
        f"telesurg bench ingest --kind primitives --rate 30 --json {P}/ingest-1205-primitives-30hz.json",
        _ingest,
    ),
    Result(
        "TCP loopback vs Unix socket",
        f"{P}/links-1205.json",
        f"telesurg bench links --pairs 4 --seconds 20 --rate 1000 --json {P}/links-1205.json",
        _links,
    ),
    Result(
        "Wake-up lateness of a control thread",
        f"{P}/wakeup-cpu2-1204e.json",
        "telesurg bench wakeup --seconds 10 --blocks 2 --slice-us 100 --load cpu:2 "
        f"--json {P}/wakeup-cpu2-1204e.json",
        _wakeup,
    ),
    Result(
        "Memory over a quiet run (the mirror trimming its heap)",
        f"{P}/memory/memory-600s-trim30-1203-1208.json",
        "telesurg bench memory --seconds 600 --every 30 --warmup 240 "
        f"--json {P}/memory/memory-600s-trim30-1203-1208.json --plot docs/img/memory_600s_trim30.png",
        _memory,
        "2026-12-03",
    ),
    Result(
        "Flood from a refused identity (locked site, link guard on)",
        f"{P}/flood-guard/flood-rss-guard-on.json",
        "telesurg bench flood --site locked --flooder launcher --after 30 "
        f"--json {P}/flood-guard/flood-rss-guard-on.json",
        _flood,
        "2026-12-02",
    ),
    Result(
        "Fault injection",
        "docs/data/faults.json",
        "telesurg bench faults --json docs/data/faults.json --plot docs/img/faults.png",
        _faults,
    ),
    Result(
        "Malformed messages",
        "docs/data/fuzz.json",
        "telesurg bench fuzz --count 100000 --json docs/data/fuzz.json",
        _fuzz,
    ),
    Result(
        "Forged messages and commands",
        "docs/data/attack-quiet.json",
        "telesurg bench attack --json docs/data/attack-quiet.json",
        _attack,
    ),
    Result(
        "Web doors without a session",
        "docs/data/attack-web.json",
        "telesurg bench attack --quick --only web-no-session,web-foreign-host,web-cross-origin "
        "--json docs/data/attack-web.json",
        _attack,
    ),
)


def _row(r: Result) -> str:
    path = DOCS.parent / r.data
    if not path.is_file():
        raise ValueError(f"{r.data}: no such result file (the command: {r.command})")
    data = json.loads(path.read_text(encoding="utf-8"))
    try:
        figures = r.figures(data)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{r.data}: {type(exc).__name__} {exc} (the command: {r.command})") from None
    date = str(data.get("date") or r.date or data.get("mouse", {}).get("date") or "—")[:10]
    link = r.data.removeprefix("docs/")
    return f"| {r.what} | {figures} | {date} | `{r.command}` | [{Path(r.data).name}]({link}) |"


def performance_page() -> str:
    """The page: :data:`TEMPLATE` with its placeholder replaced by the table of :data:`RESULTS`."""
    rows = [
        "## Current results",
        "",
        "| result | figures | date | command | data |",
        "| --- | --- | --- | --- | --- |",
        *(_row(r) for r in RESULTS),
    ]
    text = TEMPLATE.read_text(encoding="utf-8")
    if text.count(PLACEHOLDER) != 1:
        raise ValueError(f"{TEMPLATE.name}: needs {PLACEHOLDER} once")
    return text.replace(PLACEHOLDER, "\n".join(rows))
