"""A policy that replays a fixed action sequence as a Gymnasium environment interprets it
(``tests/test_gym_live_process.py``): call ``k`` after the slave began to follow moves the master
by ``actions[k] × max_step_mm`` (clipped to ±1 as ``env.step`` clips), one call per environment
step; before the engagement and after the last action the master stands still. If the slave stops
following before the end (a watchdog HOLD), the policy pauses once (the device then presses its
pedal anew: a new engagement) and the sequence starts over at the next engagement.

``--set master_capture.device_options.policy=tests/policies/steps.py:make`` with
``device_options.options.actions=FILE.npy`` (shape (n, 3)), ``options.max_step_mm`` (the
environment's, 2) and ``options.done_file=PATH``: written once a whole sequence was played, as JSON:
for the engagement that played it, the slave's joints and the master's position (m) when it began,
when it began and ended (``start_ns``, ``end_ns``: wall clock), and the number of interrupted
attempts before it.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from telesurg.services.master_capture.devices.policy import PolicyObservation


def make(actions: str, max_step_mm: float = 2.0, done_file: str = ""):  # type: ignore[no-untyped-def]
    """The replaying policy (see the module doc)."""
    steps = np.clip(np.load(actions).astype(np.float32), -1.0, 1.0).astype(float) * (max_step_mm / 1e3)
    done = Path(done_file) if done_file else None
    # k: the next action (-1: waiting for an engagement; len(steps): finished)
    state: dict[str, object] = {"k": -1, "joints": [], "origin": [], "start_ns": 0, "interrupted": 0}

    def policy(obs: PolicyObservation) -> np.ndarray | None:
        k = int(state["k"])  # type: ignore[call-overload]
        if k >= len(steps):
            return np.zeros(3)
        if not obs.following:
            if k >= 0:  # interrupted: start over at the next engagement, which needs a new press:
                # pausing once makes the device release its pedal and press it again
                state["interrupted"] = int(state["interrupted"]) + 1  # type: ignore[call-overload]
                state["k"] = -1
                return None
            return np.zeros(3)
        if k < 0:  # a new engagement: the slave stands where the mapping anchored it
            state["joints"] = [float(v) for v in obs.joints]
            state["origin"] = [float(v) for v in obs.master]
            state["start_ns"] = time.time_ns()
            k = 0
        state["k"] = k + 1
        if k + 1 == len(steps) and done is not None:
            keys = ("joints", "origin", "start_ns", "interrupted")
            report = {n: state[n] for n in keys} | {"end_ns": time.time_ns()}
            done.write_text(json.dumps(report))
        out: np.ndarray = steps[k]
        return out

    return policy
