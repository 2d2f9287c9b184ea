"""``telesurg bench gym``: what one step of each registered Gymnasium environment costs.

Each environment (``telesurg.gym.ENVIRONMENTS``) runs ``--steps`` steps of random actions from a
seeded reset, without rendering (``image=False``), ``--runs`` times; a step is timed around
``env.step`` alone (resets are not counted). Reports per environment the median step of each run
and the min / median / max over the runs, in ms, and how many times faster than real time the
median is (a step simulates one 10 ms master sample).

Example::

    telesurg bench gym --runs 3 --json docs/data/gym-steps.json
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared import jsonio


def step_costs(env_id: str, steps: int, seed: int) -> list[float]:
    """Seconds of each of ``steps`` steps of ``env_id`` with seeded random actions."""
    import gymnasium

    env = gymnasium.make(env_id, image=False)
    try:
        env.reset(seed=seed)
        env.action_space.seed(seed)
        out = []
        for _ in range(steps):
            a = env.action_space.sample()
            t = time.perf_counter()
            _obs, _r, term, trunc, _info = env.step(a)
            out.append(time.perf_counter() - t)
            if term or trunc:
                env.reset()
        return out
    finally:
        env.close()


def run(steps: int, runs: int, seed: int) -> dict[str, Any]:
    """The measured result (see the module's docstring)."""
    from telesurg.gym import ENVIRONMENTS

    envs: dict[str, Any] = {}
    for env_id in ENVIRONMENTS:
        step_costs(env_id, 20, seed)  # warm: first-call imports and caches
        medians = [float(np.median(step_costs(env_id, steps, seed + k))) * 1e3 for k in range(runs)]
        med = statistics.median(medians)
        lo, hi = min(medians), max(medians)
        envs[env_id] = {
            "step_ms_per_run": [round(m, 4) for m in medians],
            "step_ms": {"min": round(lo, 4), "median": round(med, 4), "max": round(hi, 4)},
            "times_real_time": round(10.0 / med, 1),
        }
    return {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC"),
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine()},
        "cpus": os.cpu_count(),
        "steps": steps,
        "runs": runs,
        "seed": seed,
        "environments": envs,
        "command": "",
    }


def print_table(r: dict[str, Any]) -> None:
    """A rich table of the result."""
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"telesurg bench gym: {r['steps']} steps × {r['runs']} runs, no rendering")
    for col in ("environment", "step ms min", "median", "max", "× real time"):
        t.add_column(col, justify="left" if col == "environment" else "right")
    for env_id, e in r["environments"].items():
        s = e["step_ms"]
        cost = [f"{s[k]:.3f}" for k in ("min", "median", "max")]
        t.add_row(env_id, *cost, f"{e['times_real_time']:g}")
    Console().print(t)


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bench gym``."""
    ap = argparse.ArgumentParser(
        prog="telesurg bench gym", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--steps", type=int, default=2000, help="timed steps a run (default 2000)")
    ap.add_argument("--runs", type=int, default=3, help="runs per environment (default 3)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the resets and actions (default 0)")
    ap.add_argument("--json", type=Path, help="write the result as JSON here")
    args = ap.parse_args(argv)
    if args.steps < 1 or args.runs < 1:
        print("telesurg bench gym: --steps and --runs must be positive", file=sys.stderr)
        return 2
    result = run(args.steps, args.runs, args.seed)
    result["command"] = "telesurg bench gym " + " ".join(argv if argv is not None else sys.argv[3:])
    print_table(result)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(jsonio.dumps(result, indent=2))
    return 0
