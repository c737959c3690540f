"""The render stage: only planned frames, two mask methods that agree, DAgger frames that leave
the episode untouched, deterministic bytes."""

from __future__ import annotations

import hashlib
import zipfile

import numpy as np
import pytest
from stage_helpers import ANCHORS, FIRST_TASKS, SMALL_WORLD, stage_episode

from anchordp3.schemas.stages import RenderConfig
from anchordp3.sim.episode import build
from anchordp3.sim.frames import FrameRequest, render_frames
from anchordp3.sim.masks import ROBOT_ROLE, critical_roles, segmentation_masks
from anchordp3.stages.anchors import load_plan
from anchordp3.stages.render import AUDIT_ARRAYS, load_frames, prune_frames
from anchordp3.stages.rollout import load_episode


@pytest.mark.parametrize("task", FIRST_TASKS)
def test_every_planned_frame_is_rendered_from_four_views(staged, task):
    e = staged[task]
    plan, frames = load_plan(e.plan), load_frames(e.frames)
    F, V, H, W = len(plan), 4, SMALL_WORLD.cameras.height, SMALL_WORLD.cameras.width
    assert frames["rgb"].shape == (F, V, H, W, 3) and frames["rgb"].dtype == np.uint8
    assert frames["depth"].shape == frames["mask"].shape == (F, V, H, W)
    assert frames["K"].shape == (F, V, 3, 3) and frames["cam2world"].shape == (F, V, 4, 4)
    np.testing.assert_array_equal(frames["t"], plan.t)
    np.testing.assert_array_equal(frames["anchors"], plan.anchors)
    assert list(frames["views"]) == ["head", "front", "left_wrist", "right_wrist"]
    assert 0.005 < (frames["mask"] > 0).mean() < 0.5  # something, not everything, is critical


def test_expert_frames_observe_the_recorded_states(staged):
    e = staged["stack_blocks_three"]
    frames = load_frames(e.frames)
    states = load_episode(e.root / "rollout", e.record)["states"]
    expert = frames["kind"] == 0
    np.testing.assert_allclose(frames["state"][expert], states[frames["t"][expert]].astype(np.float32), atol=1e-6)


def _requests(plan) -> list[FrameRequest]:
    return [FrameRequest(int(plan.t[i]), plan.kind[i], plan.dagger_arm[i], plan.dagger_mode[i], int(plan.dagger_seed[i]),
                         plan.anchors[i][0].astype(np.float64)) for i in range(len(plan))]


@pytest.mark.parametrize("reach", ["set", "replay"])
def test_dagger_frames_show_a_perturbed_arm_and_leave_the_episode_unchanged(staged, reach):
    e = staged["stack_blocks_three"]
    plan = load_plan(e.plan)
    episode = load_episode(e.root / "rollout", e.record)
    physx = episode["physx"] if reach == "set" else None
    dagger = [i for i, k in enumerate(plan.kind) if k == "dagger"]
    assert dagger, "the plan has DAgger frames"
    requests = _requests(plan)
    with_dagger = render_frames("stack_blocks_three", 0, SMALL_WORLD, episode["actions"], requests, dagger=ANCHORS.dagger, physx=physx)
    expert_only = [r for r in requests if r.kind != "dagger"]
    without = render_frames("stack_blocks_three", 0, SMALL_WORLD, episode["actions"], expert_only, physx=physx)
    kept = [f for i, f in enumerate(with_dagger) if i not in dagger]
    for a, b in zip(kept, without):  # the remaining frames, and the episode's state at each, bit for bit
        np.testing.assert_array_equal(np.stack([v.rgb for v in a.views]), np.stack([v.rgb for v in b.views]))
        np.testing.assert_array_equal(a.episode_state, b.episode_state)
    for i in dagger:
        f = with_dagger[i]
        assert f.perturbed
        assert np.abs(f.state - f.episode_state).max() > 0.01  # the arm was somewhere else
        np.testing.assert_allclose(f.episode_state, episode["states"][plan.t[i]], atol=1e-6)


