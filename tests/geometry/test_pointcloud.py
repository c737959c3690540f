"""Depth back-projection, view fusion and workspace cropping."""

from __future__ import annotations

import numpy as np
import pytest

from anchordp3.geometry.pointcloud import Cloud, backproject, crop_box, fuse_views

H, W = 48, 64
K = np.array([[60.0, 0.0, 31.5], [0.0, 62.0, 23.5], [0.0, 0.0, 1.0]])


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) OpenCV camera-to-world pose at ``eye`` looking at ``target`` (x right, y down, z
    forward), image up roughly along world +z."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = eye
    return pose


CAM2WORLD = look_at(np.array([0.3, -0.6, 1.4]), np.array([0.0, 0.1, 0.75]))


def render_plane(cam2world: np.ndarray, height: float) -> tuple[np.ndarray, np.ndarray]:
    """Analytic depth image of the plane z = height, and the world point seen by each pixel."""
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T  # camera frame, z = 1
    dirs = rays @ cam2world[:3, :3].T
    depth = (height - cam2world[2, 3]) / dirs[..., 2]  # camera z of the hit, since rays have z = 1
    return depth.astype(np.float32), cam2world[:3, 3] + depth[..., None] * dirs


def test_plane_is_recovered() -> None:
    depth, world = render_plane(CAM2WORLD, height=0.75)
    assert (depth > 0).all()
    cloud = backproject(depth, K, CAM2WORLD)
    assert cloud.points.shape == (H * W, 3) and cloud.points.dtype == np.float32
    assert cloud.colors is None and cloud.labels is None
    np.testing.assert_allclose(cloud.points, world.reshape(-1, 3), atol=1e-5)
    np.testing.assert_allclose(cloud.points[:, 2], 0.75, atol=1e-5)


def test_matches_the_report_formula() -> None:
    """p = R^-1 (K^-1 [u v 1]^T d - t), [R | t] = world -> camera, pixel by pixel."""
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.3, 2.0, (H, W)).astype(np.float32)
    world2cam = np.linalg.inv(CAM2WORLD)
    R, t = world2cam[:3, :3], world2cam[:3, 3]
    points = backproject(depth, K, CAM2WORLD).points
    for v, u in [(0, 0), (5, 17), (H - 1, W - 1), (30, 2)]:
        expected = np.linalg.inv(R) @ (np.linalg.inv(K) @ np.array([u, v, 1.0]) * depth[v, u] - t)
        np.testing.assert_allclose(points[v * W + u], expected, atol=1e-5)


def test_invalid_pixels_are_skipped_and_attributes_follow() -> None:
    depth, world = render_plane(CAM2WORLD, height=0.75)
    depth[0, :] = 0.0
    depth[1, 3] = np.nan
    depth[2, 5] = np.inf
    rgb = np.random.default_rng(1).integers(0, 256, (H, W, 3), dtype=np.uint8)
    mask = np.zeros((H, W), dtype=bool)
    mask[10:20, 10:30] = True
    valid = np.isfinite(depth) & (depth > 0)

    cloud = backproject(depth, K, CAM2WORLD, rgb=rgb, mask=mask)
    assert len(cloud.points) == valid.sum() == H * W - W - 2
    np.testing.assert_allclose(cloud.points, world[valid], atol=1e-5)
    np.testing.assert_allclose(cloud.colors, rgb[valid] / 255.0, atol=1e-7)
    assert cloud.colors.dtype == np.float32 and cloud.labels.dtype == np.uint8
    np.testing.assert_array_equal(cloud.labels, mask[valid])

    float_rgb = rgb.astype(np.float32) / 255.0
    np.testing.assert_allclose(backproject(depth, K, CAM2WORLD, rgb=float_rgb).colors, cloud.colors, atol=1e-7)


