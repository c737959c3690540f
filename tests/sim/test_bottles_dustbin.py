"""put_bottles_dustbin: the success check on hand-placed bottles, the layout that forces a
handover, and the expert."""

from __future__ import annotations

import numpy as np
import pytest
import sapien

from anchordp3.schemas.randomization import preset
from anchordp3.schemas.sim import WorldConfig
from anchordp3.sim.episode import build, run_expert
from anchordp3.sim.expert import top_down_pose
from anchordp3.sim.poses import HOME_FINGER_YAW
from anchordp3.sim.tasks import get_task
from anchordp3.sim.tasks.bottles_dustbin import PutBottlesDustbin

TASK = "put_bottles_dustbin"
CLEAN = WorldConfig(randomization=preset("clean"))
RANDOMIZED = WorldConfig(randomization=preset("randomized"))
LAYOUT = RANDOMIZED.robot.layout


def settled(seed: int = 0):
    world, task = build(TASK, seed, CLEAN, render=False)
    assert world.settle_and_check()
    return world, task


def put(world, name: str, xyz, tilt: float = 0.0) -> None:
    """Teleport a bottle with its bottom centre at ``xyz``, tilted ``tilt`` radians about world x."""
    e = world.objects[name]
    e.set_pose(sapien.Pose(xyz, [np.cos(tilt / 2), np.sin(tilt / 2), 0.0, 0.0]))
    body = e.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent)
    body.set_linear_velocity([0, 0, 0])
    body.set_angular_velocity([0, 0, 0])


def bin_local(world, task: PutBottlesDustbin, x: float, y: float, z: float) -> np.ndarray:
    """World position of (x, y, z) in the dustbin's frame (origin at the floor's underside)."""
    m = world.objects["dustbin"].pose.to_transformation_matrix()
    return m[:3, :3] @ np.array([x, y, z]) + m[:3, 3]


def all_standing_in_bin(world, task: PutBottlesDustbin) -> None:
    for name, xy in zip(task.bottles, task.drop_points()[:3]):
        local = np.linalg.solve(world.objects["dustbin"].pose.to_transformation_matrix(), [*xy, 0.0, 1.0])
        put(world, name, bin_local(world, task, local[0], local[1], task.bin.floor + 0.001))


def test_three_bottles_standing_in_the_bin_count_as_success():
    world, task = settled()
    all_standing_in_bin(world, task)
    world.step(100)
    assert all(task.bottle_in_bin(b) for b in task.bottles)
    assert task.check_success()


def test_bottle_standing_just_outside_the_wall_is_a_near_miss():
    world, task = settled()
    all_standing_in_bin(world, task)
    outside = task.bin.outer_radius + task.models[task.bottles[0]].radius + 0.005
    toward_robot = -outside if task.side > 0 else outside  # a side of the bin with table beyond it
    put(world, task.bottles[0], bin_local(world, task, toward_robot, 0.0, 0.001))
    world.step(100)
    assert not task.bottle_in_bin(task.bottles[0])
    assert all(task.bottle_in_bin(b) for b in task.bottles[1:])
    assert not task.check_success()


def test_bottle_lying_across_the_rim_is_a_near_miss():
    world, task = settled()
    all_standing_in_bin(world, task)
    name = task.bottles[0]
    h = task.models[name].height
    world.step(50)
    # lying along world y across the bin's mouth, its middle over the bin's centre
    put(world, name, bin_local(world, task, 0.0, 0.0, 0.0) + [0.0, -h / 2, task.bin.height + task.models[name].radius + 0.002],
        tilt=-np.pi / 2)
    assert not task.bottle_in_bin(name)
    assert not task.check_success()


def test_bottles_left_on_the_table_are_not_success():
    world, task = settled()
    for i, name in enumerate(task.bottles):
        put(world, name, [task.handover[0] + 0.07 * (i - 1), task.handover[1], world.table_top + 0.001])
    world.step(50)
    assert not any(task.bottle_in_bin(b) for b in task.bottles)
    assert not task.check_success()


