"""Anchor tagging (symbolic and kinematic) and the frame plan of kept episodes."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from anchordp3.schemas.state import StateLayout
from anchordp3.schemas.stages import AnchorsConfig
from anchordp3.stages.anchors import (
    PLAN_COLUMNS,
    anchor_states,
    episode_anchors,
    kinematic_anchors,
    load_plan,
    match_anchors,
    plan_frames,
    reached,
    table_bytes,
)
from anchordp3.stages.rollout import load_episode

L = StateLayout(6)


def _episode(staged, task):
    e = staged[task]
    return e, load_episode(e.root / "rollout", e.record)


@pytest.mark.parametrize("task", ["stack_blocks_three", "place_mouse"])
def test_kinematic_tags_from_commands_match_the_symbolic_tags_within_3_steps(staged, task):
    _, arr = _episode(staged, task)
    pred = kinematic_anchors(arr["states"], arr["actions"])
    matched, n_pred, n_true = match_anchors(pred, arr["anchor_t"], tol=3)
    assert matched / n_pred >= 0.95 and matched / n_true >= 0.95


def test_kinematic_tags_from_states_alone_mark_each_rest_between_motions():
    # rest, arm move, rest, gripper closes, rest, arm move, rest until the end
    T = 60
    states = np.zeros((T + 1, L.dim))
    q, g = L.qpos("left").start, L.gripper("left")
    states[5:21, q] = np.linspace(0, 0.5, 16)
    states[21:, q] = 0.5
    states[:31, g] = 1.0
    states[31:36, g] = np.linspace(1.0, 0.0, 5)
    states[36:, g] = 0.0
    states[45:51, q] = np.linspace(0.5, 0.2, 6)
    states[51:, q] = 0.2
    # a perfectly still rest has no stillest instant: its first state is taken
    assert kinematic_anchors(states).tolist() == [21, 36, T]


def test_anchor_labels_are_measured_states_with_commanded_grippers(staged):
    _, arr = _episode(staged, "stack_blocks_three")
    t = arr["anchor_t"]
    lab = anchor_states(arr["states"], arr["actions"], t)
    j = L.qpos("right")
    np.testing.assert_array_equal(lab[:, j], arr["states"][t][:, j])
    np.testing.assert_array_equal(lab[:, L.gripper("left")], arr["actions"][t - 1, L.gripper("left")])
    closed = arr["anchor_name"] == "TGC"
    assert closed.any() and (lab[closed][:, [L.gripper("left"), L.gripper("right")]].min(axis=1) == 0).all()


REPORT_PLAN = dict(rest_frames=False, relabel_reached=False)  # the report's frames and labels


def test_report_plan_draws_frames_inside_each_interval_labelled_with_the_next_eight_anchors(staged):
    e, arr = _episode(staged, "stack_blocks_three")
    cfg = AnchorsConfig(dagger={"fraction": 0.0}, **REPORT_PLAN)
    anchors = episode_anchors(e.record, arr, cfg)
    table = plan_frames(e.record.task, e.record.seed, anchors, cfg)
    t = table.column("t").to_numpy()
    nxt = table.column("next_anchor").to_numpy()
    bounds = np.concatenate([[0], anchors.t])
    assert len(t) == 2 * len(anchors.t)
    for ti, i in zip(t, nxt):
        assert bounds[i] <= ti < bounds[i + 1]
    labels = np.asarray(table.column("anchors").to_pylist(), dtype=np.float32).reshape(len(t), 8, 32)
    for row, i in zip(labels, nxt):
        want = np.minimum(np.arange(i, i + 8), len(anchors.t) - 1)
        np.testing.assert_array_equal(row, anchors.states[want].astype(np.float32))


def test_plan_is_deterministic_and_depends_on_its_seed(staged):
    e, arr = _episode(staged, "place_mouse")
    cfg = AnchorsConfig()
    a = episode_anchors(e.record, arr, cfg)
    assert table_bytes(plan_frames("place_mouse", 0, a, cfg)) == table_bytes(plan_frames("place_mouse", 0, a, cfg))
    other = plan_frames("place_mouse", 0, a, AnchorsConfig(seed=1)).column("t").to_pylist()
    assert other != plan_frames("place_mouse", 0, a, cfg).column("t").to_pylist()


def test_rest_frames_observe_each_interval_start_labelled_with_the_anchor_after_it(staged):
    e, arr = _episode(staged, "place_mouse")
    cfg = AnchorsConfig(dagger={"fraction": 0.0})
    anchors = episode_anchors(e.record, arr, cfg)
    rows = plan_frames(e.record.task, e.record.seed, anchors, cfg, arr["states"]).to_pylist()
    rest = [r for r in rows if r["kind"] == "rest"]
    starts = np.concatenate([[0], anchors.t[:-1]])
    assert [r["t"] for r in rest] == starts.tolist()  # one per interval, at the previous anchor (home first)
    assert [r["next_anchor"] for r in rest] == list(range(len(anchors.t)))
    assert len(rows) == 3 * len(anchors.t)  # and the report's 2 random frames after each start


def test_frames_that_already_reached_their_anchor_are_labelled_with_the_anchors_after_it(staged):
    e, arr = _episode(staged, "place_mouse")
    states, anchors_cfg = arr["states"], AnchorsConfig(dagger={"fraction": 0.0}, frames_per_interval=40)
    anchors = episode_anchors(e.record, arr, anchors_cfg)
    report = plan_frames("place_mouse", 0, anchors, AnchorsConfig(dagger={"fraction": 0.0}, frames_per_interval=40, **REPORT_PLAN))
    ours = plan_frames("place_mouse", 0, anchors, anchors_cfg, states)
    measured = states[anchors.t]

    def at_first_label(rows):  # frames whose state already is their first label anchor
        return sum(reached(states[r["t"]], measured[r["next_anchor"]], 0.01) and r["next_anchor"] < len(anchors.t) - 1 for r in rows)

    assert at_first_label(report.to_pylist()) > 0  # the report's labels say "go where you are" near each anchor
    assert at_first_label(ours.to_pylist()) == 0
    shifted = [r for r in ours.to_pylist() if r["kind"] == "expert" and not starts_interval(r, anchors)]
    assert any(r["next_anchor"] > interval_of(r["t"], anchors) for r in shifted)


def starts_interval(row, anchors) -> bool:
    return row["t"] == 0 or row["t"] in anchors.t.tolist()


def interval_of(t: int, anchors) -> int:
    return int(np.searchsorted(anchors.t, t, side="right"))


def test_dagger_frames_follow_their_expert_frame_with_the_same_labels(staged):
    e, arr = _episode(staged, "stack_blocks_three")
    cfg = AnchorsConfig(dagger={"fraction": 1.0, "wrong_affordance_prob": 0.5}, **REPORT_PLAN)
    table = plan_frames("stack_blocks_three", 0, episode_anchors(e.record, arr, cfg), cfg).to_pylist()
    assert [r["kind"] for r in table] == ["expert", "dagger"] * (len(table) // 2)
    for ex, dg in zip(table[::2], table[1::2]):
        assert ex["t"] == dg["t"] and ex["anchors"] == dg["anchors"]
        assert dg["dagger_mode"] in ("near_target", "wrong_affordance") and dg["dagger_arm"] in ("left", "right")
    share = AnchorsConfig(dagger={"fraction": 0.1})
    rows = []
    for task in staged:
        ee, aa = _episode(staged, task)
        rows += plan_frames(task, 0, episode_anchors(ee.record, aa, share), share).column("kind").to_pylist()
    assert 0.0 < rows.count("dagger") / rows.count("expert") < 0.3


def test_plan_file_is_a_readable_parquet_table(staged):
    e = staged["blocks_ranking_rgb"]
    table = pq.read_table(e.plan)
    assert set(PLAN_COLUMNS) == set(table.column_names)
    plan = load_plan(e.plan)
    assert plan.anchors.shape == (len(plan), 8, 32)
    assert list(plan.anchor_names) and plan.anchor_t[-1] == e.record.steps


def test_dense_plan_takes_a_frame_every_stride_steps_labelled_with_the_next_commanded_actions(staged):
    from anchordp3.stages.anchors import plan_dense_frames

    e, arr = _episode(staged, "place_mouse")
    cfg = AnchorsConfig(plan="dense", dense={"frame_stride": 3, "action_stride": 2})
    anchors = episode_anchors(e.record, arr, cfg)
    actions, states = arr["actions"], arr["states"]
    T = len(actions)
    table = plan_dense_frames(e.record.task, e.record.seed, anchors, actions, states, cfg)
    path = e.root / "dense.parquet"
    path.write_bytes(table_bytes(table))
    plan = load_plan(path)
    assert plan.t.tolist() == list(range(0, T, 3)) and set(plan.kind) == {"expert"}
    J = L.joint_dim
    for i in (0, len(plan) // 2, len(plan) - 1):
        t = int(plan.t[i])
        steps = np.minimum(t + 2 * np.arange(8), T - 1)
        np.testing.assert_allclose(plan.anchors[i][:, :J], actions[steps, :J], atol=1e-6)  # joints and grippers as commanded
        np.testing.assert_allclose(plan.anchors[i][:, J:], states[steps + 1, J:], atol=1e-6)  # end effectors as reached
