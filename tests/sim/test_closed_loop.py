"""Executing predictions in a closed-loop episode: an anchor by a smooth motion, or (dense
baseline) a chunk of actions followed at a fixed spacing."""

from __future__ import annotations

import numpy as np
import pytest

from anchordp3.schemas.run import RunConfig
from anchordp3.schemas.state import ARMS
from anchordp3.sim.closed_loop import MIN_MOVE_STEPS, EvalEpisode, gripper_command


@pytest.fixture(scope="module")
def episode() -> EvalEpisode:
    cfg = RunConfig.model_validate({"name": "cl", "tasks": ["place_mouse"], "seeds": "0", "cameras": {"width": 64, "height": 48}})
    return EvalEpisode("place_mouse", 1000, cfg.world())


def _target(ep: EvalEpisode, offset: float, gripper: float) -> np.ndarray:
    state = ep.robot.state().copy()
    for arm in ARMS:
        state[ep.layout.qpos(arm)] += offset
        state[ep.layout.gripper(arm)] = gripper
    return state


def test_following_a_chunk_commands_each_action_after_its_spacing(episode):
    ep = episode
    steps0 = ep.steps
    targets = np.stack([_target(ep, 0.02, 0.8), _target(ep, 0.04, 0.6)])
    used = ep.follow(targets, steps_each=3)
    assert used == 6 and ep.steps == steps0 + 6
    np.testing.assert_allclose(ep.robot.joint_target(), ep.joint_goal(targets[-1]), atol=1e-9)


def test_executing_an_anchor_ends_at_its_joint_and_gripper_targets(episode):
    ep = episode
    target = _target(ep, -0.05, 1.0)
    used = ep.execute(target)
    assert used >= MIN_MOVE_STEPS
    np.testing.assert_allclose(ep.robot.joint_target(), ep.joint_goal(target), atol=1e-9)
    obs = ep.observe()
    assert len(obs.views) == 4 and obs.state.shape == (ep.layout.dim,)


def test_an_anchors_gripper_is_carried_out_as_open_or_closed_so_it_cannot_drift(episode):
    np.testing.assert_array_equal(gripper_command(np.array([0.83, 0.31])), [1.0, 0.0])
    ep = episode
    for _ in range(3):  # an idle gripper predicted a few per cent more closed each decision stays open
        ep.execute(_target(ep, 0.0, float(ep.robot.state()[ep.layout.gripper(ARMS[0])]) - 0.05))
    assert all(ep.robot.joint_target()[ep.layout.gripper(a)] == 1.0 for a in ARMS)
    ep.execute(_target(ep, 0.0, 0.2))
    assert all(ep.robot.joint_target()[ep.layout.gripper(a)] == 0.0 for a in ARMS)
    ep.execute(_target(ep, 0.0, 1.0))


@pytest.mark.parametrize("task, seed", [("place_mouse", 0), ("place_phone_stand", 1), ("stack_blocks_three", 0)])
@pytest.mark.parametrize("plan", ["anchors", "dense"])
def test_carrying_out_the_experts_own_labels_completes_the_task(tmp_path, task, seed, plan):
    """The evaluation protocol's ceiling: a perfect policy succeeds (each of these failed once
    when anchor moves were timed faster than the expert's gripper strokes)."""
    from anchordp3.stages.oracle import oracle_episode
    from anchordp3.stages.rollout import load_episode, rollout

    cfg = RunConfig.model_validate({"name": "oracle", "tasks": [task], "seeds": str(seed), "cameras": {"width": 32, "height": 24},
                                    "anchors": {"plan": plan}})
    rec = rollout(task, seed, cfg.world(), cfg.preset, tmp_path)
    assert rec.success
    res = oracle_episode(rec, load_episode(tmp_path, rec), cfg)
    assert res.success and res.steps <= rec.steps + 25 * res.decisions


def test_executing_through_the_pose_puts_the_gripper_where_the_anchor_says_despite_a_shoulder_error(episode):
    ep, arm = episode, "left"
    qpos, xyz, rot = ep.layout.qpos(arm), ep.layout.ee_xyz(arm), ep.layout.ee_rot6(arm)
    anchor = ep.robot.state().copy()
    q = anchor[qpos].copy()
    q[1] -= 0.15
    q[2] += 0.2
    pose = ep.robot.fk(arm, q)
    anchor[qpos], anchor[xyz], anchor[rot] = q, pose[:3, 3], pose[:3, :2].reshape(-1)
    wrong = anchor.copy()
    wrong[qpos.start] += 0.02  # 0.02 rad at the shoulder, the end-effector pose still right
    goal, fell_back = ep.pose_goal(wrong)
    assert fell_back == []
    by_pose = ep.robot.fk(arm, goal[qpos])[:3, 3]
    by_joints = ep.robot.fk(arm, wrong[qpos])[:3, 3]
    assert np.linalg.norm(by_pose - pose[:3, 3]) < 2e-3 < 5e-3 < np.linalg.norm(by_joints - pose[:3, 3])
    with pytest.raises(ValueError, match="through"):
        ep.execute(wrong, through="elbows")


def test_the_executor_carries_out_the_first_anchor_the_robot_does_not_already_stand_at(episode):
    from anchordp3.schemas.stages import AnchorsConfig
    from anchordp3.stages.evaluate import act, first_unreached

    ep = episode
    here = ep.robot.state().copy()
    left = ep.layout.ee_xyz(ARMS[0])
    near = here.copy()
    near[left] += np.array([0.01, 0.0, 0.0])  # 1 cm off: where the robot stands, as a tracking error leaves it
    away = _target(ep, -0.05, 1.0)
    away[left] += np.array([0.0, 0.03, 0.0])  # the end effector moves 3 cm
    commands = ep.gripper_commands()
    close = here.copy()
    close[ep.layout.gripper(ARMS[1])] = 0.0  # a close in place is not reached
    assert first_unreached(np.stack([near, away]), here, commands, 0.015) == 1
    assert first_unreached(np.stack([near, close, away]), here, commands, 0.015) == 1
    assert first_unreached(np.stack([near, near]), here, commands, 0.015) == 0  # nothing left to do: the first
    assert first_unreached(np.stack([near, away]), here, commands, 0.005) == 0
    # once closed, a close is done though the gripper, stopped by the object, stays partly open
    held = here.copy()
    held[ep.layout.gripper(ARMS[1])] = 0.7
    assert first_unreached(np.stack([close, away]), held, np.array([1.0, 0.0]), 0.015) == 1
    act(ep, np.stack([near, away]), AnchorsConfig(), "joints", skip_reached=0.015)
    np.testing.assert_allclose(ep.robot.joint_target(), ep.joint_goal(away), atol=1e-9)
    act(ep, np.stack([ep.robot.state(), away]), AnchorsConfig(), "joints", skip_reached=0.0)  # off: always the first
    np.testing.assert_allclose(ep.robot.joint_target(), ep.joint_goal(ep.robot.state()), atol=0.02)
