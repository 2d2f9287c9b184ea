"""A study's report: a table (Markdown) and score-vs-condition plots with their spread (PNG).

Only the scored trials count (the practice block does not). Conditions are in the protocol's
order; each panel shows every trial as a dot and the mean ± one standard deviation.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

#: (result field, label, unit) of the report's columns and plots
SCORES = (
    ("completion_time_s", "completion time", "s"),
    ("path_length_mm", "tip path length", "mm"),
    ("economy", "economy of motion", ""),
    ("peak_force_n", "peak tissue force", "N"),
    ("time_held_s", "time held", "s"),
)
PLOTTED = ("completion_time_s", "path_length_mm", "economy")


def _stats(v: list[Any]) -> tuple[float, float, int]:
    a = np.array([x for x in v if x is not None and math.isfinite(x)], dtype=float)
    if a.size == 0:
        return math.nan, math.nan, 0
    return float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else 0.0, int(a.size)


def summarize(rows: list[dict[str, Any]], conditions: list[str]) -> list[dict[str, Any]]:
    """One row per task × condition: n, completed, each score's mean and SD, errors by kind."""
    out = []
    tasks = list(dict.fromkeys(r["task"] for r in rows if not r["practice"]))
    for task in tasks:
        for cond in conditions:
            sel = [r for r in rows if r["task"] == task and r["condition"] == cond and not r["practice"]]
            if not sel:
                continue
            row: dict[str, Any] = {"task": task, "condition": cond, "n": len(sel)}
            row["completed"] = sum(bool(r["completed"]) for r in sel)
            for key, _, _ in SCORES:
                m, sd, _n = _stats([r.get(key) for r in sel])
                row[key] = {"mean": m, "sd": sd}
            kinds = sorted({k for r in sel for k in r["errors"]})
            row["errors"] = {k: sum(r["errors"].get(k, 0) for r in sel) for k in kinds}
            row["clutch_count"] = sum(r["clutch_count"] for r in sel)
            out.append(row)
    return out


