"""Write one shard: a zarr v3 group ``shards/<k:05d>.zarr`` holding the arrays of ``LAYOUT``.

Each array has the sample axis first and is stored with zarr's sharding codec: one shard file per
array (``<name>/c/0/...``) made of inner chunks of ``inner_chunk`` samples, each compressed on its
own, so reading one sample decompresses ``inner_chunk`` samples only. The per-sample scalar
arrays (task_id, episode_index, ...) are one inner chunk each; readers load them whole.

The group is written under a temporary name beside the final one, fsynced, checksummed and
renamed: a crash leaves no half shard under the final name. The same arrays and config always give
the same bytes (no timestamps; codecs are deterministic), so the checksum identifies the content.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from zarr.codecs import BloscCodec, GzipCodec, ZstdCodec
from zarr.storage import LocalStore

from anchordp3.dataset.files import fsync_tree, remove_stale, swap_in, tree_checksum
from anchordp3.schemas.dataset import (
    LAYOUT,
    META_ARRAYS,
    SHARDS_DIR,
    ArraySpec,
    ShardStats,
    WriteConfig,
)

ATTRS_KEY = "anchordp3"  # group attribute holding the shard's own description


def shard_path(k: int) -> str:
    """Path of shard ``k`` relative to the dataset folder: ``shards/<k:05d>.zarr``."""
    return f"{SHARDS_DIR}/{k:05d}.zarr"


@dataclass(frozen=True)
class ShardWritten:
    """Outcome of writing one shard group."""

    checksum: str  # sha256 over file names and bytes (dataset.files.tree_checksum)
    nbytes: int  # bytes on disk
    stats: ShardStats  # statistics of points, state, anchors


def compressors(cfg: WriteConfig) -> list[Any]:
    """The zarr v3 compressor list of the config's codec (empty for ``none``)."""
    if cfg.codec == "zstd":
        return [ZstdCodec(level=cfg.level)]
    if cfg.codec in ("blosc-zstd", "blosc-lz4"):
        return [BloscCodec(cname=cfg.codec.split("-")[1], clevel=cfg.level, shuffle="shuffle")]
    if cfg.codec == "gzip":
        return [GzipCodec(level=cfg.level)]
    return []


def check_arrays(arrays: dict[str, np.ndarray]) -> tuple[int, int]:
    """Check ``arrays`` against ``LAYOUT``; return ``(samples, n_points)``.

    Raises ValueError naming the array on a missing name, wrong dtype or shape."""
    missing = [s.name for s in LAYOUT if s.name not in arrays]
    extra = sorted(set(arrays) - {s.name for s in LAYOUT})
    if missing or extra:
        raise ValueError(f"shard arrays: missing {missing}, unexpected {extra}")
    n_samples = len(arrays["points"])
    n_points = arrays["points"].shape[1] if arrays["points"].ndim == 3 else -1
    for spec in LAYOUT:
        a = arrays[spec.name]
        want = (n_samples, *spec.shape(n_points))
        if a.shape != want or a.dtype != np.dtype(spec.dtype):
            raise ValueError(f"shard array {spec.name!r}: expected {want} {np.dtype(spec.dtype)}, got {a.shape} {a.dtype}")
    return n_samples, n_points


def write_shard_group(final: Path, arrays: dict[str, np.ndarray], attrs: dict[str, Any], cfg: WriteConfig) -> ShardWritten:
    """Write ``arrays`` (every ``LAYOUT`` array, sample axis first) as the zarr group ``final``.

    ``attrs`` (JSON-able) is stored as the group attribute ``anchordp3``. Exactly one writer per
    shard is assumed (the plan gives each shard to one task); leftovers of crashed earlier writes
    of the same shard are deleted first."""
    final = Path(final)
    check_arrays(arrays)
    final.parent.mkdir(parents=True, exist_ok=True)
    remove_stale(final)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    try:
        group = zarr.create_group(LocalStore(tmp), zarr_format=3, attributes={ATTRS_KEY: attrs})
        for spec in LAYOUT:
            _write_array(group, spec, arrays[spec.name], cfg)
        fsync_tree(tmp)
        checksum, nbytes = tree_checksum(tmp)
        swap_in(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ShardWritten(checksum=checksum, nbytes=nbytes, stats=ShardStats.of(arrays))


def _write_array(group: zarr.Group, spec: ArraySpec, data: np.ndarray, cfg: WriteConfig) -> None:
    """One array of the group, one zarr shard covering all its samples."""
    n = len(data)
    inner = max(1, n) if spec.name in META_ARRAYS else cfg.inner_chunk
    shard_len = max(1, -(-n // inner)) * inner
    rest = tuple(max(1, d) for d in data.shape[1:])  # an empty shard has N = 0; chunks need >= 1
    arr = group.create_array(
        spec.name, shape=data.shape, dtype=data.dtype, chunks=(inner, *rest), shards=(shard_len, *rest),
        compressors=compressors(cfg), fill_value=0, dimension_names=_dim_names(spec),
        config={"write_empty_chunks": True},
    )
    if n:
        arr[...] = data


def _dim_names(spec: ArraySpec) -> tuple[str, ...]:
    names = {"points": ("point", "channel"), "labels": ("point",), "state": ("dim",), "anchors": ("horizon", "dim")}
    return ("sample", *names.get(spec.name, ()))
