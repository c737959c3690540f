"""Slow, obviously-correct reference of the 11-d point features, for tests and benchmarks only.

It follows the AnchorDP3 definitions literally: KNN for every point of the cloud, covariance and
``np.linalg.eigh`` per point, S_k = V_k V_k^T and ``np.linalg.eigvalsh`` per point, then FPS with
open3d's legacy ``farthest_point_down_sample``. ``anchordp3.geometry.features.point_features`` must
give the same numbers at the same points. Also home of the synthetic tabletop cloud used by both.
Production code must not import this module.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from anchordp3.geometry.features import NeighbourTree, knn


def reference_normals(points: np.ndarray, k: int = 16, viewpoint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """PCA normals of every point.

    points: (M, 3) float, metres; k: neighbours incl. the point itself; viewpoint: (3,) or None.
    Returns: normals (M, 3) float64, flipped so that n . (viewpoint - p) >= 0 when a viewpoint is
    given; neighbour indices (M, k) int64, nearest first.
    """
    p = np.asarray(points, dtype=np.float64)
    nbr = knn(p, k, tree=NeighbourTree(p, scipy=True))  # scipy's tree; ties broken by index, as in the fast path
    x = p[nbr]  # (M, k, 3)
    x -= x.mean(axis=1, keepdims=True)
    cov = x.transpose(0, 2, 1) @ x / k  # (M, 3, 3)
    normals = np.linalg.eigh(cov)[1][:, :, 0]  # eigenvalues ascending: column 0 = smallest
    if viewpoint is not None:
        flip = np.sum(normals * (np.asarray(viewpoint, dtype=np.float64) - p), axis=1) < 0
        normals[flip] *= -1.0
    return normals, nbr


def reference_curvature(normals: np.ndarray, nbr: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    """Curvature features of every point: log of the two largest eigenvalues of V V^T (+ eps).

    normals: (M, 3); nbr: (M, K) neighbour indices, row k = neighbourhood of point k.
    Returns: (M, 2) float64.
    """
    v = np.cross(normals[:, None, :], normals[nbr])  # (M, K, 3), V_k transposed
    lam = np.linalg.eigvalsh(v.transpose(0, 2, 1) @ v)  # ascending
    return np.log(lam[:, [2, 1]] + eps)


def reference_features(
    points: np.ndarray, colors: np.ndarray, k: int = 16, viewpoint: np.ndarray | None = None, eps: float = 1e-5
) -> np.ndarray:
    """11-d features (x, y, z, r, g, b, nx, ny, nz, c1, c2) of every point. Returns: (M, 11) float64."""
    normals, nbr = reference_normals(points, k, viewpoint)
    return np.concatenate([points, colors, normals, reference_curvature(normals, nbr, eps)], axis=1)


def reference_fps(points: np.ndarray, n: int, start: int = 0) -> np.ndarray:
    """FPS with open3d's legacy ``farthest_point_down_sample``, first pick ``points[start]``.

    points: (M, 3) float, metres; n <= M. Returns: (n,) int64 indices into ``points``, in index
    order (open3d returns the picked points, which are matched back by exact coordinates).
    """
    import open3d as o3d

    p = np.asarray(points, dtype=np.float64)
    picked = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).farthest_point_down_sample(n, start)
    dist, idx = cKDTree(p).query(np.asarray(picked.points))
    if dist.max() > 0:
        raise RuntimeError("open3d returned points that are not in the input cloud")
    return idx.astype(np.int64)


def reference_point_features(
    points: np.ndarray,
    colors: np.ndarray,
    n_samples: int,
    k: int = 16,
    viewpoint: np.ndarray | None = None,
    start: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Whole-cloud features, then open3d FPS. Returns: idx (n,) int64, features (n, 11) float64."""
    feats = reference_features(points, colors, k, viewpoint)
    idx = reference_fps(points, n_samples, start)
    return idx, feats[idx]


def synthetic_tabletop(n_points: int = 150_000, seed: int = 0, noise: float = 5e-4) -> tuple[np.ndarray, np.ndarray]:
    """A tabletop-like scene: 1.2 x 0.8 m table top at z = 0.75 m, three boxes and two spheres on
    it, surfaces sampled uniformly by area, Gaussian position noise, shuffled point order.

    n_points: M; seed: RNG seed; noise: position noise standard deviation, metres.
    Returns: points (M, 3) float32 metres, colors (M, 3) float32 in [0, 1].
    """
    rng = np.random.default_rng(seed)
    table_z = 0.75
    boxes = [  # (centre, size, colour)
        ((0.15, 0.10, table_z + 0.06), (0.10, 0.08, 0.12), (0.85, 0.20, 0.15)),
        ((-0.20, -0.05, table_z + 0.025), (0.16, 0.10, 0.05), (0.15, 0.35, 0.85)),
        ((-0.05, 0.22, table_z + 0.10), (0.05, 0.05, 0.20), (0.95, 0.80, 0.10)),
    ]
    spheres = [((0.30, -0.15, table_z + 0.05), 0.05, (0.20, 0.75, 0.25)), ((-0.35, 0.20, table_z + 0.03), 0.03, (0.60, 0.25, 0.70))]
    n_table, n_boxes = int(0.55 * n_points), int(0.30 * n_points)
    n_spheres = n_points - n_table - n_boxes

    parts = [(_box_top(np.array([0.0, 0.0, table_z]), np.array([1.2, 0.8]), n_table, rng), (0.55, 0.42, 0.30))]
    for (centre, size, colour), m in zip(boxes, _split(n_boxes, len(boxes))):
        parts.append((_box_surface(np.array(centre), np.array(size), m, rng), colour))
    for (centre, radius, colour), m in zip(spheres, _split(n_spheres, len(spheres))):
        d = rng.normal(size=(m, 3))
        parts.append((np.array(centre) + radius * d / np.linalg.norm(d, axis=1, keepdims=True), colour))

    points = np.concatenate([p for p, _ in parts]) + rng.normal(scale=noise, size=(n_points, 3))
    colors = np.concatenate([np.tile(c, (len(p), 1)) for p, c in parts]) + rng.normal(scale=0.03, size=(n_points, 3))
    order = rng.permutation(n_points)
    return points[order].astype(np.float32), np.clip(colors[order], 0.0, 1.0).astype(np.float32)


def _split(n: int, parts: int) -> list[int]:
    """n split into ``parts`` near-equal counts."""
    return [n // parts + (i < n % parts) for i in range(parts)]


def _box_top(centre: np.ndarray, size_xy: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """m uniform points on a horizontal rectangle centred at ``centre``. Returns (m, 3)."""
    xy = (rng.random((m, 2)) - 0.5) * size_xy
    return np.column_stack([xy + centre[:2], np.full(m, centre[2])])


def _box_surface(centre: np.ndarray, size: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """m uniform points on the top and four side faces of an axis-aligned box. Returns (m, 3)."""
    sx, sy, sz = size
    faces = [(2, +1, sx * sy), (0, -1, sy * sz), (0, +1, sy * sz), (1, -1, sx * sz), (1, +1, sx * sz)]  # (axis, side, area)
    area = np.array([f[2] for f in faces])
    face = rng.choice(len(faces), size=m, p=area / area.sum())
    pts = (rng.random((m, 3)) - 0.5) * size
    for i, (axis, side, _) in enumerate(faces):
        pts[face == i, axis] = side * size[axis] / 2
    return pts + centre