def table(summary: list[dict[str, Any]]) -> str:
    """The summary as a Markdown table (mean ± SD)."""
    head = ["task", "condition", "n", "done"] + [f"{lab} ({u})" if u else lab for _, lab, u in SCORES]
    head += ["errors"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for r in summary:
        cells = [r["task"], r["condition"], str(r["n"]), str(r["completed"])]
        for key, _, _ in SCORES:
            m, sd = r[key]["mean"], r[key]["sd"]
            cells.append("–" if not math.isfinite(m) else f"{m:.2f} ± {sd:.2f}")
        cells.append(", ".join(f"{k} {v}" for k, v in r["errors"].items() if v) or "none")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], conditions: list[str], out: Path, title: str = "") -> None:
    """Write the PNG: one column per task, one row per plotted score."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scored = [r for r in rows if not r["practice"]]
    tasks = list(dict.fromkeys(r["task"] for r in scored))
    fig, axes = plt.subplots(
        len(PLOTTED),
        max(len(tasks), 1),
        figsize=(4.6 * max(len(tasks), 1), 2.6 * len(PLOTTED)),
        squeeze=False,
    )
    labels = dict((k, (lab, u)) for k, lab, u in SCORES)
    rng = np.random.default_rng(0)
    for j, task in enumerate(tasks):
        for i, key in enumerate(PLOTTED):
            ax = axes[i][j]
            means, sds = [], []
            for x, cond in enumerate(conditions):
                got = [r.get(key) for r in scored if r["task"] == task and r["condition"] == cond]
                v = [float(y) for y in got if y is not None and math.isfinite(y)]
                ax.scatter(x + rng.uniform(-0.08, 0.08, len(v)), v, s=14, color="#7f8c8d", zorder=2)
                m, sd, _ = _stats(v)
                means.append(m)
                sds.append(sd)
            ax.errorbar(
                range(len(conditions)), means, yerr=sds, color="#20639b", marker="o", capsize=4, zorder=3
            )
            ax.set_xticks(range(len(conditions)), conditions, fontsize=8)
            lab, unit = labels[key]
            ax.set_ylabel(f"{lab} ({unit})" if unit else lab, fontsize=8)
            if i == 0:
                ax.set_title(task, fontsize=10)
            ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def plot_tasks(traces: dict[str, np.ndarray | list[np.ndarray]], out: Path) -> None:
    """The tasks from above and from the side (mm, the slave's base frame): goals with their
    radius, the wire with its tube, and one trial's tip path each (``traces``: task → (n, 4) t,
    x, y, z in m)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle
    from telesurg.shared import tasks

    names = list(traces)
    fig, axes = plt.subplots(2, len(names), figsize=(4.6 * len(names), 6.4), squeeze=False)
    for j, name in enumerate(names):
        task = tasks.get(name)
        trace = traces[name]
        paths = [t * 1e3 for t in trace] if isinstance(trace, list) else [trace * 1e3]
        for i, (a, b, view) in enumerate(((1, 2, "from above"), (1, 3, "from the side"))):
            ax = axes[i][j]
            if task.kind == "path":
                wire = np.array(task.path) * 1e3
                r = task.tube_radius_m * 1e3
                ax.plot(wire[:, a - 1], wire[:, b - 1], color="#c0392b", lw=1.5, label="wire")
                ax.fill_between(
                    wire[:, 0], wire[:, b - 1] - r, wire[:, b - 1] + r, color="#c0392b", alpha=0.15, lw=0
                ) if a == 1 else None
            for k, g in enumerate(task.goals):
                p = np.array(g.position) * 1e3
                ax.add_patch(Circle((p[a - 1], p[b - 1]), g.radius_m * 1e3, color="#27ae60", alpha=0.3))
                if task.kind == "targets" and k < 2:
                    ax.annotate("AB"[k], (p[a - 1], p[b - 1]), ha="center", va="center", fontsize=8)
            for n, (tip, start) in enumerate(zip(paths, task.start_tips or (task.start_tip,), strict=False)):
                s = np.array(start) * 1e3
                label = "tip" if len(paths) == 1 else f"{task.arms[n]} tip"
                ax.plot(tip[:, a], tip[:, b], color=("#20639b", "#e67e22")[n % 2], lw=0.8, label=label)
                ax.plot(s[a - 1], s[b - 1], "k^", ms=6, label="start" if n == 0 else None)
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_xlabel("x (mm)", fontsize=8)
            ax.set_ylabel(("y", "z")[i] + " (mm)", fontsize=8)
            ax.set_title(f"{name}, {view}", fontsize=9)
            ax.grid(alpha=0.3)
            if i == 0 and j == 0:
                ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def _clean(v: Any) -> Any:
    """NaN → None, recursively (JSON has no NaN)."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_clean(x) for x in v]
    return v


def write(out_dir: Path, rows: list[dict[str, Any]], conditions: list[str], title: str) -> list[Path]:
    """``report.md``, ``report.json`` and ``report.png`` in ``out_dir``; their paths."""
    summary = summarize(rows, conditions)
    md = out_dir / "report.md"
    md.write_text(f"# {title}\n\n{table(summary)}\n")
    js = out_dir / "report.json"
    js.write_text(json.dumps(_clean({"title": title, "summary": summary}), indent=1, allow_nan=False) + "\n")
    png = out_dir / "report.png"
    plot(rows, conditions, png, title)
    written = [md, js, png]
    from telesurg.shared import tasks

    traces: dict[str, np.ndarray | list[np.ndarray]] = {}
    for r in rows:  # the first finished trial of each task at the first condition: its tip path
        if (
            r["task"] not in traces
            and r["completed"]
            and r["condition"] == conditions[0]
            and "recording" in r
        ):
            from telesurg.tools.study.runner import streams_from_mcap

            rec = out_dir / r["recording"]
            if rec.exists():
                st = streams_from_mcap(rec, tasks.get(r["task"]))
                traces[r["task"]] = [st.tip, *st.more_tips.values()]
    if traces:
        plot_tasks(traces, out_dir / "tasks.png")
        written.append(out_dir / "tasks.png")
    return written
