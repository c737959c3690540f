"""Fast point features against the whole-cloud reference, plus geometric sanity checks."""

from __future__ import annotations

import numpy as np
import pytest

from anchordp3.geometry.features import (
    NeighbourTree,
    _smallest_eigenvectors,
    curvature_features,
    knn,
    normals_pca,
    point_features,
)
from anchordp3.geometry.reference import reference_features, synthetic_tabletop

EPS = 1e-5
NORMAL_TOL = 1e-4
CURVATURE_TOL = 1e-3
VIEWPOINT = np.array([-0.03, -0.45, 1.35])  # head camera of the default rig


def tilted_plane(m: int, rng: np.random.Generator, noise: float = 0.0) -> np.ndarray:
    """m points on a 0.6 x 0.4 m plane through (0, 0, 0.75) with normal ~ (0.2, -0.3, 1)."""
    u, v = (rng.random((2, m)) - 0.5) * np.array([[0.6], [0.4]])
    return np.column_stack([u, v, 0.75 - 0.2 * u + 0.3 * v]) + rng.normal(scale=noise, size=(m, 3))


def sphere(m: int, rng: np.random.Generator, radius: float = 0.1, noise: float = 0.0) -> np.ndarray:
    """m points on a sphere of the given radius (metres) centred at (0.1, 0, 0.85)."""
    d = rng.normal(size=(m, 3))
    return np.array([0.1, 0.0, 0.85]) + radius * d / np.linalg.norm(d, axis=1, keepdims=True) + rng.normal(scale=noise, size=(m, 3))


def box(m: int, rng: np.random.Generator, noise: float = 3e-4) -> np.ndarray:
    """m points on all six faces of a 0.2 x 0.15 x 0.1 m box."""
    size = np.array([0.2, 0.15, 0.1])
    p = (rng.random((m, 3)) - 0.5) * size
    axis = rng.integers(0, 3, m)
    p[np.arange(m), axis] = np.sign(rng.random(m) - 0.5) * size[axis] / 2
    return p + np.array([0.0, 0.0, 0.8]) + rng.normal(scale=noise, size=(m, 3))


def scene(name: str) -> tuple[np.ndarray, np.ndarray]:
    """A named synthetic cloud: points (M, 3) float32 metres, random colours (M, 3) float32."""
    rng = np.random.default_rng(len(name))
    points = {
        "plane": lambda: tilted_plane(8000, rng, noise=2e-4),
        "sphere": lambda: sphere(8000, rng, noise=2e-4),
        "box": lambda: box(10000, rng),
        "noise": lambda: rng.normal(scale=0.05, size=(5000, 3)) + [0.0, 0.0, 0.8],
        "tabletop": lambda: synthetic_tabletop(20000, seed=3)[0],
    }[name]().astype(np.float32)
    return points, rng.random(points.shape).astype(np.float32)


@pytest.mark.parametrize("name", ["plane", "sphere", "box", "noise", "tabletop"])
@pytest.mark.parametrize("viewpoint", [VIEWPOINT, None], ids=["oriented", "unoriented"])
def test_fast_path_matches_reference(name: str, viewpoint: np.ndarray | None) -> None:
    points, colors = scene(name)
    idx, feats = point_features(points, colors, 1024, k=16, viewpoint=viewpoint, seed=1)
    assert idx.shape == (1024,) and idx.dtype == np.int64
    assert feats.shape == (1024, 11) and feats.dtype == np.float32
    ref = reference_features(points, colors, k=16, viewpoint=viewpoint)[idx]

    np.testing.assert_array_equal(feats[:, :6], ref[:, :6].astype(np.float32))
    normals, ref_normals = feats[:, 6:9].astype(np.float64), ref[:, 6:9]
    if viewpoint is None:  # unoriented: compare up to sign
        ref_normals = ref_normals * np.sign(np.sum(normals * ref_normals, axis=1))[:, None]
    assert np.abs(normals - ref_normals).max() <= NORMAL_TOL
    assert np.abs(feats[:, 9:] - ref[:, 9:]).max() <= CURVATURE_TOL


def test_plane_normals_face_the_viewpoint() -> None:
    points = tilted_plane(5000, np.random.default_rng(0)).astype(np.float32)
    true_normal = np.array([0.2, -0.3, 1.0]) / np.linalg.norm([0.2, -0.3, 1.0])
    for viewpoint, sign in [(np.array([0.0, 0.0, 2.0]), 1.0), (np.array([0.0, 0.0, -1.0]), -1.0)]:
        _, feats = point_features(points, np.zeros_like(points), 256, viewpoint=viewpoint)
        np.testing.assert_allclose(feats[:, 6:9], np.tile(sign * true_normal, (256, 1)), atol=1e-5)


def test_curvature_is_flat_on_a_plane_and_larger_on_a_sphere() -> None:
    rng = np.random.default_rng(1)
    flat = tilted_plane(5000, rng).astype(np.float32)
    ball = sphere(5000, rng).astype(np.float32)
    _, plane_feats = point_features(flat, np.zeros_like(flat), 256)
    _, ball_feats = point_features(ball, np.zeros_like(ball), 256)
    np.testing.assert_allclose(plane_feats[:, 9:], np.log(EPS), atol=1e-3)
    assert (ball_feats[:, 9] > np.log(EPS) + 3).all()
    assert (ball_feats[:, 10] > np.log(EPS) + 3).all()
    assert (ball_feats[:, 9] >= ball_feats[:, 10]).all()


