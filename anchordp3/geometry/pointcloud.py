"""Depth images to world-frame point clouds, multi-view fusion and workspace cropping.

Camera convention (OpenCV): x right, y down, z forward; pixel (u, v) = (column, row) with integer
coordinates at pixel centres; depth is the z coordinate in the camera frame (not the ray length).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np


class Cloud(NamedTuple):
    """A point cloud with optional per-point attributes (M points)."""

    points: np.ndarray
    """(M, 3) float32, world frame, metres."""
    colors: np.ndarray | None
    """(M, 3) float32 in [0, 1], or None."""
    labels: np.ndarray | None
    """(M,) uint8 mask / segmentation values, or None."""


def backproject(
    depth: np.ndarray,
    K: np.ndarray,
    cam2world: np.ndarray,
    rgb: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    box: tuple[np.ndarray, np.ndarray] | None = None,
) -> Cloud:
    """Back-project every valid depth pixel to a world point: p = R^-1 (K^-1 [u v 1]^T d - t).

    [R | t] is the world-to-camera transform, i.e. ``cam2world = [[R^T, -R^T t], [0, 1]]``.

    depth: (H, W) float, metres along the optical axis; 0 or non-finite = no hit (skipped).
    K: (3, 3) OpenCV intrinsics.
    cam2world: (4, 4) rigid transform, OpenCV camera frame -> world.
    rgb: optional (H, W, 3) uint8 (0-255) or float (0-1) colours.
    mask: optional (H, W) bool / integer label image; carried along as uint8 labels.
    box: optional ``(lo, hi)`` corners (3,), metres: points outside (``crop_box``) are dropped
        before colours and labels are gathered (the same cloud as cropping afterwards, cheaper).
    Returns: Cloud with M = number of valid (and kept) pixels, in row-major pixel order.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    h, w = depth.shape
    flat = np.flatnonzero(np.isfinite(depth) & (depth > 0))  # row-major pixel numbers: v * W + u
    v, u = np.divmod(flat, w)
    d = depth.ravel()[flat].astype(np.float64)

    cam2world = np.asarray(cam2world, dtype=np.float64)
    # World point = R_c2w (d K^-1 [u v 1]^T) + t_c2w; fold R_c2w K^-1 into one 3x3 matrix and
    # evaluate it one world axis at a time, each a 1-D float32 column (no (P, 3) temporaries, no
    # BLAS call on a 3-wide matrix, and the crop and its gathers on 1-D columns: 2-3x faster on one
    # thread than the stacked matmul and (P, 3) boolean indexing, the same float32 points).
    ray2world = cam2world[:3, :3] @ np.linalg.inv(np.asarray(K, dtype=np.float64))
    u, v = u.astype(np.float64), v.astype(np.float64)
    axes = [((u * ray2world[a, 0] + v * ray2world[a, 1] + ray2world[a, 2]) * d + cam2world[a, 3]).astype(np.float32) for a in range(3)]
    if box is not None:
        kept = np.flatnonzero(inside_box(axes, *box))
        axes, flat = [x.take(kept) for x in axes], flat.take(kept)
    points = np.stack(axes, axis=1)

    # Colours and labels by flat pixel number, one take each.
    colors = None
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != (h, w, 3):
            raise ValueError(f"rgb must be {(h, w, 3)}, got {rgb.shape}")
        colors = rgb.reshape(h * w, 3).take(flat, axis=0).astype(np.float32)
        if np.issubdtype(rgb.dtype, np.integer):
            colors /= 255.0
    labels = None
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != (h, w):
            raise ValueError(f"mask must be {(h, w)}, got {mask.shape}")
        labels = mask.ravel()[flat].astype(np.uint8)
    return Cloud(points, colors, labels)


def fuse_views(views: Sequence[Cloud]) -> Cloud:
    """Concatenate several back-projected views (same world frame) into one cloud.

    views: non-empty sequence of Cloud; colours / labels are kept only if every view has them.
    Returns: Cloud with M = sum of the views' point counts, views in the given order.
    """
    if not views:
        raise ValueError("fuse_views needs at least one view")
    points = np.concatenate([c.points for c in views], axis=0)
    colors = None if any(c.colors is None for c in views) else np.concatenate([c.colors for c in views], axis=0)
    labels = None if any(c.labels is None for c in views) else np.concatenate([c.labels for c in views], axis=0)
    return Cloud(points, colors, labels)


def crop_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Keep-mask of the points inside an axis-aligned box (bounds inclusive).

    points: (M, 3) float, metres; lo, hi: (3,) box corners, metres.
    Returns: (M,) bool.
    """
    points = np.asarray(points)
    return inside_box([points[:, a] for a in range(3)], lo, hi)


def inside_box(columns: Sequence[np.ndarray], lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``crop_box`` on the points' coordinates given as three (M,) columns (x, y, z), bounds
    inclusive: per column, ~3x faster than over (M, 3) then all(). Returns: (M,) bool."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    keep = (columns[0] >= lo[0]) & (columns[0] <= hi[0])
    for axis in (1, 2):
        keep &= (columns[axis] >= lo[axis]) & (columns[axis] <= hi[axis])
    return keep


def table_top_height(points: np.ndarray, bin_size: float = 0.002) -> float | None:
    """Height of the dominant horizontal surface (the table top) of a fused cloud, metres.

    The table fills most views, so its top is the most populated ``bin_size`` z-slab; the height is
    the median z of the points in that slab and its two neighbours. points: (M, 3) metres.
    Returns None for an empty cloud."""
    z = np.asarray(points)[:, 2].astype(np.float64)
    if len(z) == 0:
        return None
    edges = np.arange(z.min(), z.max() + 2 * bin_size, bin_size)
    counts = slab_counts(z, edges)
    k = int(np.argmax(counts))
    near = z[(z >= edges[max(k - 1, 0)]) & (z <= edges[min(k + 2, len(edges) - 1)])]
    return float(np.median(near))


def slab_counts(z: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``np.histogram(z, bins=edges)[0]`` without sorting ``z``: each value's bin from its offset in
    bin widths, moved by one where that lands beside the edge it should not cross (bins
    ``[e_i, e_i+1)``, the last one closed), then one ``bincount``.

    z: (M,) float, inside ``[edges[0], edges[-1]]``; edges: (B + 1,) increasing, evenly spaced
    (``np.arange``). Returns: (B,) int64."""
    nbins = len(edges) - 1
    if nbins < 1:
        return np.zeros(0, np.int64)
    width = (edges[-1] - edges[0]) / nbins
    bins = np.clip(((z - edges[0]) / width).astype(np.int64), 0, nbins - 1)
    bins -= z < edges[bins]  # the guess overshot an edge by rounding
    bins += (z >= edges[np.minimum(bins + 1, nbins)]) & (bins < nbins - 1)  # or fell short of one
    return np.bincount(bins, minlength=nbins)