def test_setting_the_recorded_states_renders_what_replaying_the_physics_renders(staged):
    """The rollout's packed PhysX states put every body where the replay puts it: the same
    segmentation and states to float32 rounding, colours and depth equal on all but a few pixels."""
    e = staged["place_mouse"]
    plan = load_plan(e.plan)
    episode = load_episode(e.root / "rollout", e.record)
    assert episode["physx"].shape[0] == len(episode["states"]) and episode["physx"].dtype == np.uint8
    requests = [r for r in _requests(plan) if r.kind != "dagger"]
    set_ = render_frames("place_mouse", 0, SMALL_WORLD, episode["actions"], requests, physx=episode["physx"])
    replayed = render_frames("place_mouse", 0, SMALL_WORLD, episode["actions"], requests)
    for a, b in zip(set_, replayed):
        np.testing.assert_allclose(a.state, b.state, atol=1e-6)
        rgb_a, rgb_b = np.stack([v.rgb for v in a.views]), np.stack([v.rgb for v in b.views])
        assert (rgb_a != rgb_b).any(axis=-1).mean() < 1e-3
        assert (a.masks != b.masks).mean() < 1e-3
        depth_a, depth_b = np.stack([v.depth for v in a.views]), np.stack([v.depth for v in b.views])
        assert (np.abs(depth_a - depth_b) > 1e-4).mean() < 1e-3


def test_segmentation_and_depth_difference_masks_agree(tmp_path, staged):
    e = staged["place_mouse"]
    seg = load_frames(e.frames)
    depth = stage_episode(tmp_path, "place_mouse", 0, render=RenderConfig(mask_method="depth_diff"))
    dd = load_frames(depth.frames)
    np.testing.assert_array_equal(seg["rgb"], dd["rgb"])
    agree = (seg["mask"] == dd["mask"]).mean()
    assert agree > 0.999, agree


@pytest.mark.parametrize("task_name", ["place_mouse", "blocks_ranking_rgb"])
def test_masks_label_each_critical_object_with_its_role_the_robot_apart_and_nothing_else(task_name):
    world, task = build(task_name, 1, SMALL_WORLD, render=True)
    world.settle_and_check()
    caps = world.capture()
    roles = critical_roles(world, task.critical_objects(), include_robot=True)
    masks = segmentation_masks(caps, roles)
    role_of = {e.per_scene_id: role for role, ents in roles for e in ents}
    names = task.critical_objects()
    assert [r for r, _ in roles] == list(range(1, len(names) + 1)) + [ROBOT_ROLE]
    for c, m in zip(caps, masks):
        for seg_id in np.unique(c.segmentation):
            assert set(np.unique(m[c.segmentation == seg_id]).tolist()) == {role_of.get(int(seg_id), 0)}
    head = caps[0].segmentation
    seen = set(np.unique(masks[0]).tolist())
    for k, n in enumerate(names):  # every critical object in view carries its own role, in the task's order
        if n in world.objects and (head == world.objects[n].per_scene_id).any():
            assert k + 1 in seen
    robot_only = segmentation_masks(caps, critical_roles(world, [], include_robot=True))
    assert set(np.unique(robot_only).tolist()) == {0, ROBOT_ROLE} and (robot_only > 0).sum() < (masks > 0).sum()


def test_rendering_an_episode_twice_gives_the_same_bytes(tmp_path, staged):
    again = stage_episode(tmp_path, "place_mouse", 0)
    digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()  # noqa: E731
    assert digest(again.frames) == digest(staged["place_mouse"].frames)
    assert digest(again.features) == digest(staged["place_mouse"].features)


def test_transient_frames_are_stored_without_deflate_and_give_the_same_features(tmp_path, staged):
    """``keep_frames: false``: the frames file is stored (no deflate), its arrays and the features
    made from it equal the deflated file's; pruning leaves the calibration and labels only."""
    kept = staged["place_mouse"]
    transient = stage_episode(tmp_path, "place_mouse", 0, render=RenderConfig(keep_frames=False))
    with zipfile.ZipFile(kept.frames) as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_DEFLATED}
    with zipfile.ZipFile(transient.frames) as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
    a, b = load_frames(kept.frames), load_frames(transient.frames)
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert transient.features.read_bytes() == kept.features.read_bytes()
    prune_frames(transient.frames)
    assert set(load_frames(transient.frames)) == set(a) - set(AUDIT_ARRAYS)
