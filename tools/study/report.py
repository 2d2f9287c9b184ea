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


def _stats(v: list[float]) -> tuple[float, float, int]:
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
                v = [r.get(key) for r in scored if r["task"] == task and r["condition"] == cond]
                v = [y for y in v if y is not None and math.isfinite(y)]
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
    return [md, js, png]
