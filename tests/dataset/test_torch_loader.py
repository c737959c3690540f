"""Torch loading: tensors of the right dtypes; 0 and 2 workers give the same batches for a seed."""

from __future__ import annotations

import torch

from anchordp3.dataset.reader import open_dataset
from anchordp3.dataset.torch_data import SplitDataset, make_loader


def batches(loader, epochs=2):
    return [(b["index"].tolist(), b["points"].clone()) for _ in range(epochs) for b in loader]


def test_sample_tensors(built):
    ds = SplitDataset(built[0], split="train")
    s = ds[0]
    assert s["points"].dtype == torch.float32 and s["points"].shape[1] == 11
    assert s["labels"].dtype == torch.uint8 and s["anchors"].shape == (8, 32)
    assert s["task_id"].dtype == torch.int64
    assert len(ds) == built[1].counts.train_samples
    only = SplitDataset(open_dataset(built[0]), split=None, tasks=["place_bell"], keys=("state",))
    assert set(only[0]) == {"state", "task_id", "episode_index", "timestep", "kind", "index"}


def test_zero_and_two_workers_yield_the_same_samples(built):
    ds = SplitDataset(built[0], split="train")
    b0 = batches(make_loader(ds, batch_size=5, workers=0, seed=11))
    loader2 = make_loader(ds, batch_size=5, workers=2, seed=11)
    assert loader2.persistent_workers
    b2 = batches(loader2)
    assert [i for i, _ in b0] == [i for i, _ in b2]
    assert all(torch.equal(p, q) for (_, p), (_, q) in zip(b0, b2))
    flat = sorted(i for idx, _ in b0[: len(b0) // 2] for i in idx)
    assert flat == ds.samples.tolist()  # one epoch visits every train sample once
    other = batches(make_loader(ds, batch_size=5, workers=0, seed=12))
    assert [i for i, _ in other] != [i for i, _ in b0]
