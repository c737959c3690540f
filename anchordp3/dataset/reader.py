"""Read a written dataset: ``open_dataset(path)`` -> ``ShardedDataset`` with random access by sample.

A sample's arrays are read straight from its shard's inner chunk (``dataset.chunks``): one
``pread`` and one decompression per array. Per shard, the small per-sample arrays (task_id,
episode_index, timestep, kind) are loaded once and cached with the open array handles. The object
can be pickled (e.g. into DataLoader workers): handles are reopened in the new process.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from anchordp3.dataset.chunks import ArrayReader
from anchordp3.dataset.index import INDEX_SCHEMA, read_table
from anchordp3.schemas.dataset import (
    ARRAYS,
    INDEX_FILE,
    INFO_FILE,
    READABLE_SCHEMA_VERSIONS,
    SPLITS,
    DatasetInfo,
    NormStats,
    Split,
)

SAMPLE_ARRAYS = ("points", "labels", "state", "anchors")
_META = ("task_id", "episode_index", "timestep", "kind")


@dataclass(frozen=True)
class EpisodeEntry:
    """One written episode: its identity, split and global sample range ``[start, stop)``."""

    episode_index: int
    task: str
    task_id: int
    seed: int
    split: Split
    instruction: str
    shard: int
    start: int
    stop: int

    @property
    def frames(self) -> int:
        """Samples of the episode."""
        return self.stop - self.start


class _Shard:
    """Open handles and cached per-sample metadata of one shard group."""

    def __init__(self, path: Path):
        self.path = path
        self.arrays = {name: ArrayReader(path / name) for name in SAMPLE_ARRAYS}
        self.meta = {name: ArrayReader(path / name).read_all() for name in _META}

    def close(self) -> None:
        for a in self.arrays.values():
            a.close()


class ShardedDataset:
    """Random access to the samples of a dataset folder (see ``schemas.dataset``).

    ``ds[i]`` -> dict with ``points (N, 11) f32``, ``labels (N,) u8``, ``state (32,) f32``,
    ``anchors (8, 32) f32``, ints ``task_id, episode_index, timestep, kind, seed, index`` and strs
    ``task, instruction``."""

    def __init__(self, path: Path, info: DatasetInfo, index: dict[str, np.ndarray]):
        self.path = Path(path)
        self.info = info
        self._index = index
        self._shard_starts = np.array([s.start for s in info.shards], dtype=np.int64)
        self._shards: dict[int, _Shard] = {}
        self._pid = os.getpid()
        self._row_of_episode = {int(e): r for r, e in enumerate(index["episode_index"])}

    # ---- sizes and metadata ----------------------------------------------------------------
    def __len__(self) -> int:
        return self.info.counts.samples

    @property
    def tasks(self) -> list[str]:
        """Task names; ``task_id`` indexes this list."""
        return list(self.info.tasks)

    @property
    def stats(self) -> dict[str, NormStats]:
        """Normalisers of points, state and anchors (per last dimension) over all samples."""
        return self.info.stats

    def episodes(self, split: Split | None = None, tasks: Iterable[str] | None = None) -> list[EpisodeEntry]:
        """Written episodes in ``episode_index`` order, optionally of one split and some tasks."""
        rows = self._rows(split, tasks)
        ix = self._index
        return [EpisodeEntry(
            episode_index=int(ix["episode_index"][r]), task=str(ix["task"][r]), task_id=int(ix["task_id"][r]),
            seed=int(ix["seed"][r]), split=str(ix["split"][r]), instruction=str(ix["instruction"][r]),
            shard=int(ix["shard"][r]), start=int(ix["start"][r]), stop=int(ix["stop"][r]),
        ) for r in rows]

    def indices(self, split: Split | None = None, tasks: Iterable[str] | None = None) -> np.ndarray:
        """Global sample indices ``(M,) int64`` of a split (and tasks), ascending."""
        rows = self._rows(split, tasks)
        starts, stops = self._index["start"][rows], self._index["stop"][rows]
        if len(rows) == 0:
            return np.zeros(0, dtype=np.int64)
        return np.concatenate([np.arange(a, b, dtype=np.int64) for a, b in zip(starts, stops)])

    def _rows(self, split: Split | None, tasks: Iterable[str] | None) -> np.ndarray:
        keep = np.ones(len(self._index["episode_index"]), dtype=bool)
        if split is not None:
            if split not in SPLITS:
                raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
            keep &= self._index["split"] == split
        if tasks is not None:
            tasks = list(tasks)
            unknown = sorted(set(tasks) - set(self.info.tasks))
            if unknown:
                raise ValueError(f"tasks: unknown {unknown}; the dataset has {self.info.tasks}")
            keep &= np.isin(self._index["task"], tasks)
        return np.flatnonzero(keep)

    # ---- samples ---------------------------------------------------------------------------
    def locate(self, i: int) -> tuple[int, int]:
        """``(position in info.shards, sample within that shard)`` of global sample ``i``."""
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"sample {i} out of range for a dataset of {n}")
        s = int(np.searchsorted(self._shard_starts, i, side="right")) - 1
        while self.info.shards[s].samples == 0 or i >= self._shard_starts[s] + self.info.shards[s].samples:
            s += 1  # skip empty shards sharing a start
        return s, i - int(self._shard_starts[s])

    def _shard(self, s: int) -> _Shard:
        if self._pid != os.getpid():
            self._shards, self._pid = {}, os.getpid()
        sh = self._shards.get(s)
        if sh is None:
            path = self.path / self.info.shards[s].path
            try:
                sh = _Shard(path)
            except (OSError, json.JSONDecodeError, KeyError) as e:
                raise ValueError(f"{path}: missing or corrupt shard ({type(e).__name__})") from None
            self._shards[s] = sh
        return sh

    def sample(self, i: int, keys: Iterable[str] = SAMPLE_ARRAYS) -> dict:
        """Sample ``i`` with the arrays named in ``keys`` (a subset of points, labels, state, anchors)."""
        s, j = self.locate(int(i))
        sh = self._shard(s)
        out: dict = {k: sh.arrays[k].sample(j) for k in keys}
        ep = int(sh.meta["episode_index"][j])
        row = self._row_of_episode[ep]
        out.update(
            task_id=int(sh.meta["task_id"][j]), episode_index=ep, timestep=int(sh.meta["timestep"][j]),
            kind=int(sh.meta["kind"][j]), seed=int(self._index["seed"][row]), index=int(i) % len(self),
            task=str(self._index["task"][row]), instruction=str(self._index["instruction"][row]),
        )
        return out

    def episode_arrays(self, entry: EpisodeEntry, keys: Iterable[str] = SAMPLE_ARRAYS) -> dict[str, np.ndarray]:
        """The samples of one episode stacked in sample order: the arrays named in ``keys``
        (``points (F, N, 11)``, ...) and ``timestep (F,) int64``, ``kind (F,) uint8``."""
        keys = tuple(keys)
        rows = [self.sample(i, keys) for i in range(entry.start, entry.stop)]
        out = {k: np.stack([r[k] for r in rows]) if rows else np.zeros((0, *ARRAYS[k].shape(self.info.n_points)), ARRAYS[k].dtype)
               for k in keys}
        out["timestep"] = np.array([r["timestep"] for r in rows], dtype=np.int64)
        out["kind"] = np.array([r["kind"] for r in rows], dtype=np.uint8)
        return out

    def __getitem__(self, i: int) -> dict:
        return self.sample(i)

    def close(self) -> None:
        """Close every open shard file (reopened on the next read)."""
        for sh in self._shards.values():
            sh.close()
        self._shards = {}

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_shards"] = {}
        return state

    def __repr__(self) -> str:
        c = self.info.counts
        return (f"ShardedDataset({str(self.path)!r}, samples={c.samples}, episodes={c.episodes}, "
                f"tasks={len(self.info.tasks)}, shards={len(self.info.shards)})")


def read_dataset_info(root: Path) -> DatasetInfo:
    """The ``dataset.json`` of the dataset folder ``root``; ValueError naming the path when there is
    none or it does not validate."""
    info_path = Path(root) / INFO_FILE
    if not info_path.is_file():
        raise ValueError(f"{root}: not an anchordp3 dataset (no {INFO_FILE}; unfinished or foreign folder)")
    try:
        return DatasetInfo.model_validate_json(info_path.read_bytes())
    except ValidationError as e:
        raise ValueError(f"{info_path}: not a valid dataset description ({e.error_count()} errors)") from None


def open_dataset(path: str | Path) -> ShardedDataset:
    """Open a dataset folder written by the write stage; ValueError naming the path when it is not one."""
    root = Path(path)
    info = read_dataset_info(root)
    info_path = root / INFO_FILE
    if info.schema_version not in READABLE_SCHEMA_VERSIONS:
        raise ValueError(f"{info_path}: schema version {info.schema_version}, this code reads {list(READABLE_SCHEMA_VERSIONS)}")
    table = read_table(root / INDEX_FILE, INDEX_SCHEMA)
    index = {name: table.column(name).to_numpy(zero_copy_only=False) for name in table.column_names}
    return ShardedDataset(root, info, index)
