"""Time reading the sharded dataset: per-sample random access and torch loader throughput.

    python benchmarks/loader.py --dataset PATH [--batch 256] [--workers 0 1 2] [--seconds 10]
    python benchmarks/loader.py --make-test-data DIR [--episodes 48] [--frames 22] [--points 4096]

--dataset: a folder written by the write stage (``dataset.json`` inside).
--make-test-data: writes SYNTHETIC features files (random values of the right format, a stand-in
for timing only while the features stage is unfinished) to ``DIR/features``, builds the dataset
``DIR/dataset-<codec><level>-inner<k>`` with the write stage, and benchmarks that. Its numbers say nothing about real
clouds' compression ratio; rerun on a real dataset.

Random access (side by side on the same random sample indices): the reader's direct path
(``ShardedDataset.sample``: one pread + one decompression per array) against plain zarr
(``zarr.Array.__getitem__`` on the same four arrays). Loader: ``make_loader`` at ``--batch`` over
the train split, shuffled, for each worker count; samples/s counted after the first batch (worker
start-up and first-touch reported apart), the loop touching every tensor as a training step would.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install

import torch
import zarr

from anchordp3.dataset.reader import SAMPLE_ARRAYS, open_dataset
from anchordp3.dataset.torch_data import SplitDataset, make_loader
from anchordp3.schemas.dataset import WriteConfig
from anchordp3.stages.files import features_file, save_npz
from anchordp3.stages.write import (
    finalize,
    plan_tasks,
    shard_plan,
    write_shard,
)

SYNTHETIC_TASKS = ("synthetic_task_a", "synthetic_task_b")


def synthetic_features(seed: int, frames: int, n_points: int) -> dict[str, np.ndarray]:
    """SYNTHETIC stand-in of one episode's features (timing only): plausible ranges, random values."""
    rng = np.random.default_rng(seed)
    f, n = frames, n_points
    xyz = np.stack([rng.uniform(-0.4, 0.4, (f, n)), rng.uniform(-0.3, 0.3, (f, n)), rng.uniform(0.74, 0.95, (f, n))], -1)
    rgb = rng.integers(0, 256, (f, n, 3)) / 255.0  # 8-bit camera colours
    nrm = rng.normal(size=(f, n, 3))
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    curv = np.log(rng.random((f, n, 2)) + 1e-6)
    return {
        "points": np.concatenate([xyz, rgb, nrm, curv], -1).astype(np.float32),
        "labels": (rng.random((f, n)) < 0.2).astype(np.uint8),
        "state": rng.normal(size=(f, 32)).astype(np.float32),
        "anchors": rng.normal(size=(f, 8, 32)).astype(np.float32),
        "t": np.sort(rng.choice(1000, size=f, replace=False)).astype(np.int64),
        "kind": (rng.random(f) < 0.1).astype(np.uint8),
    }


def make_test_data(root: Path, episodes: int, frames: int, n_points: int, cfg: WriteConfig) -> Path:
    """Write SYNTHETIC features under ``root/features`` and the dataset ``root/dataset``; return the latter."""
    ids = [(SYNTHETIC_TASKS[i % len(SYNTHETIC_TASKS)], i) for i in range(episodes)]
    t0 = time.perf_counter()
    for task, seed in ids:  # deterministic contents: a file left by an earlier run with these sizes is reused
        path = root / features_file(task, seed)
        if not _has_shape(path, frames, n_points):
            save_npz(path, synthetic_features(seed, frames, n_points))
    t1 = time.perf_counter()
    plan = shard_plan([(t, s, f"synthetic instruction for {t}") for t, s in ids], cfg)
    tasks = plan_tasks(plan)
    out = root / f"dataset-{cfg.codec}{cfg.level}-inner{cfg.inner_chunk}"
    records = [write_shard(k, m, root, out, cfg, tasks=tasks) for k, m in enumerate(plan)]
    t2 = time.perf_counter()
    info = finalize(out, records, cfg)
    t3 = time.perf_counter()
    mb = sum(r.nbytes for r in records) / 1e6
    print(f"SYNTHETIC test data: {episodes} episodes x {frames} frames x {n_points} points -> {info.counts.samples} "
          f"samples, {len(records)} shards, {mb:.1f} MB; features {t1 - t0:.1f} s, shards {t2 - t1:.1f} s, "
          f"finalize (verify + tables + dask stats) {t3 - t2:.1f} s")
    return out


def _has_shape(path: Path, frames: int, n_points: int) -> bool:
    if not path.exists():
        return False
    with np.load(path) as z:
        return z["points"].shape == (frames, n_points, 11)


