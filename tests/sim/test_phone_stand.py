"""place_phone_stand: the success check on hand-placed phones, the procedural phone and stand, and
the expert that leans the phone on the stand."""

from __future__ import annotations

import numpy as np
import pytest
import sapien

from anchordp3.schemas.randomization import preset
from anchordp3.schemas.sim import WorldConfig
from anchordp3.sim.actors import matrix_pose, pose_matrix
from anchordp3.sim.episode import build, run_expert
from anchordp3.sim.poses import yaw_pose
from anchordp3.sim.tasks import get_task
from anchordp3.sim.tasks.phone_stand import PlacePhoneStand

TASK = "place_phone_stand"
CLEAN = WorldConfig(randomization=preset("clean"))
RANDOMIZED = WorldConfig(randomization=preset("randomized"))
LAYOUT = RANDOMIZED.robot.layout


def settled(seed: int = 0, close_gripper: bool = False):
    world, task = build(TASK, seed, CLEAN, render=False)
    assert world.settle_and_check()
    if close_gripper:
        action = world.robot.joint_target()
        action[LAYOUT.gripper(task.arm)] = 0.0
        for _ in range(30):
            world.control_step(action)
    return world, task


def teleport(world, pose: sapien.Pose) -> None:
    e = world.objects["phone"]
    e.set_pose(pose)
    body = e.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent)
    body.set_linear_velocity([0, 0, 0])
    body.set_angular_velocity([0, 0, 0])


def leaning_pose(world, task: PlacePhoneStand, across: float = 0.0, lean_extra: float = 0.0) -> sapien.Pose:
    """The phone leaning on the plate, its lower edge just above the base, shifted ``across``
    metres along the stand's width and tipped ``lean_extra`` radians further back than the plate."""
    s = pose_matrix(world.objects["stand"].pose)
    lean = task.stand.lean + lean_extra
    up = s[:3, :3] @ np.array([0.0, np.sin(lean), np.cos(lean)])
    normal = s[:3, :3] @ np.array([0.0, -np.cos(lean), np.sin(lean)])
    foot = s[:3, :3] @ (np.asarray(task.stand.functional_point) + [across, 0.0, 0.0]) + s[:3, 3]
    m = np.eye(4)
    m[:3, 0], m[:3, 2] = up, normal
    m[:3, 1] = np.cross(normal, up)
    m[:3, 3] = foot + up * (task.phone.length / 2 + 0.002) + normal * (task.phone.thickness / 2 + 0.001)
    return matrix_pose(m)


def test_phone_leaning_on_the_plate_counts_as_success():
    world, task = settled()
    teleport(world, leaning_pose(world, task))
    world.step(100)
    assert task.check_success()


def test_phone_leaning_6cm_to_one_side_is_a_near_miss():
    world, task = settled()
    teleport(world, leaning_pose(world, task, across=0.06))
    world.step(100)
    phone_fp, stand_fp = task.functional_points()
    assert abs(float(phone_fp[2] - stand_fp[2])) < 0.02  # still standing on the base
    assert not task.check_success()


def test_phone_at_the_spot_but_not_leaning_with_the_plate_is_a_near_miss():
    world, task = settled()
    teleport(world, leaning_pose(world, task, lean_extra=np.deg2rad(-25.0)))  # tipped forward past upright
    assert not task.check_success()  # judged at once: it would fall


def test_phone_flat_on_the_table_before_the_stand_is_not_success():
    world, task = settled()
    s = world.objects["stand"].pose
    teleport(world, yaw_pose(s.p[0], s.p[1] - 0.12, world.table_top + task.phone.thickness / 2 + 0.001, 0.0))
    world.step(50)
    assert not task.check_success()


def test_phone_on_the_stand_still_gripped_is_not_success():
    world, task = settled(close_gripper=True)
    teleport(world, leaning_pose(world, task))
    world.step(100)
    assert world.robot.gripper(task.arm) < 0.5
    assert not task.check_success()


def test_phone_and_stand_vary_with_the_seed():
    tasks = [build(TASK, s, RANDOMIZED, render=False)[1] for s in range(6)]
    assert len({round(t.phone.length, 6) for t in tasks}) == 6
    assert len({round(t.stand.lean, 6) for t in tasks}) == 6
    assert len({t.phone.colour for t in tasks}) > 1
    for t in tasks:
        assert t.phone.colour in t.instruction() and t.stand.colour in t.instruction()
        assert np.deg2rad(15) <= t.stand.lean <= np.deg2rad(25)


def test_critical_objects_are_the_phone_and_the_stand_on_the_arms_side():
    for seed in range(6):
        world, task = build(TASK, seed, RANDOMIZED, render=False)
        assert task.critical_objects() == ["phone", "stand"]
        assert task.arm == ("left" if world.objects["phone"].pose.p[0] < 0 else "right")


@pytest.mark.parametrize("seed", [0, 1])
def test_expert_tilts_the_phone_onto_the_stand(seed: int):
    r = run_expert(TASK, seed, RANDOMIZED)
    assert r.success, (r.reason, r.detail)
    assert [a.name for a in r.anchors] == ["PG", "TGO", "TGC", "PG", "PP", "TPC", "TPO", "PP", "HM"]
    assert len(r.actions) <= get_task(TASK).step_limit
    world, task = build(TASK, seed, RANDOMIZED, render=False)
    tgc, tpc = r.anchors[2], r.anchors[5]
    assert 0.5 < r.states[tgc.t][LAYOUT.gripper(task.arm)] < 0.95  # closed on the phone's width
    # grasped top-down; placed with the approach tilted to the plate's slope, into the plate
    approach = {a.name: LAYOUT.ee_matrix(r.states[a.t], task.arm)[:3, 2] for a in (tgc, tpc)}
    assert approach["TGC"][2] < -0.99
    plate_normal = pose_matrix(world.objects["stand"].pose)[:3, :3] @ task.stand.normal
    assert float(approach["TPC"] @ -plate_normal) > 0.99
    assert abs(float(approach["TPC"][2])) < 0.5
