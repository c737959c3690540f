"""place_dual_shoes: the success check on hand-placed shoes, the mirrored procedural pair, and the
two-arm expert."""

from __future__ import annotations

import numpy as np
import pytest
import sapien

from anchordp3.schemas.randomization import preset
from anchordp3.schemas.sim import WorldConfig
from anchordp3.sim.episode import build, run_expert
from anchordp3.sim.poses import yaw_pose
from anchordp3.sim.tasks import get_task
from anchordp3.sim.tasks.dual_shoes import PlaceDualShoes, shoe_parts, shoe_size

TASK = "place_dual_shoes"
CLEAN = WorldConfig(randomization=preset("clean"))
RANDOMIZED = WorldConfig(randomization=preset("randomized"))
LAYOUT = RANDOMIZED.robot.layout
ARMS = ("left", "right")


def settled(seed: int = 0, close_gripper: str | None = None):
    world, task = build(TASK, seed, CLEAN, render=False)
    assert world.settle_and_check()
    if close_gripper is not None:
        action = world.robot.joint_target()
        action[LAYOUT.gripper(close_gripper)] = 0.0
        for _ in range(30):
            world.control_step(action)
    return world, task


def put_shoes(world, task: PlaceDualShoes, placed: dict[str, tuple[float, float, float]]) -> None:
    """Teleport each named side's shoe flat onto the table at (x, y, heading), then 0.2 s of physics."""
    for arm, (x, y, yaw) in placed.items():
        e = world.objects[task.shoes[arm]]
        e.set_pose(yaw_pose(x, y, world.table_top + 0.001, yaw))
        body = e.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent)
        body.set_linear_velocity([0, 0, 0])
        body.set_angular_velocity([0, 0, 0])
    world.step(50)


def on_targets(task: PlaceDualShoes, shift: dict[str, tuple[float, float]] | None = None,
               turn: dict[str, float] | None = None) -> dict[str, tuple[float, float, float]]:
    shift, turn = shift or {}, turn or {}
    return {arm: (task.targets[arm][0] + shift.get(arm, (0.0, 0.0))[0], task.targets[arm][1] + shift.get(arm, (0.0, 0.0))[1],
                  task.heading + turn.get(arm, 0.0)) for arm in ARMS}


def test_pair_side_by_side_on_the_mat_counts_as_success():
    world, task = settled()
    put_shoes(world, task, on_targets(task))
    assert task.shoe_ok("left") and task.shoe_ok("right")
    assert task.check_success()


def test_shoe_6cm_from_its_target_is_a_near_miss():
    world, task = settled()
    put_shoes(world, task, on_targets(task, shift={"right": (0.0, 0.06)}))
    assert task.shoe_ok("left") and not task.shoe_ok("right")
    assert not task.check_success()


def test_shoe_turned_35_degrees_is_a_near_miss():
    world, task = settled()
    put_shoes(world, task, on_targets(task, turn={"left": np.deg2rad(35.0)}))
    assert not task.shoe_ok("left")
    assert not task.check_success()


def test_toes_pointing_opposite_ways_is_rejected():
    world, task = settled()
    put_shoes(world, task, on_targets(task, turn={"right": np.pi}))
    assert not task.check_success()


def test_swapped_shoes_are_rejected():
    world, task = settled()
    swapped = on_targets(task)
    swapped["left"], swapped["right"] = swapped["right"], swapped["left"]
    put_shoes(world, task, swapped)
    assert not task.check_success()


def test_pair_on_the_mat_still_gripped_is_not_success():
    world, task = settled(close_gripper="left")
    put_shoes(world, task, on_targets(task))
    assert world.robot.gripper("left") < 0.5
    assert not task.check_success()


def test_left_and_right_shoes_are_mirror_images():
    size = shoe_size(np.random.default_rng(0))
    colours = ((0.5, 0.2, 0.1, 1.0), (0.9, 0.9, 0.9, 1.0), (0.1, 0.1, 0.1, 1.0))
    left, right = shoe_parts(size, "left", *colours), shoe_parts(size, "right", *colours)
    assert len(left) == len(right)
    for a, b in zip(left, right):
        assert a.kind == b.kind and a.size == b.size
        np.testing.assert_allclose(a.pose.p * [1, -1, 1], b.pose.p, atol=1e-9)
    assert any(abs(p.pose.p[1]) > 1e-4 for p in left), "a pair must not be symmetric about its own axis"


def test_shoe_size_and_colour_vary_with_the_seed():
    tasks = [build(TASK, s, RANDOMIZED, render=False)[1] for s in range(6)]
    assert len({round(t.size.length, 4) for t in tasks}) == 6
    assert len({round(t.size.width, 4) for t in tasks}) == 6
    assert len({t.colour for t in tasks}) > 1
    assert all(t.colour in t.instruction() for t in tasks)


def test_critical_objects_are_both_shoes_and_the_mat():
    world, task = build(TASK, 0, RANDOMIZED, render=False)
    assert task.critical_objects() == ["left_shoe", "right_shoe", "mat"]
    assert world.objects["left_shoe"].pose.p[0] < 0 < world.objects["right_shoe"].pose.p[0]


@pytest.mark.parametrize("seed", [0, 1])
def test_expert_grasps_with_both_arms_then_places_left_then_right(seed: int):
    r = run_expert(TASK, seed, RANDOMIZED)
    assert r.success, (r.reason, r.detail)
    assert len(r.actions) <= get_task(TASK).step_limit
    names = [(a.name, a.arm) for a in r.anchors]
    assert names == ([(n, "both") for n in ("PG", "TGO", "TGC", "PG")]
                     + [(n, "left") for n in ("PP", "TPC", "TPO", "PP", "HM")]
                     + [(n, "right") for n in ("PP", "TPC", "TPO", "PP", "HM")])
    tgc = r.anchors[2]
    for arm in ARMS:  # the fingers stopped on the shoe's upper, neither open nor shut
        assert 0.3 < r.states[tgc.t][LAYOUT.gripper(arm)] < 0.9
