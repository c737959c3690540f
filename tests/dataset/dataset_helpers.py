"""Helpers: small features files in the exact format of the features stage, random contents."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from anchordp3.schemas.dataset import WriteConfig
from anchordp3.stages.files import features_file, save_npz
from anchordp3.stages.write import (
    finalize,
    plan_tasks,
    shard_plan,
    write_shard,
)

N_POINTS = 48
EPISODES = [("place_bell", s) for s in (0, 1, 2, 5, 7)] + [("stack_blocks_three", s) for s in (3, 4, 9, 10)]


def fake_features(task: str, seed: int, n_points: int = N_POINTS) -> dict[str, np.ndarray]:
    """One episode's features: F = 3..7 frames of random values (format of the features stage)."""
    rng = np.random.default_rng([seed, len(task)])
    f = int(rng.integers(3, 8))
    pts = rng.normal(size=(f, n_points, 11)).astype(np.float32)
    labels = (rng.random((f, n_points)) < 0.3).astype(np.uint8)
    labels[0] = 0  # an all-zero row, as in frames without a critical object in view
    return {
        "points": pts, "labels": labels,
        "state": rng.normal(size=(f, 32)).astype(np.float32),
        "anchors": rng.normal(size=(f, 8, 32)).astype(np.float32),
        "t": np.sort(rng.choice(400, size=f, replace=False)).astype(np.int64),
        "kind": (rng.random(f) < 0.2).astype(np.uint8),
    }


def instruction(task: str, seed: int) -> str:
    """A stand-in instruction text; two variants per task."""
    return f"please do {task.replace('_', ' ')} {'now' if seed % 2 else 'carefully'}"


def write_features(root: Path, episodes=EPISODES) -> Path:
    """Features files of ``episodes`` under ``root/features/...``; returns ``root``."""
    for task, seed in episodes:
        save_npz(root / features_file(task, seed), fake_features(task, seed))
    return root


def build(features_dir: Path, out: Path, cfg: WriteConfig, failed=(), order=None):
    """Plan, write every shard (in ``order`` if given), finalize; returns (info, records, plan)."""
    plan = shard_plan([(t, s, instruction(t, s)) for t, s in EPISODES], cfg)
    tasks = plan_tasks(plan)
    ks = order if order is not None else range(len(plan))
    records = [write_shard(k, plan[k], features_dir, out, cfg, tasks=tasks, failed=failed) for k in ks]
    return finalize(out, records, cfg), records, plan


VIEWS = ("head", "front")


def fake_frames(task: str, seed: int, h: int = 12, w: int = 16) -> dict[str, np.ndarray]:
    """The rendered-frames file of an episode of ``fake_features`` (rgb of two views, steps, kinds)."""
    f = fake_features(task, seed)
    rng = np.random.default_rng([seed, len(task), 7])
    rgb = rng.integers(0, 256, size=(len(f["t"]), len(VIEWS), h, w, 3), dtype=np.uint8)
    return {"rgb": rgb, "t": f["t"], "kind": f["kind"], "views": np.array(VIEWS)}


def make_run(root: Path, cfg: WriteConfig, images: bool = True, failed=(("place_bell", 5),)) -> Path:
    """A run directory ``root/run`` as the data stages leave it, without simulating: ``config.yaml``,
    ``dataset/`` built from fake features, and ``render/frames/...`` (with RGB when ``images``,
    as with ``render.keep_frames: true``; pruned to steps and kinds otherwise)."""
    import yaml

    from anchordp3.stages.files import frames_file

    run = Path(root) / "run"
    build(write_features(Path(root) / "src"), run / "dataset", cfg, failed=failed)
    for task, seed in EPISODES:
        frames = fake_frames(task, seed)
        save_npz(run / "render" / frames_file(task, seed), frames if images else {k: v for k, v in frames.items() if k != "rgb"})
    (run / "config.yaml").write_text(yaml.safe_dump({"name": "fake", "tasks": sorted({t for t, _ in EPISODES})}))
    return run
