"""The features stage on real rendered frames: shapes, labels from masks, and the fast path's
agreement with the whole-cloud reference."""

from __future__ import annotations

import numpy as np
import pytest
from stage_helpers import FEATURES, FIRST_TASKS

from anchordp3.geometry.features import point_features
from anchordp3.schemas.dataset import MAX_OBJECT_ROLES, ROBOT_ROLE
from anchordp3.geometry.reference import reference_features
from anchordp3.stages.features import frame_cloud, load_features
from anchordp3.stages.render import load_frames


@pytest.mark.parametrize("task", FIRST_TASKS)
def test_each_frame_becomes_n_points_with_11_features_and_labels(staged, task):
    e = staged[task]
    f, frames = load_features(e.features), load_frames(e.frames)
    F, N = len(frames["t"]), FEATURES.n_points
    assert f["points"].shape == (F, N, 11) and f["points"].dtype == np.float32
    roles = set(range(MAX_OBJECT_ROLES + 1)) | {ROBOT_ROLE}
    assert f["labels"].shape == (F, N) and set(np.unique(f["labels"]).tolist()) <= roles
    assert np.isfinite(f["points"]).all()
    np.testing.assert_allclose(np.linalg.norm(f["points"][..., 6:9], axis=-1), 1.0, atol=1e-4)
    lo, hi = np.asarray(FEATURES.workspace_lo), np.asarray(FEATURES.workspace_hi)
    assert (f["points"][..., :3] >= lo - 1e-6).all() and (f["points"][..., :3] <= hi + 1e-6).all()
    assert 0.02 < (f["labels"] > 0).mean() < 0.95  # the robot and task objects, with the table cropped away
    for k in ("state", "anchors", "t", "kind"):
        np.testing.assert_array_equal(f[k], frames[k])


def test_role_labels_come_from_the_rendered_masks(staged):
    frames = load_frames(staged["place_mouse"].frames)
    cloud = frame_cloud(frames, 0, FEATURES)
    for role in np.unique(frames["mask"][0]).tolist():
        n_mask = sum(int(((frames["depth"][0, v] > 0) & (frames["mask"][0, v] == role)).sum()) for v in range(4))
        assert 0 < int((cloud.labels == role).sum()) <= n_mask or role == 0


def test_fast_features_equal_the_whole_cloud_reference_on_a_rendered_frame(staged):
    frames = load_frames(staged["stack_blocks_three"].frames)
    cloud = frame_cloud(frames, 3, FEATURES)
    view = frames["cam2world"][3, 0][:3, 3]
    idx, fast = point_features(cloud.points, cloud.colors, FEATURES.n_points, FEATURES.k, view, seed=7)
    ref = reference_features(cloud.points, cloud.colors, FEATURES.k, view)[idx]
    np.testing.assert_array_equal(fast[:, :6], ref[:, :6])
    normal_err = np.minimum(np.abs(fast[:, 6:9] - ref[:, 6:9]), np.abs(fast[:, 6:9] + ref[:, 6:9])).max()
    assert normal_err <= 1e-4
    assert np.abs(fast[:, 9:] - ref[:, 9:]).max() <= 1e-3


def test_the_table_is_cropped_away_unless_asked_to_keep_it(staged):
    from anchordp3.geometry.pointcloud import table_top_height

    frames = load_frames(staged["place_mouse"].frames)
    whole = frame_cloud(frames, 0, FEATURES.model_copy(update={"table_margin": None}))
    top = table_top_height(whole.points)
    assert (np.abs(whole.points[:, 2] - top) < 1e-3).mean() > 0.3  # the table dominates the uncropped cloud
    cropped = frame_cloud(frames, 0, FEATURES)
    assert len(cropped.points) > 0 and (cropped.points[:, 2] > top + FEATURES.table_margin).all()
    assert cropped.labels.mean() > 1.5 * whole.labels.mean()  # the critical objects' share grows


@pytest.mark.parametrize("task", ["stack_blocks_three", "blocks_ranking_rgb"])
def test_a_task_with_several_critical_objects_labels_each_with_a_role_of_its_own(staged, task):
    labels = load_features(staged[task].features)["labels"]
    objects = {r for r in np.unique(labels).tolist() if 1 <= r <= MAX_OBJECT_ROLES}
    assert objects == {1, 2, 3, 4}, objects  # the three blocks, told apart, and the target pad the table crop keeps


@pytest.mark.parametrize("task", ["stack_blocks_three", "blocks_ranking_rgb"])
def test_the_target_pad_stands_clear_of_the_table_crop_in_every_frame(staged, task):
    labels = load_features(staged[task].features)["labels"]
    assert ((labels == 4).sum(axis=1) > 0).mean() > 0.9  # the goal is observed: role 4, the target