def test_a_box_given_to_backproject_crops_as_cropping_afterwards_would() -> None:
    depth, _ = render_plane(CAM2WORLD, height=0.75)
    rgb = np.random.default_rng(2).integers(0, 256, (H, W, 3), dtype=np.uint8)
    mask = np.random.default_rng(3).random((H, W)) > 0.5
    whole = backproject(depth, K, CAM2WORLD, rgb=rgb, mask=mask)
    lo, hi = whole.points.min(0) + 0.3 * np.ptp(whole.points, 0), whole.points.max(0) - 0.2 * np.ptp(whole.points, 0)
    lo[2], hi[2] = -10.0, 10.0  # a plane: crop in x and y only
    keep = crop_box(whole.points, lo, hi)
    assert 0 < keep.sum() < len(keep)
    boxed = backproject(depth, K, CAM2WORLD, rgb=rgb, mask=mask, box=(lo, hi))
    for got, want in zip(boxed, whole):
        np.testing.assert_array_equal(got, want[keep])


def test_rejects_mismatched_images() -> None:
    depth = np.ones((H, W), dtype=np.float32)
    with pytest.raises(ValueError):
        backproject(depth, K, CAM2WORLD, rgb=np.zeros((H, W + 1, 3), dtype=np.uint8))
    with pytest.raises(ValueError):
        backproject(depth, K, CAM2WORLD, mask=np.zeros((H + 1, W), dtype=bool))


def test_two_views_of_one_plane_agree() -> None:
    other = look_at(np.array([-0.5, 0.4, 1.2]), np.array([0.05, 0.0, 0.75]))
    views = [backproject(render_plane(pose, 0.75)[0], K, pose) for pose in (CAM2WORLD, other)]
    fused = fuse_views(views)
    assert len(fused.points) == 2 * H * W
    np.testing.assert_array_equal(fused.points[: H * W], views[0].points)
    np.testing.assert_allclose(fused.points[:, 2], 0.75, atol=1e-5)


def test_fuse_keeps_attributes_only_if_all_views_have_them() -> None:
    a = Cloud(np.zeros((2, 3), np.float32), np.ones((2, 3), np.float32), np.array([1, 2], np.uint8))
    b = Cloud(np.ones((3, 3), np.float32), np.zeros((3, 3), np.float32), None)
    both = fuse_views([a, a])
    np.testing.assert_array_equal(both.labels, [1, 2, 1, 2])
    assert both.colors.shape == (4, 3)
    mixed = fuse_views([a, b])
    assert mixed.points.shape == (5, 3) and mixed.colors.shape == (5, 3) and mixed.labels is None
    with pytest.raises(ValueError):
        fuse_views([])


def test_crop_box_is_inclusive() -> None:
    points = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.5, 0.2], [1.01, 0.5, 0.5], [0.5, -0.1, 0.5]])
    keep = crop_box(points, lo=np.zeros(3), hi=np.ones(3))
    assert keep.dtype == bool
    np.testing.assert_array_equal(keep, [True, True, True, False, False])


def test_table_top_is_the_densest_horizontal_slab_under_objects_and_walls() -> None:
    from anchordp3.geometry.pointcloud import table_top_height

    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(-0.6, 0.6, (5000, 2)), np.full(5000, 0.7213)]
    box = np.c_[rng.uniform(-0.05, 0.05, (800, 2)), rng.uniform(0.7213, 0.76, 800)]  # an object on it
    wall = np.c_[rng.uniform(-0.6, 0.6, 1500), np.full(1500, 0.5), rng.uniform(0.5, 1.4, 1500)]
    front = np.c_[rng.uniform(-0.6, 0.6, 900), np.full(900, -0.4), rng.uniform(0.0, 0.7213, 900)]
    cloud = rng.permutation(np.concatenate([table, box, wall, front]))
    assert abs(table_top_height(cloud) - 0.7213) < 1e-6
    assert table_top_height(np.zeros((0, 3))) is None


def test_slab_counts_are_numpys_histogram_counts() -> None:
    from anchordp3.geometry.pointcloud import slab_counts
    rng = np.random.default_rng(0)
    z = np.round(rng.normal(0.75, 0.05, 20000), 3).astype(np.float32).astype(np.float64)  # many values on the edges
    edges = np.arange(z.min(), z.max() + 2 * 0.002, 0.002)
    z = np.concatenate([z, edges[[0, 5, -1]]])  # the first, an inner and the last edge itself
    np.testing.assert_array_equal(slab_counts(z, edges), np.histogram(z, bins=edges)[0])
