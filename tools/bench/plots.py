"""Figures of benchmark runs (matplotlib, headless): one timeline per injected fault.

Each panel shows the slave tip's displacement (MuJoCo, mm) from where it was when the fault was
injected, over a window around the fault, on a background coloured by the watchdog's state
(DEGRADED yellow, HOLD red, ESTOP purple), with the clutch pedal as a grey bar and vertical lines
at injection, detection (the slave's fault hold), clearing, and the re-engage.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.tools.bench.harness import Probe

STATE_COLOURS = {"DEGRADED": "#f6d55c", "HOLD": "#ed553b", "ESTOP": "#8e44ad"}


def plot_faults(probe: Probe, rows: list[dict[str, Any]], out: Path, cols: int = 3) -> None:
    """Write one PNG with a panel per fault row (rows from ``run_fault``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tips = probe.tips()
    with probe.lock:
        safety = [(t, s) for t, s, *_ in probe.safety]
        clutch = list(probe.clutch)
    n = len(rows)
    nrows = math.ceil(n / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols, 2.9 * nrows), squeeze=False)
    for ax, row in zip(axes.flat, rows, strict=False):
        times = row.get("_times_ns") or {}
        t0 = times.get("inject")
        if t0 is None:
            ax.set_title(f"{row['fault']}: {row.get('error', 'no data')}", fontsize=9)
            continue
        end = max(v for v in times.values() if v is not None) + 1.0e9
        start = t0 - 1.0e9
        sel = (tips[:, 0] >= start) & (tips[:, 0] <= end)
        i0 = max(int(np.searchsorted(tips[:, 0], t0, side="right")) - 1, 0)
        disp = np.linalg.norm(tips[sel, 1:] - tips[i0, 1:], axis=1) * 1e3
        ts = (tips[sel, 0] - t0) / 1e9
        _shade_states(ax, safety, start, end, t0)
        _clutch_bar(ax, clutch, start, end, t0)
        ax.plot(ts, disp, color="#20639b", lw=1.2)
        for key, colour, label in (
            ("inject", "#ed553b", "inject"),
            ("hold", "#f39c12", "detect"),
            ("clear", "#3caea3", "clear"),
            ("follow", "#173f5f", "re-engage"),
        ):
            if times.get(key) is not None:
                ax.axvline((times[key] - t0) / 1e9, color=colour, ls="--", lw=1.0, label=label)
        detect = row.get("detect_ms")
        title = row["fault"] + (f" — detect {detect:.0f} ms" if detect is not None else " — no hold")
        ax.set_title(title, fontsize=9)
        ax.set_xlim((start - t0) / 1e9, (end - t0) / 1e9)
        ax.set_xlabel("s from injection", fontsize=8)
        ax.set_ylabel("tip displacement [mm]", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    from matplotlib.patches import Patch

    handles += [Patch(color=c, alpha=0.35) for c in STATE_COLOURS.values()] + [Patch(color="0.6")]
    labels += [f"watchdog {s}" for s in STATE_COLOURS] + ["clutch pressed"]
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def _shade_states(ax: Any, safety: list[tuple[int, str]], start: float, end: float, t0: int) -> None:
    prev_t, prev_s = start, "OK"
    for t, s in safety:
        if t < start:
            prev_s = s
            continue
        if t > end:
            break
        if prev_s in STATE_COLOURS:
            ax.axvspan((prev_t - t0) / 1e9, (t - t0) / 1e9, color=STATE_COLOURS[prev_s], alpha=0.35, lw=0)
        prev_t, prev_s = t, s
    if prev_s in STATE_COLOURS:
        ax.axvspan((prev_t - t0) / 1e9, (end - t0) / 1e9, color=STATE_COLOURS[prev_s], alpha=0.35, lw=0)


def _clutch_bar(ax: Any, clutch: list[tuple[int, bool]], start: float, end: float, t0: int) -> None:
    pressed_since: float | None = None
    for t, pressed in clutch:
        if pressed and pressed_since is None:
            pressed_since = max(t, start)
        elif not pressed and pressed_since is not None:
            if t >= start:
                ax.axvspan(
                    (pressed_since - t0) / 1e9, (min(t, end) - t0) / 1e9, ymin=0, ymax=0.04, color="0.6"
                )
            pressed_since = None
    if pressed_since is not None and pressed_since <= end:
        ax.axvspan((pressed_since - t0) / 1e9, (end - t0) / 1e9, ymin=0, ymax=0.04, color="0.6")


def plot_latency(results: list[dict[str, Any]], out: Path) -> None:
    """One panel per ``telesurg bench latency`` result: p50/p90/p99 of the bare relay and of the
    pipeline, end to end, with the goal (1.25 × the relay) marked, and the pipeline's two hops."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pcts = ("p50", "p90", "p99")
    fig, axes = plt.subplots(1, len(results), figsize=(5.0 * len(results), 3.6), squeeze=False)
    for ax, res in zip(axes.flat, results, strict=True):
        relay, pipe = res["relay"]["end_to_end"], res["pipeline"]
        x = np.arange(len(pcts))
        w = 0.38
        ax.bar(x - w / 2, [relay[p] for p in pcts], w, label="bare relay (3 processes)", color="#8aa")
        hop1 = [pipe["master_to_mapping_out"][p] for p in pcts]
        e2e = [pipe["end_to_end"][p] for p in pcts]
        ax.bar(x + w / 2, e2e, w, label="pipeline, end to end", color="#c75")
        ax.plot(x + w / 2, hop1, "k_", markersize=18, label="… of which master → mapping out")
        for i, p in enumerate(pcts):
            goal = "goal: 1.25 × relay" if i == 0 else None
            ax.hlines(1.25 * relay[p], i - w, i + w, colors="g", linestyles="--", linewidth=1, label=goal)
            ax.text(i + w / 2, e2e[i], f"{e2e[i]:.2f}", ha="center", va="bottom", fontsize=8)
        rate = res["rate_hz"]
        ax.set_title(f"{rate:g} Hz" if rate > 0 else "unpaced", fontsize=10)
        ax.set_xticks(x, pcts)
        ax.set_ylabel("one-way latency, ms")
        ax.legend(fontsize=7, loc="upper left")
    # (wrapped: one panel is narrower than the line, and a suptitle is not clipped to fit)
    fig.suptitle("master sample → setpoint used by the slave loop,\nagainst the bare transport", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def plot_memory(res: dict[str, Any], out: Path) -> None:
    """``telesurg bench memory``: RSS of each process over the run (top) and, per process, its
    anonymous memory (bottom, dashed), with the warm-up boundary marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = res["samples"]
    t = [s["t_s"] for s in samples]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8.0, 5.6), sharex=True)
    for name in res["processes"]:
        rss = [s["rss_mb"].get(name, np.nan) for s in samples]
        anon = [s["detail_mb"].get(name, {}).get("anon", np.nan) for s in samples]
        (line,) = top.plot(t, rss, marker=".", label=f"{name} ({res['processes'][name]['slope_mb_s']} MB/s)")
        bottom.plot(t, anon, "--", marker=".", color=line.get_color(), label=name)
    for ax in (top, bottom):
        ax.axvline(res["warmup_s"], color="grey", linewidth=0.8)
        ax.grid(alpha=0.3)
    top.set_ylabel("RSS, MB")
    top.set_title(f"bench memory: {res['seconds']:g} s, set: {', '.join(res['set']) or 'none'}", fontsize=10)
    top.legend(fontsize=7, title="slope after the warm-up (grey line)", title_fontsize=7)
    bottom.set_ylabel("anonymous, MB")
    bottom.set_xlabel("s after the slave follows")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def plot_viewer_lag(runs: list[tuple[str, dict[str, Any]]], out: Path) -> None:
    """``telesurg bench viewer --plot``: each run's lag behind live over the time the page was
    open (log scale; the 1 s goal and the warm-up marked), one line per ``(label, result)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.6, 4.2))
    for label, res in runs:
        pts = [(s["t_s"], s["lag_s"]) for s in res["samples"] if s.get("lag_s") is not None]
        if pts:
            t, lag = zip(*pts, strict=True)
            ax.plot(t, lag, marker=".", markersize=3, linewidth=1.2, label=label)
    ax.axhline(1.0, color="black", linewidth=0.8, linestyle="--")
    ax.text(1.0, 1.05, "1 s", fontsize=8)
    if runs:
        ax.axvline(runs[0][1]["warmup_s"], color="grey", linewidth=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("s after the page opened (grey: end of the warm-up)")
    ax.set_ylabel("viewer behind live, s")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
