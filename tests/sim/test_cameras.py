"""The camera rig: four calibrated RGB-D views with per-entity segmentation.

Conventions pinned here: ``cam2world`` maps OpenCV camera coordinates (x right, y down, z forward)
to world; ``K`` is OpenCV intrinsics, integer pixel coordinates at pixel centres; depth is metres
along the optical axis, 0 where nothing is hit.
"""

import numpy as np
import pytest

from anchordp3.geometry.pointcloud import backproject
from anchordp3.schemas.camera import CameraRigConfig, CameraSpec
from anchordp3.schemas.randomization import preset
from anchordp3.schemas.sim import WorldConfig
from anchordp3.sim.episode import build
from anchordp3.sim.world import World

W, H = 64, 48
CFG = WorldConfig(randomization=preset("randomized"), cameras=CameraRigConfig(width=W, height=H))
VIEWS = ("head", "front", "left_wrist", "right_wrist")

@pytest.fixture(scope="module")
def scene():
    """One settled render world of a block task and one capture of all views."""
    world, task = build("stack_blocks_three", 5, CFG, render=True)
    world.settle_and_check()
    caps = world.capture()
    return world, task, {c.name: c for c in caps}, [c.name for c in caps]


def back_project(cap, mask: np.ndarray) -> np.ndarray:
    """World points ``(n, 3)`` of the pixels in ``mask``, from depth, K and cam2world."""
    v, u = np.nonzero(mask)
    pix = np.stack([u, v, np.ones(len(u))])
    cam = np.linalg.inv(cap.K) @ pix * cap.depth[v, u]
    return (cap.cam2world[:3, :3] @ cam + cap.cam2world[:3, 3:4]).T


def interior(mask: np.ndarray) -> np.ndarray:
    """Pixels of ``mask`` whose 8 neighbours are in it too (no edge pixels)."""
    m = mask.copy()
    m[0, :] = m[-1, :] = m[:, 0] = m[:, -1] = False
    core = m.copy()
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            core &= np.roll(np.roll(mask, dv, 0), du, 1)
    return core


def test_four_views_in_configured_order(scene):
    world, _, caps, order = scene
    assert order == list(VIEWS)
    assert world.cameras.names == list(VIEWS)


@pytest.mark.parametrize("view", VIEWS)
def test_images_have_the_configured_shape_and_dtypes(scene, view):
    cap = scene[2][view]
    assert cap.rgb.shape == (H, W, 3) and cap.rgb.dtype == np.uint8
    assert cap.depth.shape == (H, W) and cap.depth.dtype == np.float32
    assert cap.segmentation.shape == (H, W) and cap.segmentation.dtype == np.int32
    assert cap.K.shape == (3, 3) and cap.cam2world.shape == (4, 4)
    assert cap.rgb.std() > 1.0, "the image should show something, not one flat colour"


