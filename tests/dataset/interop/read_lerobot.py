"""Load a LeRobot export with the real LeRobot (run by the interop venv's python, not the project's).

    python read_lerobot.py ROOT  ->  prints one JSON line describing what LeRobot read

Loads ``LeRobotDataset(repo_id, root=ROOT)`` offline, iterates it through a torch DataLoader,
asks for frames with ``delta_timestamps`` (how LeRobot policies get chunks), and combines the
per-episode statistics with LeRobot's own ``aggregate_stats``.
"""

import hashlib
import json
import os
import sys

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402
import torch  # noqa: E402
from lerobot.datasets.compute_stats import aggregate_stats  # noqa: E402
from lerobot.datasets.lerobot_dataset import CODEBASE_VERSION, LeRobotDataset  # noqa: E402
from lerobot.datasets.utils import dataset_to_policy_features  # noqa: E402


def image_sha(t: torch.Tensor) -> str:
    """sha256 of a (C, H, W) float image in [0, 1] as (H, W, C) uint8 bytes."""
    return hashlib.sha256((t.permute(1, 2, 0) * 255).round().to(torch.uint8).numpy().tobytes()).hexdigest()


def episode_stats(root: str) -> list[dict]:
    """The per-episode ``stats/<feature>/<stat>`` of the episodes table, as LeRobot's nested dicts."""
    files = sorted(os.path.join(d, f) for d, _, fs in os.walk(os.path.join(root, "meta", "episodes")) for f in fs)
    table = pq.read_table(files).to_pylist()
    out = []
    for row in table:
        stats: dict = {}
        for key, value in row.items():
            if key.startswith("stats/"):
                _, feature, stat = key.split("/")
                stats.setdefault(feature, {})[stat] = np.asarray(value)
        out.append(stats)
    return out


def main(root: str) -> None:
    ds = LeRobotDataset("local/anchordp3-export", root=root)
    loader = torch.utils.data.DataLoader(ds, batch_size=4, shuffle=True, num_workers=0,
                                         generator=torch.Generator().manual_seed(0))
    batches = 0
    for batch in loader:
        batches += 1
    cams = ds.meta.camera_keys
    first = ds[0]
    chunked = LeRobotDataset("local/anchordp3-export", root=root,
                             delta_timestamps={"action": [0.0, 1.0 / ds.fps, 2.0 / ds.fps], "observation.state": [-1.0 / ds.fps, 0.0]})
    ep0 = ds.meta.episodes[0]
    last0 = chunked[ep0["dataset_to_index"] - 1]
    agg = aggregate_stats(episode_stats(root))
    stats = ds.meta.stats
    print(json.dumps({
        "codebase_version": CODEBASE_VERSION,
        "len": len(ds), "num_episodes": ds.num_episodes, "fps": ds.fps,
        "camera_keys": cams,
        "policy_features": {k: [str(v.type), list(v.shape)] for k, v in dataset_to_policy_features(ds.meta.features).items()},
        "batches": batches,
        "batch_shapes": {k: list(v.shape) for k, v in batch.items() if isinstance(v, torch.Tensor)},
        "batch_tasks": len(batch["task"]),
        "first": {"task": first["task"], "action": first["action"].tolist(), "state": first["observation.state"].tolist(),
                  "episode_index": int(first["episode_index"]), "index": int(first["index"]),
                  "images": {k: image_sha(first[k]) for k in cams}},
        "episodes": [[int(e["dataset_from_index"]), int(e["dataset_to_index"])] for e in ds.meta.episodes],
        "tasks": list(ds.meta.tasks.index), "task_index": ds.meta.tasks["task_index"].tolist(),
        "chunk_action_shape": list(last0["action"].shape), "chunk_action_is_pad": last0["action_is_pad"].tolist(),
        "chunk_state_is_pad": chunked[0]["observation.state_is_pad"].tolist(),
        "stats_agree": {k: bool(np.allclose(agg[k][s], stats[k][s], rtol=1e-6, atol=1e-9))
                        for k in stats for s in ("min", "max", "mean", "std", "count", "q50")},
    }))


if __name__ == "__main__":
    main(sys.argv[1])
