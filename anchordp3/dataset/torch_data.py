"""Torch access to one split of a dataset: a ``Dataset`` of tensors and a seeded ``DataLoader``.

A sample is a dict of tensors: ``points (N, 11) float32``, ``labels (N,) uint8``, ``state (32,)
float32``, ``anchors (8, 32) float32`` and int64 scalars ``task_id, episode_index, timestep, kind,
index``; batches stack them along a new first axis. The sampler runs in the main process with its
own seeded generator, so the sample order is the same for any number of workers.

Batches are stacked with numpy (``collate_samples``), not ``torch.stack``: with more than one
intra-op thread on a busy machine, ``torch.stack`` of 256 clouds took seconds instead of ~20 ms
(OpenMP threads waiting for cores), and numpy's copy never starts threads.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, RandomSampler, SequentialSampler

from anchordp3.dataset.reader import SAMPLE_ARRAYS, ShardedDataset, open_dataset
from anchordp3.schemas.dataset import Split

SCALARS = ("task_id", "episode_index", "timestep", "kind", "index")


class SplitDataset(Dataset):
    """The samples of one split (optionally some tasks only) as tensors.

    dataset: an open ``ShardedDataset`` or a dataset folder; keys: which sample arrays to read."""

    def __init__(self, dataset: ShardedDataset | str | Path, split: Split | None = "train",
                 tasks: Iterable[str] | None = None, keys: Sequence[str] = SAMPLE_ARRAYS):
        self.data = dataset if isinstance(dataset, ShardedDataset) else open_dataset(dataset)
        bad = sorted(set(keys) - set(SAMPLE_ARRAYS))
        if bad:
            raise ValueError(f"keys: unknown {bad}; choose from {SAMPLE_ARRAYS}")
        self.keys = tuple(keys)
        self.split = split
        self.samples = self.data.indices(split, tasks)

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, j: int) -> dict[str, torch.Tensor]:
        s = self.data.sample(int(self.samples[j]), self.keys)
        out = {k: torch.from_numpy(s[k]) for k in self.keys}
        out.update({k: torch.tensor(s[k], dtype=torch.int64) for k in SCALARS})
        return out

    def __getitems__(self, js: list[int]) -> list[dict[str, torch.Tensor]]:
        """A batch of samples, read in storage order (fewer chunk switches) and returned in ``js`` order."""
        order = np.argsort(self.samples[np.asarray(js, dtype=np.int64)], kind="stable")
        got: list = [None] * len(js)
        for o in order:
            got[o] = self[js[o]]
        return got


def collate_samples(samples: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack per-sample tensors along a new first axis: ``{key: (B, ...)}`` (single-threaded copy)."""
    if not samples:
        raise ValueError("collate_samples: empty batch")
    out = {}
    for k, v in samples[0].items():
        batch = np.empty((len(samples), *v.shape), dtype=v.numpy().dtype)
        for i, s in enumerate(samples):
            batch[i] = s[k].numpy()
        out[k] = torch.from_numpy(batch)
    return out


def make_loader(ds: SplitDataset, batch_size: int, workers: int = 0, *, seed: int = 0, shuffle: bool = True,
                drop_last: bool = False, pin_memory: bool = False, prefetch_factor: int = 2) -> DataLoader:
    """A DataLoader over ``ds``: seeded random order (epoch ``e`` of seed ``s`` is always the same),
    persistent workers when ``workers > 0``."""
    if batch_size < 1 or workers < 0:
        raise ValueError(f"batch_size must be >= 1 and workers >= 0, got {batch_size}, {workers}")
    gen = torch.Generator()
    gen.manual_seed(seed)
    sampler = RandomSampler(ds, generator=gen) if shuffle else SequentialSampler(ds)
    return DataLoader(
        ds, batch_size=batch_size, sampler=sampler, num_workers=workers, drop_last=drop_last,
        pin_memory=pin_memory, persistent_workers=workers > 0, collate_fn=collate_samples,
        prefetch_factor=prefetch_factor if workers > 0 else None,
    )