@pytest.mark.parametrize("view", VIEWS)
def test_intrinsics_follow_fovy_and_resolution(scene, view):
    K = scene[2][view].K
    f = H / 2 / np.tan(np.deg2rad(CFG.cameras.fovy_deg) / 2)
    np.testing.assert_allclose(K, [[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("view", VIEWS)
def test_cam2world_is_a_rigid_transform(scene, view):
    m = scene[2][view].cam2world
    np.testing.assert_allclose(m[3], [0, 0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-5)
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0, abs=1e-5)


def test_head_camera_extrinsics_use_the_opencv_convention(scene):
    spec = next(v for v in CFG.cameras.views if v.name == "head")
    m = scene[2]["head"].cam2world
    r = CFG.randomization
    assert np.linalg.norm(m[:3, 3] - spec.position) <= r.camera_jitter_pos * np.sqrt(3) + 1e-4
    fwd = np.asarray(spec.forward) / np.linalg.norm(spec.forward)
    assert m[:3, 2] @ fwd > np.cos(np.deg2rad(3 * r.camera_jitter_rot_deg))  # z: forward
    assert m[2, 1] < -0.5  # y: image down is world down-ish for a camera looking down at the table
    assert m[0, 0] > 0.99  # x: image right is world +x for a camera looking along +y


@pytest.mark.parametrize("view", VIEWS)
def test_depth_is_positive_and_in_range_where_geometry_is_hit(scene, view):
    cap = scene[2][view]
    hit = cap.segmentation != 0
    assert hit.any()
    assert (cap.depth[hit] > 0).all()
    assert (cap.depth[hit] >= CFG.cameras.near * 0.99).all() and (cap.depth[hit] <= CFG.cameras.far).all()
    assert (cap.depth[~hit] == 0).all()


def test_depth_and_segmentation_are_zero_where_nothing_is_hit():
    rig = CameraRigConfig(width=16, height=12, views=[CameraSpec(name="sky", position=(0.0, 0.0, 3.0), forward=(0.0, 0.0, 1.0), up=(0.0, 1.0, 0.0))])
    world = World(WorldConfig(cameras=rig), seed=0, render=True)
    (cap,) = world.capture()
    assert cap.name == "sky"
    assert (cap.depth == 0).all()
    assert (cap.segmentation == 0).all()


def test_table_pixels_of_the_head_view_back_project_onto_the_table_top(scene):
    world, _, caps, _ = scene
    cap = caps["head"]
    mask = interior(cap.segmentation == world.table.per_scene_id)
    assert mask.sum() > 100
    pts = back_project(cap, mask)
    assert np.abs(pts[:, 2] - world.table_top).max() < 5e-3
    # a half-pixel error in the pixel-centre convention would show as ~4 mm here
    assert np.median(np.abs(pts[:, 2] - world.table_top)) < 1e-3
    assert (np.abs(pts[:, 0]) <= 0.6 + 1e-3).all() and (np.abs(pts[:, 1]) <= 0.35 + 1e-3).all()


@pytest.mark.parametrize("view", VIEWS)
def test_every_view_back_projects_table_pixels_onto_the_table_box_surface(scene, view):
    """Table pixels (top or sides) land on the table box (|x| <= 0.6, |y| <= 0.35, 0 <= z <= top)."""
    world, _, caps, _ = scene
    cap = caps[view]
    mask = interior(cap.segmentation == world.table.per_scene_id)
    if mask.sum() < 5:
        pytest.skip(f"{view} sees too little of the table")
    pts = back_project(cap, mask)
    half = np.array([0.6, 0.35, world.table_top / 2])
    local = np.abs(pts - [0.0, 0.0, world.table_top / 2])
    outside = np.maximum(local - half, 0).max(axis=1)  # distance outside the box, per axis
    inside = (half - local).min(axis=1)  # distance to the nearest face from inside
    assert outside.max() < 5e-3
    assert inside.max() < 5e-3


def test_block_pixels_back_project_into_their_block(scene):
    world, task, caps, _ = scene
    cap = caps["head"]
    for name in task.blocks:
        e = world.objects[name]
        mask = cap.segmentation == e.per_scene_id
        assert mask.any(), f"{name} not visible in the head view"
        pts = back_project(cap, mask)
        d = np.linalg.norm(pts - np.asarray(e.pose.p), axis=1)
        assert d.max() < task.block_half * np.sqrt(3) + 3e-3, name


def test_task_objects_segmentation_ids_appear_in_the_head_view(scene):
    world, task, caps, _ = scene
    ids = world.entity_ids(task.critical_objects())
    assert len(ids) >= len(task.blocks)
    seen = set(np.unique(caps["head"].segmentation).tolist())
    assert ids <= seen, f"missing ids {ids - seen}"
    robot_ids = world.entity_ids([], include_robot=True)
    assert robot_ids & set(np.unique(caps["front"].segmentation).tolist())
    assert not ids & robot_ids
    assert world.table.per_scene_id not in ids


def test_world_cameras_are_jittered_per_seed_but_not_per_build():
    """Same seed → the same calibration; another seed → a jittered one (randomized preset)."""
    def head(seed):
        w = World(CFG, seed, render=True)
        return next(c for c in w.capture(segmentation=False) if c.name == "head").cam2world

    a, b, c = head(11), head(11), head(12)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-4


def test_physics_only_world_refuses_to_capture():
    world = World(CFG, seed=0, render=False)
    assert world.cameras is None
    with pytest.raises(RuntimeError, match="render=False"):
        world.capture()


@pytest.mark.parametrize("width, height", [(64, 48), (160, 120), (320, 240)])
def test_every_view_puts_the_table_top_at_the_same_height_to_a_millimetre(width, height):
    """The features' back-projection of each view's table-top pixels (OpenCV K, integer pixel
    centres) gives one table height: a half-pixel error tilts each view's rays differently."""
    cfg = WorldConfig(randomization=preset("randomized"), cameras=CameraRigConfig(width=width, height=height))
    world, _ = build("place_mouse", 3, cfg, render=True)
    world.settle_and_check()
    heights = {}
    for cap in world.capture():
        table = interior(cap.segmentation == world.table.per_scene_id)
        cloud = backproject(np.where(table, cap.depth, 0), cap.K, cap.cam2world)
        top = cloud.points[np.abs(cloud.points[:, 2] - world.table_top) < 0.02]  # the top, not the sides
        if len(top) >= 50:
            heights[cap.name] = float(np.median(top[:, 2]))
    assert {"head", "front"} <= set(heights), heights
    assert max(heights.values()) - min(heights.values()) < 1e-3, heights
    assert all(abs(h - world.table_top) < 1e-3 for h in heights.values()), (world.table_top, heights)


@pytest.mark.parametrize("shader", ["minimal", "lambert"])
def test_every_shader_pack_renders_the_default_packs_images(shader):
    """Same scene, SAPIEN's deferred pack and a one-pass pack: segmentation identical, depth within
    0.1 mm (``lambert``'s float positions: to a micrometre), colours within one level on all but a
    few edge pixels (the packs rasterise in a different number of passes)."""
    caps = {}
    for name in ("default", shader):
        cfg = WorldConfig(randomization=preset("randomized"), cameras=CameraRigConfig(width=W, height=H, shader=name))
        world, _ = build("stack_blocks_three", 5, cfg, render=True)
        world.settle_and_check()
        caps[name] = world.capture()
    for a, b in zip(caps["default"], caps[shader]):
        np.testing.assert_array_equal(a.segmentation, b.segmentation, err_msg=a.name)
        np.testing.assert_array_equal(a.depth > 0, b.depth > 0, err_msg=a.name)
        assert np.abs(a.depth - b.depth).max() < (1e-6 if shader == "lambert" else 1e-4), a.name
        off = np.abs(a.rgb.astype(int) - b.rgb).max(axis=-1)
        assert (off > 1).mean() < 1e-3, (a.name, off.max())
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.cam2world, b.cam2world)
