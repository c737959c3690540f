"""Farthest point sampling: determinism, exactness, coverage, fallback and repetition."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from anchordp3.geometry import sampling
from anchordp3.geometry.reference import reference_fps, synthetic_tabletop
from anchordp3.geometry.sampling import (
    farthest_point_sample,
    farthest_point_sample_numpy,
)


@pytest.fixture(scope="module")
def cloud() -> np.ndarray:
    return synthetic_tabletop(8000, seed=1)[0]


def _assert_exact_fps(points: np.ndarray, idx: np.ndarray) -> None:
    """Each pick after the first is (up to float32 rounding) the point farthest from earlier picks."""
    p = points.astype(np.float64)
    dist = np.sum((p - p[idx[0]]) ** 2, axis=1)
    for i in range(1, len(idx)):
        assert dist[idx[i]] >= dist.max() * (1 - 1e-5), f"pick {i} is not the farthest point"
        np.minimum(dist, np.sum((p - p[idx[i]]) ** 2, axis=1), out=dist)


def test_deterministic_shape_and_dtype(cloud: np.ndarray) -> None:
    a = farthest_point_sample(cloud, 512, start=3)
    b = farthest_point_sample(cloud.copy(), 512, start=3)
    assert a.shape == (512,) and a.dtype == np.int64
    np.testing.assert_array_equal(a, b)
    assert len(np.unique(a)) == 512 and a.min() >= 0 and a.max() < len(cloud)


def test_picks_are_exact_fps(cloud: np.ndarray) -> None:
    _assert_exact_fps(cloud, farthest_point_sample(cloud, 300))


def test_numpy_fallback_gives_the_same_picks(cloud: np.ndarray) -> None:
    fast = farthest_point_sample(cloud, 300, start=5)
    np.testing.assert_array_equal(farthest_point_sample_numpy(cloud, 300, start=int(fast[0])), fast)


def test_without_fpsample_uses_numpy(cloud: np.ndarray, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sampling, "fpsample", None)
    idx = farthest_point_sample(cloud, 64, start=7)
    assert idx[0] == 7
    np.testing.assert_array_equal(idx, farthest_point_sample_numpy(cloud, 64, start=7))


def test_same_set_as_open3d(cloud: np.ndarray) -> None:
    idx = farthest_point_sample(cloud, 1024, start=11)
    np.testing.assert_array_equal(np.sort(idx), reference_fps(cloud, 1024, start=int(idx[0])))


def test_covers_better_than_random(cloud: np.ndarray) -> None:
    idx = farthest_point_sample(cloud, 256)
    rand = np.random.default_rng(0).choice(len(cloud), 256, replace=False)
    assert pdist(cloud[idx]).min() > 5 * pdist(cloud[rand]).min()


def test_more_samples_than_points_repeats_cyclically() -> None:
    points = np.random.default_rng(2).random((10, 3)).astype(np.float32)
    idx = farthest_point_sample(points, 25, start=4)
    assert idx.shape == (25,)
    assert sorted(idx[:10]) == list(range(10))
    np.testing.assert_array_equal(idx[10:20], idx[:10])
    np.testing.assert_array_equal(idx[20:], idx[:5])
    np.testing.assert_array_equal(idx, farthest_point_sample(points, 25, start=4))


def test_single_point() -> None:
    np.testing.assert_array_equal(farthest_point_sample(np.zeros((1, 3)), 3), [0, 0, 0])


@pytest.mark.parametrize(
    ("shape", "n", "start"), [((0, 3), 1, 0), ((5, 2), 1, 0), ((5, 3), 0, 0), ((5, 3), 2, 5), ((5, 3), 2, -1)]
)
def test_rejects_bad_arguments(shape: tuple[int, int], n: int, start: int) -> None:
    with pytest.raises(ValueError):
        farthest_point_sample(np.zeros(shape), n, start)
