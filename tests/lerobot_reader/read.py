"""Read a LeRobotDataset with LeRobot's own ``LeRobotDataset`` (the ``lerobot-dataset`` package)
and write what it gives, item by item, to an ``.npz`` (run in the reader's venv by
``tests/lerobot_check.py``; nothing of telesurg is imported here).

Usage: ``python read.py DATASET_DIR OUT.npz``
"""

import json
import sys

import numpy as np
from ledataset.datasets.lerobot_dataset import LeRobotDataset


def main(root: str, out: str) -> None:
    ds = LeRobotDataset("telesurg/check", root=root, video_backend="torchcodec")
    keys = ds.meta.video_keys
    cols: dict[str, list] = {
        k: [] for k in ("episode_index", "index", "frame_index", "timestamp", "state", "action")
    }
    frames: dict[str, list] = {k: [] for k in keys}
    tasks = []
    for i in range(ds.num_frames):
        item = ds[i]
        for k in ("episode_index", "index", "frame_index", "timestamp"):
            cols[k].append(item[k].item())
        cols["state"].append(item["observation.state"].numpy())
        cols["action"].append(item["action"].numpy())
        tasks.append(item["task"])
        for k in keys:  # float C×H×W in [0, 1] → uint8 H×W×C
            frames[k].append(np.round(item[k].permute(1, 2, 0).numpy() * 255).astype(np.uint8))
    episodes = ds.meta.episodes
    meta = {
        "num_episodes": ds.num_episodes,
        "num_frames": ds.num_frames,
        "fps": ds.fps,
        "video_keys": keys,
        "tasks": sorted(set(tasks)),
        "lengths": [int(n) for n in episodes["length"]],
        "start_ns": [int(n) for n in episodes["telesurg/start_ns"]],
    }
    arrays = {k: np.array(v) for k, v in cols.items()}
    arrays.update({f"frames/{k}": np.array(v) for k, v in frames.items()})
    np.savez(out, meta=json.dumps(meta), **arrays)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