@pytest.mark.parametrize("seed", range(12))
def test_some_bottle_lies_beyond_the_bin_arms_reach(seed: int):
    world, task = build(TASK, seed, RANDOMIZED, render=False)
    bin_x = world.objects["dustbin"].pose.p[0]
    assert task.bin_arm == ("right" if bin_x > 0 else "left") and task.far_arm != task.bin_arm
    far = [b for b in task.bottles if np.sign(world.objects[b].pose.p[0]) != np.sign(bin_x)]
    assert far, "every scene needs a handover"
    # the far arm cannot hold even the shortest bottle over the bin's middle: it must hand bottles over
    lowest = task.bin.height + task.drop_clearance + min(m.grasp_height for m in task.models.values())
    over_bin = top_down_pose([*world.objects["dustbin"].pose.p[:2], world.table_top + lowest], HOME_FINGER_YAW)
    assert world.robot.ik(task.far_arm, over_bin, seed_q=np.asarray(world.robot.spec.arm(task.far_arm).home_qpos)) is None


def test_bottle_and_bin_shapes_and_colours_vary_with_the_seed():
    tasks = [build(TASK, s, RANDOMIZED, render=False)[1] for s in range(5)]
    heights = {round(m.height, 6) for t in tasks for m in t.models.values()}
    assert len(heights) == 15
    assert len({round(t.bin.inner_radius, 4) for t in tasks}) == 5
    assert len({m.colour for t in tasks for m in t.models.values()}) > 2
    for t in tasks:
        assert t.bin.colour in t.instruction() and all(m.colour in t.instruction() for m in t.models.values())


def test_critical_objects_are_the_bottles_and_the_bin():
    world, task = build(TASK, 0, RANDOMIZED, render=False)
    assert task.critical_objects() == ["bottle_0", "bottle_1", "bottle_2", "dustbin"]
    assert all(n in world.objects for n in task.critical_objects())


@pytest.mark.parametrize("seed", [0, 1])
def test_expert_hands_far_bottles_over_through_the_middle(seed: int):
    r = run_expert(TASK, seed, RANDOMIZED)
    assert r.success, (r.reason, r.detail)
    assert len(r.actions) <= get_task(TASK).step_limit
    world, task = build(TASK, seed, RANDOMIZED, render=False)
    n_far = sum(np.sign(world.objects[b].pose.p[0]) != task.side for b in task.bottles)
    far_ops = [a for a in r.anchors if a.arm == task.far_arm]
    # per far bottle: one grasp-place onto the handover spot and a home, by the far arm
    assert [a.name for a in far_ops] == ["PG", "TGO", "TGC", "PG", "PP", "TPC", "TPO", "PP", "HM"] * n_far
    for tpo in (a for a in far_ops if a.name == "TPO"):
        np.testing.assert_allclose(r.states[tpo.t][LAYOUT.ee_xyz(task.far_arm)][:2], task.handover, atol=0.03)
    # every bottle is dropped by the bin arm: three releases, and it ends the episode at home
    bin_ops = [a for a in r.anchors if a.arm == task.bin_arm]
    assert [a.name for a in bin_ops].count("TPO") == 3
    assert r.anchors[-1].name == "HM" and r.anchors[-1].arm == task.bin_arm


def test_a_scene_without_room_is_recorded_as_a_layout_failure(monkeypatch):
    def crowded(self):  # every spot on the table taken
        self.table_xy((-0.1, -0.1), (0.1, 0.1), [((0.0, 0.0), 1.0)], radius=0.05, tries=5)

    monkeypatch.setattr(PutBottlesDustbin, "build", crowded)
    r = run_expert(TASK, 0, CLEAN)
    assert not r.success and r.reason == "layout_failure"
    assert "no free table position" in r.detail
    assert r.actions.shape == (0, LAYOUT.joint_dim) and r.anchors == []
