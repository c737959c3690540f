"""Statistics: per-shard merge == dask over the shards == numpy over all samples."""

from __future__ import annotations

import numpy as np
import pytest
from dataset_helpers import fake_features

from anchordp3.dataset.stats import dask_stats
from anchordp3.schemas.dataset import STATS_ARRAYS, ArrayStats, ShardStats
from anchordp3.stages.write import finalize


def test_merged_shard_stats_equal_dask_and_numpy(built):
    out, info, records, _ = built
    merged = ShardStats()
    for r in records:
        merged = merged.merge(r.stats)
    computed = dask_stats([out / r.path for r in records])
    assert merged.disagreements(computed, rtol=1e-9) == []
    spans = [e for r in records for e in r.episodes]
    for name in STATS_ARRAYS:
        x = np.concatenate([fake_features(e.task, e.seed)[name] for e in spans]).astype(np.float64)
        x = x.reshape(-1, x.shape[-1])
        ref = ArrayStats.of(x)
        assert ref.agrees(merged.arrays[name], rtol=1e-9) and ref.agrees(computed.arrays[name], rtol=1e-9)
        norm = info.stats[name]
        assert norm.count == len(x)
        np.testing.assert_allclose(norm.mean, x.mean(0), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(norm.std, x.std(0), rtol=1e-6, atol=1e-9)
        assert norm.min == x.min(0).tolist() and norm.max == x.max(0).tolist()


def test_finalize_refuses_stats_that_disagree(built, cfg, tmp_path):
    out, _, records, _ = built
    tampered = [r.model_copy(deep=True) for r in records]
    s = tampered[0].stats.arrays["state"]
    s.sum[0] += 1.0
    with pytest.raises(ValueError, match=r"\['state'\] disagree"):
        finalize(out, tampered, cfg)
    finalize(out, records, cfg)  # put the dataset back for the other tests


def test_stats_merge_is_associative_and_empty_is_neutral():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 4)), rng.normal(size=(7, 4))
    whole = ArrayStats.of(np.concatenate([a, b]))
    assert ArrayStats.of(a).merge(ArrayStats.of(b)).agrees(whole, rtol=1e-12)
    assert ArrayStats.empty(4).merge(whole) == whole
    roundtrip = ShardStats.model_validate_json(ShardStats().model_dump_json())
    assert roundtrip.arrays["points"].min[0] == float("inf")