def test_deterministic_per_seed() -> None:
    points, colors = scene("tabletop")
    a = point_features(points, colors, 512, seed=4)
    b = point_features(points.copy(), colors.copy(), 512, seed=4)
    c = point_features(points, colors, 512, seed=5)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])


def test_fewer_points_than_samples_repeats() -> None:
    points, colors = scene("sphere")
    points, colors = points[:300], colors[:300]
    idx, feats = point_features(points, colors, 1000, viewpoint=VIEWPOINT)
    assert feats.shape == (1000, 11)
    assert sorted(idx[:300]) == list(range(300))
    np.testing.assert_array_equal(feats[300:600], feats[:300])
    ref = reference_features(points, colors, viewpoint=VIEWPOINT)[idx]
    assert np.abs(feats[:, 6:9] - ref[:, 6:9]).max() <= NORMAL_TOL


def test_knn_includes_self_first_and_caps_k() -> None:
    points = np.random.default_rng(3).random((50, 3))
    nbr = knn(points, 8)
    assert nbr.shape == (50, 8) and nbr.dtype == np.int64
    np.testing.assert_array_equal(nbr[:, 0], np.arange(50))
    np.testing.assert_array_equal(knn(points, 8, query_idx=np.array([7, 3])), nbr[[7, 3]])
    assert knn(points[:5], 16).shape == (5, 5)


def grid_cloud() -> np.ndarray:
    """A rendered-depth-like cloud: two 40 x 30 pixel grids 2 mm apart, one in a tilted view,
    and a few exact duplicates: many equidistant neighbours, inside the k and at its edge."""
    u, v = np.meshgrid(np.arange(40) * 0.002, np.arange(30) * 0.002)
    flat = np.column_stack([u.ravel(), v.ravel(), np.full(u.size, 0.75)])
    tilted = flat @ np.array([[1, 0, 0], [0, 0.8, 0.6], [0, -0.6, 0.8]]) + [0.03, 0.01, 0.0]
    points = np.concatenate([flat, tilted, flat[::97]]).astype(np.float32)
    return points


@pytest.mark.parametrize("cloud", ["grid", "box"])
def test_knn_rows_do_not_depend_on_which_tree_answered(cloud) -> None:
    points = grid_cloud() if cloud == "grid" else scene("box")[0]
    ours, scipys = knn(points, 16), knn(points, 16, tree=NeighbourTree(points, scipy=True))
    np.testing.assert_array_equal(ours, scipys)
    dist = np.linalg.norm(points[ours].astype(np.float64) - points[ours[:, :1]], axis=-1)
    assert np.all(np.diff(dist, axis=1) >= 0)  # nearest first
    tied = np.diff(dist, axis=1) == 0
    assert tied.any() if cloud == "grid" else True
    assert np.all(np.diff(ours, axis=1)[tied] > 0)  # equidistant neighbours by index


def test_building_blocks_match_reference_on_every_point() -> None:
    points, colors = scene("box")
    nbr = knn(points, 16)
    normals = normals_pca(points, nbr, VIEWPOINT)
    ref = reference_features(points, colors, viewpoint=VIEWPOINT)
    assert np.abs(normals - ref[:, 6:9]).max() <= NORMAL_TOL
    assert np.abs(curvature_features(normals, nbr) - ref[:, 9:]).max() <= CURVATURE_TOL


def test_degenerate_neighbourhoods_give_unit_normals() -> None:
    line = np.column_stack([np.linspace(0, 1, 200), np.zeros(200), np.zeros(200)])
    points = np.concatenate([line, np.zeros((20, 3)), line[:50] + [0, 1e-9, 0]])  # line, duplicates
    normals = normals_pca(points, knn(points, 16), viewpoint=None)
    assert np.isfinite(normals).all()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    assert np.abs(normals[60:200, 0]).max() < 1e-6  # pure-line neighbourhoods: normal orthogonal to x


def test_closed_form_eigenvectors_match_lapack() -> None:
    rng = np.random.default_rng(5)
    rot = np.linalg.qr(rng.normal(size=(4000, 3, 3)))[0]
    lam = np.sort(rng.uniform(0, 1, (4000, 3)) ** 4, axis=1)  # spread of conditionings
    lam[:1000, 1] = lam[:1000, 0] * (1 + 1e-9)  # nearly degenerate smallest pair: LAPACK fallback
    lam[1000:1500, 0] = 0.0  # exact planes
    mats = rot @ (lam[:, :, None] * rot.transpose(0, 2, 1))
    vec = _smallest_eigenvectors(*(mats[:, i, j] for i, j in [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]))
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), 1.0, atol=1e-12)
    residual = np.linalg.norm(np.einsum("qij,qj->qi", mats, vec) - lam[:, :1] * vec, axis=1)
    assert residual.max() < 1e-12
    well = slice(1000, None)
    ref = np.linalg.eigh(mats[well])[1][:, :, 0]
    gap = (lam[well, 1] - lam[well, 0]) / (lam[well, 2] - lam[well, 0])
    err = np.abs(np.abs(np.sum(vec[well] * ref, axis=1)) - 1)
    assert err[gap > 1e-3].max() < 1e-10
