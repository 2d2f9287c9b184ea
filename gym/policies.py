"""Policies for the ``policy`` master device (``docs/learning.md``), usable as ``module:function``.

:func:`replay` makes a policy from a LeRobotDataset written by ``telesurg export --to lerobot``: it
plays one episode's commanded tip motion (the ``action`` feature: the mapping's target, base
frame) back as master displacements — the smallest "policy learned from the data", standing in
for a trained network, which plugs into the device the same way (a callable taking a
:class:`~telesurg.services.master_capture.devices.policy.PolicyObservation`).

Example::

    telesurg up --set master_capture.device=policy \\
        --set master_capture.device_options.policy=telesurg.gym.policies:replay \\
        --set master_capture.device_options.options.dataset=dataset
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from telesurg.services.master_capture.devices.policy import PolicyObservation
from telesurg.shared.errors import ConfigError


def episode_targets(dataset: str | Path, episode: int = 0) -> tuple[np.ndarray, float]:
    """The commanded tip positions ``(n, 3)`` (m, base frame) of one episode, and the dataset's fps."""
    import pyarrow.parquet as pq

    root = Path(dataset)
    try:
        info = json.loads((root / "meta/info.json").read_text())
        table = pq.read_table(root / info["data_path"].format(chunk_index=0, file_index=0))
    except (OSError, KeyError, ValueError) as e:
        raise ConfigError(f"{root} is not a LeRobotDataset from telesurg export: {e}") from e
    data = table.to_pydict()
    rows = [i for i, e in enumerate(data["episode_index"]) if e == episode]
    if not rows:
        raise ConfigError(f"{root}: no episode {episode} (it has {info.get('total_episodes', 0)})")
    action = np.array([data["action"][i] for i in rows], dtype=float)
    return action[:, :3], float(info["fps"])


def replay(
    dataset: str, episode: int = 0, scale: float = 0.5
) -> Callable[[PolicyObservation], np.ndarray | None]:
    """A policy moving the master as the dataset's episode moved the commanded tip.

    Args:
        dataset: the dataset folder.
        episode: the episode to play.
        scale: the mapping's motion scale (slave / master): the target's displacement is divided
            by it. The master frame is taken as the slave's base frame (the mapping's default
            ``master_frame = "fixed"`` with no rotation).

    Once the slave follows, frame ``k`` of the episode is played at ``k / fps`` s; before that and
    after the last frame the master stands still.
    """
    targets, fps = episode_targets(dataset, episode)
    if not 0.0 < scale <= 2.0:
        raise ConfigError(f"replay: scale={scale} outside (0, 2]")
    state: dict[str, float] = {}  # t0: when the slave began to follow; k: the frame played

    def policy(obs: PolicyObservation) -> np.ndarray | None:
        if not obs.following:
            state.clear()  # a new engagement plays the episode from its start
            return np.zeros(3)
        if not state:
            state.update(t0=obs.t, k=0)
            return np.zeros(3)
        k = min(int((obs.t - state["t0"]) * fps), len(targets) - 1)
        out: np.ndarray = (targets[k] - targets[int(state["k"])]) / scale
        state["k"] = k
        return out

    return policy
