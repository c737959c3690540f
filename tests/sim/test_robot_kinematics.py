"""Robot: IK / FK consistency, the measured state at home, and wrist cameras riding on the arms."""

import numpy as np
import pytest

from anchordp3.schemas.camera import CameraRigConfig
from anchordp3.schemas.robot import ASSETS_DIR, RobotSpec, default_robot
from anchordp3.schemas.sim import WorldConfig
from anchordp3.schemas.state import ARMS
from anchordp3.sim.expert import top_down_pose
from anchordp3.sim.world import World

POS_TOL = 1e-3  # metres
ROT_TOL = 1e-2  # radians

def rot_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Geodesic angle between the rotations of two (4, 4) poses, radians."""
    c = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


@pytest.fixture(scope="module")
def world():
    """A physics-only world of the default robot, settled at home."""
    w = World(WorldConfig(), seed=0, render=False)
    w.step(w.cfg.sim.settle_steps)
    return w


@pytest.fixture(scope="module")
def render_world():
    """A render world with small cameras (the first render in a process compiles shaders)."""
    return World(WorldConfig(cameras=CameraRigConfig(width=64, height=48)), seed=0, render=True)


@pytest.mark.parametrize("arm", ARMS)
def test_ik_round_trips_random_joint_configurations_near_home(world, arm):
    robot = world.robot
    rng = np.random.default_rng(7 + ARMS.index(arm))
    home = np.asarray(robot.spec.arm(arm).home_qpos)
    lim = robot.articulation.get_qlimits()[robot.arm_idx[arm]]
    for _ in range(15):
        q = np.clip(home + rng.uniform(-0.4, 0.4, home.shape), lim[:, 0], lim[:, 1])
        target = robot.fk(arm, q)
        sol = robot.ik(arm, target, seed_q=home)
        assert sol is not None, f"IK failed for a pose reached by q={q.round(3).tolist()}"
        assert sol.shape == home.shape
        assert np.all(sol >= lim[:, 0] - 1e-6) and np.all(sol <= lim[:, 1] + 1e-6)
        got = robot.fk(arm, sol)
        assert np.linalg.norm(got[:3, 3] - target[:3, 3]) < POS_TOL
        assert rot_angle(got, target) < ROT_TOL


@pytest.mark.parametrize("arm", ARMS)
def test_ik_reaches_top_down_poses_over_the_table_workspace(world, arm):
    robot = world.robot
    sign = -1.0 if arm == "left" else 1.0  # each arm works its own half of the table
    for x in (0.05, 0.15, 0.3):
        for y in (-0.12, 0.0, 0.15):
            for yaw in (-np.pi / 2, -np.pi / 4):
                target = top_down_pose([sign * x, y, world.table_top + 0.03], yaw)
                sol = robot.ik(arm, target)
                assert sol is not None, f"{arm} cannot reach {(sign * x, y)} yaw {yaw:.2f}"
                got = robot.fk(arm, sol)
                assert np.linalg.norm(got[:3, 3] - target[:3, 3]) < POS_TOL
                assert rot_angle(got, target) < ROT_TOL


def test_fk_returns_a_rigid_world_transform(world):
    for arm in ARMS:
        m = world.robot.fk(arm, np.asarray(world.robot.spec.arm(arm).home_qpos))
        assert m.shape == (4, 4)
        np.testing.assert_allclose(m[3], [0, 0, 0, 1])
        np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-6)
        assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("arm", ARMS)
def test_ik_of_an_unreachable_pose_returns_none(world, arm):
    far = top_down_pose([3.0, 0.0, 1.0], 0.0)
    assert world.robot.ik(arm, far) is None
    below_floor = top_down_pose([0.0, 0.0, -2.0], 0.0)
    assert world.robot.ik(arm, below_floor) is None


def test_ik_does_not_change_the_commanded_targets(world):
    before = world.robot.joint_target().copy()
    world.robot.ik("left", top_down_pose([-0.1, 0.0, world.table_top + 0.05], -np.pi / 2))
    world.robot.fk("right", np.zeros(6))
    np.testing.assert_array_equal(world.robot.joint_target(), before)


def test_settled_state_at_home_matches_the_commanded_home_pose(world):
    robot = world.robot
    L = robot.layout
    s = robot.state()
    assert s.shape == (L.dim,) == (32,)
    for arm in ARMS:
        spec = robot.spec.arm(arm)
        np.testing.assert_allclose(s[L.qpos(arm)], spec.home_qpos, atol=1e-3)
        assert s[L.gripper(arm)] == pytest.approx(1.0, abs=1e-2)
        fk = robot.fk(arm, s[L.qpos(arm)])
        np.testing.assert_allclose(s[L.ee_xyz(arm)], fk[:3, 3], atol=1e-5)
        np.testing.assert_allclose(s[L.ee_rot6(arm)], fk[:3, :2].reshape(-1), atol=1e-5)
        np.testing.assert_allclose(L.ee_matrix(s, arm), fk, atol=1e-5)
    # the commanded action at home is the joint part of the home state
    np.testing.assert_allclose(robot.joint_target(), s[: L.joint_dim], atol=1e-3)


def test_arms_mirror_each_other_at_home(world):
    """The left arm works at world -x, the right at +x (the layout's left/right convention)."""
    s = world.robot.state()
    L = world.robot.layout
    left, right = s[L.ee_xyz("left")], s[L.ee_xyz("right")]
    assert left[0] < 0 < right[0]
    np.testing.assert_allclose(left * [-1, 1, 1], right, atol=1e-4)
    assert left[2] > world.table_top


def test_action_state_completes_a_joint_action_with_fk_poses(world):
    robot = world.robot
    L = robot.layout
    a = robot.joint_target().copy()
    a[L.qpos("left")] += 0.2
    a[L.gripper("right")] = 0.25
    full = robot.action_state(a)
    assert full.shape == (L.dim,)
    np.testing.assert_array_equal(full[: L.joint_dim], a)
    np.testing.assert_allclose(L.ee_matrix(full, "left"), robot.fk("left", a[L.qpos("left")]), atol=1e-9)


def test_robot_from_a_renamed_urdf_behaves_like_the_default(tmp_path):
    text = (ASSETS_DIR / "dual_arm.urdf").read_text()
    for side, short in (("left", "L"), ("right", "R")):
        for i in range(1, 7):
            text = text.replace(f'joint name="{side}_joint{i}"', f'joint name="{short}_axis_{i}"')
    path = tmp_path / "renamed.urdf"
    path.write_text(text)
    d = default_robot().model_dump()
    d["urdf"] = str(path)
    for side, short in (("left", "L"), ("right", "R")):
        d[side]["joints"] = [f"{short}_axis_{i}" for i in range(1, 7)]
    w = World(WorldConfig(robot=RobotSpec.model_validate(d)), seed=0, render=False)
    ref = World(WorldConfig(), seed=0, render=False)
    q = np.array([0.3, -0.2, 1.5, 0.1, 1.2, -0.4])
    for arm in ARMS:
        np.testing.assert_allclose(w.robot.fk(arm, q), ref.robot.fk(arm, q), atol=1e-6)
    np.testing.assert_allclose(w.robot.state(), ref.robot.state(), atol=1e-6)


def test_wrist_cameras_move_rigidly_with_their_arm(render_world):
    w = render_world
    L = w.robot.layout
    w.step(10)

    def poses():
        return {c.name: c.cam2world for c in w.capture(segmentation=False)}

    before = poses()
    ee_before = {a: w.robot.ee_pose(a) for a in ARMS}
    action = w.robot.joint_target().copy()
    action[L.qpos("left")] += [0.4, 0.2, -0.2, 0.3, 0.2, 0.5]
    for _ in range(40):
        w.control_step(action)
    after = poses()
    ee_after = {a: w.robot.ee_pose(a) for a in ARMS}

    assert np.linalg.norm(ee_after["left"][:3, 3] - ee_before["left"][:3, 3]) > 0.05
    # the moved arm's camera moved, and stays fixed in its end-effector frame
    assert np.linalg.norm(after["left_wrist"][:3, 3] - before["left_wrist"][:3, 3]) > 0.05
    local_before = np.linalg.inv(ee_before["left"]) @ before["left_wrist"]
    local_after = np.linalg.inv(ee_after["left"]) @ after["left_wrist"]
    np.testing.assert_allclose(local_after, local_before, atol=1e-4)
    # the wrist camera looks roughly along the approach (ee z) axis, as configured
    assert local_before[:3, 2] @ np.array([0.0, 0.35, 1.0]) / np.linalg.norm([0.0, 0.35, 1.0]) > 0.99
    # the other arm and the world cameras did not move
    for name in ("right_wrist", "head", "front"):
        np.testing.assert_allclose(after[name], before[name], atol=1e-4)
