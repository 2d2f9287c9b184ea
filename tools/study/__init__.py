"""``telesurg study PROTOCOL.toml --out DIR``: run a user study of surgical tasks under conditions.

Each trial runs on a real site with the synthetic operator as the master (docs/study.md): the
protocol's tasks × conditions × repetitions in an order randomised per participant, a practice
block first, a pause between trials. Every finished trial is appended to ``DIR/results.jsonl``
with its recording ``DIR/trials/NNN.mcap``; at the end (and with ``--report`` at any time)
``DIR/report.md``, ``report.json`` and ``report.png``. Run the same command again after an
interruption (Ctrl-C, a service that died) and it resumes after the last finished trial.

With ``--master web`` a person performs the trials at the web console's page instead (its
one-time login URL is printed for each trial); the page shows the task, its instructions, the
trial's clock and its result, and, in a blinded study, the condition's code only.

Examples::

    telesurg study docs/data/study-delay.toml --out out/study --participant p01
    telesurg study docs/data/study-delay.toml --out out/study --participant p02 --master web
    telesurg study docs/data/study-delay.toml --out out/study --report   # the report only

Exit codes: 0 done, 1 a trial failed (run again to resume), 2 a bad protocol or arguments,
130 interrupted (run again to resume).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from telesurg.tools.study.protocol import ProtocolError, Trial, load
from telesurg.tools.study.runner import (
    MASTERS,
    StudyError,
    TrialFailed,
    Where,
    finished,
    prepare,
    run_trial,
)

RETRIES = 1  # a trial whose site failed is tried this many more times before the study stops


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg study``."""
    ap = argparse.ArgumentParser(
        prog="telesurg study", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("protocol", type=Path, help="the protocol file (TOML; docs/study.md)")
    ap.add_argument("--out", type=Path, required=True, help="the study's directory (created; resumed)")
    ap.add_argument("--participant", default="p01", help="participant id: seeds the order (default p01)")
    ap.add_argument("--restart", action="store_true", help="discard what --out holds and start again")
    ap.add_argument("--report", action="store_true", help="only write the report of the finished trials")
    ap.add_argument(
        "--master",
        choices=MASTERS,
        default="operator",
        help="operator: the synthetic operator performs the trials (default); web: a person at the web "
        "console's page (its one-time login URL is printed for each trial: a fresh site each)",
    )
    ap.add_argument("--log-level", default="WARNING", help="DEBUG, INFO, WARNING, ERROR")
    a = ap.parse_args(argv)
    logging.basicConfig(level=a.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    try:
        protocol = load(a.protocol)
    except ProtocolError as e:
        print(f"telesurg study: {e}", file=sys.stderr)
        return 2
    if a.restart and a.out.exists():
        shutil.rmtree(a.out)
    where = Where(a.out)
    try:
        trials, done = prepare(protocol, a.participant, a.out)
    except StudyError as e:
        print(f"telesurg study: {e}", file=sys.stderr)
        return 2
    conditions = [c.name for c in protocol.conditions]
    title = f"{protocol.name} — participant {a.participant}"
    if not a.report:
        todo = [t for t in trials if t.index not in done]
        if done:
            print(f"resuming: {len(done)} of {len(trials)} trials done, {len(todo)} to go")
        for n, trial in enumerate(todo):
            # the operator's side sees the code only in a blinded study
            shown = trial.code if protocol.blinded else f"{trial.condition.name}"
            print(f"trial {trial.index + 1}/{len(trials)}: {trial.task}, {shown}", flush=True)
            try:
                row = _attempt(
                    trial, where, protocol.host_margin_ms, shown=shown, total=len(trials), master=a.master
                )
            except KeyboardInterrupt:
                n_done = len(finished(where.results))
                print(
                    f"\ninterrupted: {n_done} of {len(trials)} trials kept in {where.results}; "
                    "run the same command again to resume",
                    file=sys.stderr,
                )
                return 130
            except TrialFailed as e:
                print(f"telesurg study: {e}\nrun the same command again to resume", file=sys.stderr)
                return 1
            with where.results.open("a+") as f:
                f.seek(0, 2)
                if f.tell() > 0:  # a line torn by a crash mid-write ends here, not in this one
                    f.seek(f.tell() - 1)
                    if f.read(1) != "\n":
                        f.write("\n")
                f.write(json.dumps(row) + "\n")
                f.flush()
            score = "done" if row["completed"] else "not done"
            t = row["completion_time_s"]
            print(f"  {score}" + (f" in {t:.1f} s" if t is not None else ""), flush=True)
            if protocol.pause_s > 0 and n < len(todo) - 1:
                time.sleep(protocol.pause_s)
    rows = sorted(finished(where.results).values(), key=lambda r: r["trial"])
    if not any(not r["practice"] for r in rows):
        print("no scored trial yet: no report")
        return 0
    from telesurg.tools.study.report import write

    for p in write(a.out, rows, conditions, title):
        print(f"wrote {p}")
    return 0


def _console(url: str) -> None:
    print(f"  the console for this trial (one-time login): {url}", flush=True)


def _attempt(trial: Trial, where: Where, margin_ms: float, **how: Any) -> dict[str, Any]:
    """Run the trial, once more if its site failed (``how``: :func:`run_trial`'s keywords)."""
    for attempt in range(RETRIES + 1):
        try:
            return run_trial(trial, where, margin_ms, on_console=_console, **how)
        except TrialFailed as e:
            if attempt == RETRIES:
                raise
            print(f"  trial failed ({str(e).splitlines()[0]}); once more", file=sys.stderr)
    raise AssertionError("unreachable")
