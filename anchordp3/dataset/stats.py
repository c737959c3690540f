"""Dataset-level statistics with dask over the shards' zarr arrays.

Every shard group is its own zarr array per name, so dask chunks never straddle two shards; inside
a shard, dask chunks are whole multiples of the zarr inner chunk (about ``target_bytes`` each) so
every zarr chunk is decoded by exactly one task. The result is a ``ShardStats`` comparable with the
merge of the per-shard statistics computed at write time.
"""

from __future__ import annotations

from pathlib import Path

import dask
import dask.array as da
import numpy as np
import zarr

from anchordp3.schemas.dataset import STATS_ARRAYS, ArrayStats, ShardStats


def _sample_chunk(arr: zarr.Array, target_bytes: int) -> int:
    """Samples per dask chunk: a multiple of the zarr inner chunk near ``target_bytes``."""
    inner = arr.chunks[0]
    per_sample = max(1, int(np.prod(arr.shape[1:])) * arr.dtype.itemsize)
    k = max(1, target_bytes // (per_sample * inner))
    return min(max(1, arr.shape[0]), k * inner)


def dask_stats(shard_dirs: list[Path], target_bytes: int = 32 << 20, num_workers: int | None = None) -> ShardStats:
    """Count, sum, sum of squares, min and max per last dimension of points, state and anchors.

    shard_dirs: shard groups in any order (sums are float64; the order changes only rounding).
    num_workers: dask threads (default: dask's)."""
    out: dict[str, ArrayStats] = {}
    pending = {}
    for name in STATS_ARRAYS:
        parts = []
        dim = None
        for d in shard_dirs:
            arr = zarr.open_array(Path(d) / name, mode="r")
            dim = arr.shape[-1]
            if arr.shape[0] == 0:
                continue
            x = da.from_zarr(arr, chunks=(_sample_chunk(arr, target_bytes), *arr.shape[1:]))
            parts.append(x.reshape(-1, dim))
        if not parts:
            out[name] = ArrayStats.empty(dim or 0)
            continue
        v = da.concatenate(parts).astype(np.float64)
        pending[name] = (v.shape[0], v.sum(0), (v * v).sum(0), v.min(0), v.max(0))
    computed = dask.compute(pending, scheduler="threads", num_workers=num_workers)[0]
    for name, (count, s, ss, lo, hi) in computed.items():
        out[name] = ArrayStats(count=int(count), sum=s.tolist(), sumsq=ss.tolist(), min=lo.tolist(), max=hi.tolist())
    return ShardStats(arrays={k: out[k] for k in STATS_ARRAYS})
