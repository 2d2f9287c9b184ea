"""Experiments that reproduce the seed papers in simulation.

``telesurg experiment NAME --out DIR`` runs one, with a progress bar, and writes ``DIR/metrics.json``
and PNG figures:

* ``jinno-insertion`` — Jinno 2014: posture adjustment (PTP, jog, direct teach; three starts),
  insertion through the trocar and master–slave tracing in trocar mode, through the running
  services and MuJoCo (about 1.5 min on 2 cores). See ``docs/experiments/jinno.md``.
* ``shim-mapping`` — Shim 2015: the PLAS all-joints mapping factors of Section 4 (kinematic,
  seconds). See ``docs/experiments/shim.md``.
* ``jang-vip`` — Jang 2014: VIP redundancy resolution (Figs. 6, 9), elbow excursion VIP vs
  pseudo-inverse, and the 25 Hz → 1 kHz interpolation in MuJoCo (seconds). See
  ``docs/experiments/jang.md``.

Exit codes: 0 done, 1 the experiment failed (the reason is printed), 2 bad arguments.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from pathlib import Path

from telesurg.shared import jsonio

#: experiment name → module with ``run(out, progress) -> metrics``
EXPERIMENTS = {
    "jinno-insertion": "telesurg.tools.experiment.jinno",
    "shim-mapping": "telesurg.tools.experiment.shim",
    "jang-vip": "telesurg.tools.experiment.jang",
}


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg experiment``."""
    ap = argparse.ArgumentParser(
        prog="telesurg experiment", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("name", choices=sorted(EXPERIMENTS), help="which experiment")
    ap.add_argument("--out", type=Path, required=True, help="output directory (created)")
    ap.add_argument("--quick", action="store_true", help="jinno-insertion: a short protocol (the tests')")
    a = ap.parse_args(argv)
    if a.quick and a.name != "jinno-insertion":
        ap.error("--quick: only jinno-insertion has a short protocol")
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    module = importlib.import_module(EXPERIMENTS[a.name])
    with Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), TimeElapsedColumn(), console=console
    ) as bar:
        task = bar.add_task(a.name, total=1.0)

        def progress(text: str, fraction: float) -> None:
            bar.update(task, completed=fraction, description=f"{a.name}: {text}")

        try:
            metrics = module.run(a.out, progress, **({"quick": True} if a.quick else {}))
        except (RuntimeError, TimeoutError, OSError) as exc:
            console.print(f"[red]telesurg experiment {a.name} failed:[/red] {exc}")
            return 1
    summary = {k: v for k, v in metrics.items() if not isinstance(v, list | dict)}
    print(jsonio.dumps(summary, indent=2))
    print(f"wrote {a.out / 'metrics.json'} and the figures in {a.out}", file=sys.stderr)
    return 0