def random_access(path: Path, samples: int, seed: int) -> None:
    """Per-sample random read time: the reader's direct path against plain zarr indexing."""
    ds = open_dataset(path)
    idx = np.random.default_rng(seed).integers(0, len(ds), size=samples)
    groups = {s: zarr.open_group(path / e.path, mode="r") for s, e in enumerate(ds.info.shards)}
    arrays = {s: {k: g[k] for k in SAMPLE_ARRAYS} for s, g in groups.items()}
    for i in idx[:8]:  # open handles, load shard indexes
        ds.sample(int(i))
    fast, ref = [], []
    for i in idx:  # alternate so load changes on the machine hit both alike
        t = time.perf_counter()
        a = ds.sample(int(i))
        fast.append(time.perf_counter() - t)
        s, j = ds.locate(int(i))
        t = time.perf_counter()
        b = {k: arrays[s][k][j] for k in SAMPLE_ARRAYS}
        ref.append(time.perf_counter() - t)
        assert all(np.array_equal(a[k], b[k]) for k in SAMPLE_ARRAYS)
    inner = ds.info.config.inner_chunk
    print(f"random access, {samples} samples (inner chunk {inner}, codec {ds.info.config.codec}):")
    for name, ts in (("reader (direct)", fast), ("zarr indexing", ref)):
        ms = np.array(ts) * 1e3
        print(f"  {name:16s} median {np.median(ms):.3f} ms, p90 {np.percentile(ms, 90):.3f} ms, mean {ms.mean():.3f} ms")
    print(f"  speed-up (median) {np.median(ref) / np.median(fast):.1f}x")


def loader_rate(path: Path, batch: int, workers: int, seconds: float, seed: int) -> None:
    """Samples/s delivered to a loop that touches every tensor of every batch."""
    ds = SplitDataset(path, split="train")
    loader = make_loader(ds, batch_size=batch, workers=workers, seed=seed, drop_last=True)
    if len(loader) == 0:
        print(f"  workers={workers}: train split smaller than one batch of {batch}")
        return
    t0 = time.perf_counter()
    first = None
    n, batches, epochs = 0, 0, 0
    while True:
        epochs += 1
        for b in loader:
            _touch(b)
            now = time.perf_counter()
            if first is None:
                first, t_start = now - t0, now
                continue
            n += len(b["index"])
            batches += 1
            if now - t_start >= seconds and batches >= 3:
                break
        else:
            continue
        break
    rate = n / (time.perf_counter() - t_start)
    print(f"  workers={workers}: {rate:8.0f} samples/s ({batches} batches of {batch}, {epochs} epochs); "
          f"first batch {first:.2f} s")
    del loader


def _touch(b: dict[str, torch.Tensor]) -> None:
    for v in b.values():
        v.sum()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--dataset", type=Path, help="dataset folder written by the write stage")
    src.add_argument("--make-test-data", type=Path, metavar="DIR", help="write SYNTHETIC data to DIR and use it")
    parser.add_argument("--episodes", type=int, default=48, help="synthetic episodes")
    parser.add_argument("--frames", type=int, default=22, help="synthetic frames per episode")
    parser.add_argument("--points", type=int, default=4096, help="synthetic points per cloud")
    parser.add_argument("--inner-chunk", type=int, default=WriteConfig().inner_chunk, help="samples per inner chunk")
    parser.add_argument("--codec", default=WriteConfig().codec, help="compression codec of synthetic data")
    parser.add_argument("--level", type=int, default=WriteConfig().level, help="compression level of synthetic data")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--seconds", type=float, default=10.0, help="timed loading per worker count")
    parser.add_argument("--samples", type=int, default=500, help="random-access samples")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    if args.make_test_data is not None:
        cfg = WriteConfig(inner_chunk=args.inner_chunk, codec=args.codec, level=args.level, episodes_per_shard=16)
        path = make_test_data(args.make_test_data, args.episodes, args.frames, args.points, cfg)
    else:
        path = args.dataset
    ds = open_dataset(path)
    print(f"dataset: {path} ({ds.info.counts.samples} samples, N={ds.info.n_points}, "
          f"{len(ds.info.shards)} shards); torch threads {torch.get_num_threads()}")
    random_access(path, args.samples, args.seed)
    print(f"loader, batch {args.batch}, train split ({ds.info.counts.train_samples} samples):")
    for w in args.workers:
        loader_rate(path, args.batch, w, args.seconds, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
