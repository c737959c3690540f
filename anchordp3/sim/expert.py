"""The scripted expert: atomic operations whose terminal states are tagged anchors (keyposes).

Every atomic operation (move an arm or both arms, open or close a gripper) drives the world one
control step at a time, recording the measured 32-d state and the commanded joint-space action,
and ends by tagging an anchor with its keypose name:

    PG  pre-grasp            TGO target grasp, open     TGC target grasp, closed
    PP  pre-place            TPC target place, closed   TPO target place, opened
    HM  home                 (tasks may add their own names)

Poses are world-frame ``(4, 4)`` matrices of the tool centre point (between the finger tips):
z is the approach direction, y the finger-opening direction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from anchordp3.schemas.episode import AnchorTag
from anchordp3.schemas.state import ARMS
from anchordp3.sim.world import World

KEYPOSES = ("PG", "TGO", "TGC", "PP", "TPC", "TPO", "HM")
GRIPPER_SECONDS = 0.4  # a full gripper stroke (open to closed), seconds
HOLD_STEPS = 4  # control steps the target is held after each move, at least
HOLD_MAX_STEPS = 25  # ... and at most, while the arms have not reached it
HOLD_TOLERANCE = 0.01  # largest arm-joint error at which a target counts as reached, radians


class ExpertFailure(Exception):
    """The expert could not finish; ``reason`` is one of the rollout failure reasons."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason, self.detail = reason, detail


@dataclass
class Trajectory:
    """What the expert did. states: ``(T + 1, 32)`` measured before each action and after the last;
    actions: ``(T, 14)`` commanded joint-space targets (both arms' qpos and grippers); physx:
    ``T + 1`` packed PhysX states (``World.pack``) at the same instants as ``states``."""

    states: list[np.ndarray] = field(default_factory=list)
    physx: list[bytes] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)
    anchors: list[AnchorTag] = field(default_factory=list)


def top_down_pose(xyz, finger_yaw: float) -> np.ndarray:
    """A TCP pose at ``xyz`` (metres) approaching straight down, fingers opening along world
    direction ``(cos yaw, sin yaw, 0)``."""
    c, s = np.cos(finger_yaw), np.sin(finger_yaw)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = (-s, c, 0.0), (c, s, 0.0), (0.0, 0.0, -1.0), xyz
    return m


def offset_along_approach(pose: np.ndarray, distance: float) -> np.ndarray:
    """``pose`` moved back against its approach direction by ``distance`` metres (pre-grasp = grasp − offset)."""
    out = pose.copy()
    out[:3, 3] = pose[:3, 3] - distance * pose[:3, 2]
    return out


def _smooth(n: int) -> np.ndarray:
    """Minimum-jerk interpolation fractions for steps 1..n, ``(n,)`` from ~0 to 1."""
    s = np.arange(1, n + 1) / n
    return 10 * s**3 - 15 * s**4 + 6 * s**5


