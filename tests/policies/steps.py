"""A policy that replays a fixed action sequence as a Gymnasium environment interprets it
(``tests/test_gym_live_process.py``): call ``k`` after the slave began to follow moves the master
by ``actions[k] × max_step_mm`` (clipped to ±1 as ``env.step`` clips), one call per environment
step; before the engagement and after the last action the master stands still.

``--set master_capture.device_options.policy=tests/policies/steps.py:make`` with
``device_options.options.actions=FILE.npy`` (shape (n, 3)), ``options.max_step_mm`` (the
environment's, 2) and ``options.done_file=PATH``: written ``done`` after the last action, or
``interrupted`` if the slave stopped following before it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from telesurg.services.master_capture.devices.policy import PolicyObservation


def make(actions: str, max_step_mm: float = 2.0, done_file: str = ""):  # type: ignore[no-untyped-def]
    """The replaying policy (see the module doc)."""
    steps = np.clip(np.load(actions).astype(np.float32), -1.0, 1.0).astype(float) * (max_step_mm / 1e3)
    done = Path(done_file) if done_file else None
    state = {"k": -1}  # the next action; -1: not engaged yet; len(steps): finished

    def finish(word: str) -> None:
        state["k"] = len(steps)
        if done is not None and not done.exists():
            done.write_text(word)

    def policy(obs: PolicyObservation) -> np.ndarray:
        k = state["k"]
        if not obs.following:
            if 0 <= k < len(steps):
                finish("interrupted")
            return np.zeros(3)
        if k < 0:
            k = 0
        if k >= len(steps):
            return np.zeros(3)
        state["k"] = k + 1
        if k + 1 == len(steps):
            finish("done")
        out: np.ndarray = steps[k]
        return out

    return policy