class Expert:
    """Executes atomic operations in ``world`` and records the trajectory.

    max_steps: the task's control-step limit; exceeding it raises ``ExpertFailure("step_limit")``.
    """

    def __init__(self, world: World, max_steps: int, linear_speed: float = 0.25, gripper_seconds: float = GRIPPER_SECONDS,
                 hold_steps: int = HOLD_STEPS):
        self.world, self.robot = world, world.robot
        self.layout = world.robot.layout
        self.max_steps = max_steps
        self.linear_speed, self.gripper_seconds, self.hold_steps = linear_speed, gripper_seconds, hold_steps
        self.dt = world.cfg.sim.control_dt
        self.target = self.robot.joint_target()
        self.traj = Trajectory(states=[self.robot.state()], physx=[world.pack()])

    # ----------------------------------------------------------------------------- primitives
    def _step(self, action: np.ndarray) -> None:
        if len(self.traj.actions) >= self.max_steps:
            raise ExpertFailure("step_limit", f"{self.max_steps} control steps")
        self.world.control_step(action)
        self.target = action.copy()
        self.traj.actions.append(action.copy())
        self.traj.states.append(self.robot.state())
        self.traj.physx.append(self.world.pack())

    def _tag(self, name: str, arm: str) -> None:
        self.traj.anchors.append(AnchorTag(name=name, arm=arm, t=len(self.traj.actions)))

    def _arm_q(self, arm: str) -> np.ndarray:
        return self.target[self.layout.qpos(arm)]

    def move_joints(self, goals: dict[str, np.ndarray], name: str) -> None:
        """Joint-space move of one or both arms to ``goals`` (per arm ``(dof,)`` radians), a
        minimum-jerk profile no faster than the robot's joint speed limit."""
        start = self.target.copy()
        end = start.copy()
        for arm, q in goals.items():
            end[self.layout.qpos(arm)] = q
        delta = float(np.abs(end - start).max())
        n = max(int(np.ceil(delta / self.robot.spec.max_joint_speed / self.dt * 1.875)), 8)  # 1.875 = peak/mean speed of min-jerk
        for f in _smooth(n):
            self._step(start + f * (end - start))
        self._hold()
        self._tag(name, self._arm_label(goals))

    def move_pose(self, goals: dict[str, np.ndarray], name: str, linear: bool = False) -> None:
        """Move one or both arms' TCP to world poses ``goals`` (per arm ``(4, 4)``).

        linear: a straight Cartesian line (IK at every control step, each seeded from the last),
        else a joint-space move to the IK solution (seeded from the commanded joints, then, if that
        finds none, from home). Raises ``ExpertFailure("ik_failure")`` when a pose is unreachable."""
        if not linear:
            self.move_joints({arm: self._solve(arm, pose, retry_from_home=True) for arm, pose in goals.items()}, name)
            return
        starts = {arm: self.robot.fk(arm, self._arm_q(arm)) for arm in goals}
        dist = max(float(np.linalg.norm(goals[a][:3, 3] - starts[a][:3, 3])) for a in goals)
        n = max(int(np.ceil(dist / self.linear_speed / self.dt * 1.875)), 6)
        for f in _smooth(n):
            action = self.target.copy()
            for arm, goal in goals.items():
                action[self.layout.qpos(arm)] = self._solve(arm, _interp_pose(starts[arm], goal, f))
            self._step(action)
        self._hold()
        self._tag(name, self._arm_label(goals))

    def set_gripper(self, values: dict[str, float], name: str) -> None:
        """Ramp one or both grippers to normalised openings ``values`` (0 closed, 1 open)."""
        start = self.target.copy()
        end = start.copy()
        for arm, g in values.items():
            end[self.layout.gripper(arm)] = g
        n = max(int(round(self.gripper_seconds / self.dt)), 2)
        for f in np.arange(1, n + 1) / n:
            self._step(start + f * (end - start))
        self._hold()
        self._tag(name, self._arm_label(values))

    def _hold(self, tol: float = HOLD_TOLERANCE, max_steps: int = HOLD_MAX_STEPS) -> None:
        """Hold the target for ``hold_steps`` control steps, then until every arm joint is within
        ``tol`` radians of it (at most ``max_steps`` in all), so anchors are states actually reached."""
        arms = np.concatenate([np.arange(self.layout.dim)[self.layout.qpos(a)] for a in ARMS])
        for i in range(max_steps):
            if i >= self.hold_steps and float(np.abs(self.traj.states[-1][arms] - self.target[arms]).max()) < tol:
                break
            self._step(self.target.copy())

    def reachable(self, arm: str, *poses: np.ndarray) -> bool:
        """Whether a joint-space move could take ``arm`` to every pose ``(4, 4)`` from the
        commanded joints (IK seeded as ``move_pose`` seeds it); nothing moves."""
        return all(self._ik(arm, p, retry_from_home=True) is not None for p in poses)

    def _ik(self, arm: str, pose: np.ndarray, retry_from_home: bool = False) -> np.ndarray | None:
        q = self.robot.ik(arm, pose, seed_q=self._arm_q(arm))
        if q is None and retry_from_home:
            q = self.robot.ik(arm, pose, seed_q=np.asarray(self.robot.spec.arm(arm).home_qpos))
        return q

    def _solve(self, arm: str, pose: np.ndarray, retry_from_home: bool = False) -> np.ndarray:
        q = self._ik(arm, pose, retry_from_home)
        if q is None:
            raise ExpertFailure("ik_failure", f"{arm} arm cannot reach {np.round(pose[:3, 3], 3).tolist()}")
        return q

    @staticmethod
    def _arm_label(goals: dict) -> str:
        return next(iter(goals)) if len(goals) == 1 else "both"

    # ----------------------------------------------------------------------------- skills
    def home(self, arms: tuple[str, ...] = ARMS) -> None:
        """Joint-space move of ``arms`` to the home pose (HM)."""
        self.move_joints({a: np.asarray(self.robot.spec.arm(a).home_qpos) for a in arms}, "HM")

    def grasp(self, arm: str, grasp_pose: np.ndarray, obj: str, pre: float = 0.08, lift: float = 0.08) -> None:
        """PG → TGO → TGC → PG: approach ``grasp_pose`` from ``pre`` metres back, close, lift.

        Raises ``ExpertFailure("grasp_lost")`` when ``obj`` did not come up with the gripper."""
        z0 = float(self.world.objects[obj].pose.p[2])
        if self.target[self.layout.gripper(arm)] < 0.99:
            self.set_gripper({arm: 1.0}, "TGO")
        self.move_pose({arm: offset_along_approach(grasp_pose, pre)}, "PG")
        self.move_pose({arm: grasp_pose}, "TGO", linear=True)
        self.set_gripper({arm: 0.0}, "TGC")
        lifted = grasp_pose.copy()
        lifted[2, 3] += lift
        self.move_pose({arm: lifted}, "PG", linear=True)
        if float(self.world.objects[obj].pose.p[2]) < z0 + 0.5 * lift:
            raise ExpertFailure("grasp_lost", f"{obj} did not lift with the {arm} gripper")

    def grasp_pair(self, grasp_poses: dict[str, np.ndarray], objs: dict[str, str], pre: float = 0.08, lift: float = 0.08) -> None:
        """Both arms at once: PG → TGO → TGC → PG, each arm approaching its ``grasp_poses[arm]``
        from ``pre`` metres back, closing on ``objs[arm]`` and lifting ``lift`` metres (anchors
        tagged ``both``).

        Raises ``ExpertFailure("grasp_lost")`` when an object did not come up with its gripper."""
        z0 = {arm: float(self.world.objects[o].pose.p[2]) for arm, o in objs.items()}
        opening = {arm: 1.0 for arm in grasp_poses if self.target[self.layout.gripper(arm)] < 0.99}
        if opening:
            self.set_gripper(opening, "TGO")
        self.move_pose({arm: offset_along_approach(p, pre) for arm, p in grasp_poses.items()}, "PG")
        self.move_pose(dict(grasp_poses), "TGO", linear=True)
        self.set_gripper({arm: 0.0 for arm in grasp_poses}, "TGC")
        lifted = {arm: p.copy() for arm, p in grasp_poses.items()}
        for p in lifted.values():
            p[2, 3] += lift
        self.move_pose(lifted, "PG", linear=True)
        for arm, o in objs.items():
            if float(self.world.objects[o].pose.p[2]) < z0[arm] + 0.5 * lift:
                raise ExpertFailure("grasp_lost", f"{o} did not lift with the {arm} gripper")

    def place(self, arm: str, place_pose: np.ndarray, obj: str, pre: float = 0.08, retreat: float = 0.08,
              away: np.ndarray | None = None, hold_radius: float = 0.08) -> None:
        """PP → TPC → TPO → PP: carry to ``pre`` metres from ``place_pose``, move in, open, retreat
        ``retreat`` metres.

        away: world direction ``(3,)`` from the place pose to the pre-place and retreat poses
        (normalised here; default straight up). hold_radius: the carried object's origin must be
        within this many metres of the TCP at pre-place, else ``ExpertFailure("grasp_lost")``."""
        d = np.array([0.0, 0.0, 1.0]) if away is None else np.asarray(away, dtype=np.float64) / np.linalg.norm(away)
        above = place_pose.copy()
        above[:3, 3] += pre * d
        self.move_pose({arm: above}, "PP")
        if not self._holding(arm, obj, hold_radius):
            raise ExpertFailure("grasp_lost", f"{obj} dropped while carrying")
        self.move_pose({arm: place_pose}, "TPC", linear=True)
        self.set_gripper({arm: 1.0}, "TPO")
        up = place_pose.copy()
        up[:3, 3] += retreat * d
        self.move_pose({arm: up}, "PP", linear=True)

    def _holding(self, arm: str, obj: str, radius: float = 0.08) -> bool:
        tcp = self.robot.ee_pose(arm)[:3, 3]
        return float(np.linalg.norm(np.asarray(self.world.objects[obj].pose.p) - tcp)) < radius


def _interp_pose(a: np.ndarray, b: np.ndarray, f: float) -> np.ndarray:
    """Pose a fraction ``f`` of the way from ``a`` to ``b``: linear in position, geodesic in rotation."""
    out = np.eye(4)
    out[:3, 3] = (1 - f) * a[:3, 3] + f * b[:3, 3]
    rel = a[:3, :3].T @ b[:3, :3]
    angle = np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0))
    if angle < 1e-9:
        out[:3, :3] = b[:3, :3] if f >= 1 else a[:3, :3]
        return out
    w = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]]) / (2 * np.sin(angle))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    th = f * angle
    out[:3, :3] = a[:3, :3] @ (np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K)
    return out
