"""One closed-loop evaluation episode on the simulator side: build and settle the scene of a seed
with rendering, observe it (four camera captures and the robot state), execute a predicted
anchor by a smooth joint-space motion (or, for the dense baseline, follow a chunk of predicted
actions), and check success. No learning code here: the policy side
lives in ``stages/evaluate.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from anchordp3.schemas.sim import WorldConfig
from anchordp3.schemas.state import ARMS
from anchordp3.sim.cameras import ViewCapture
from anchordp3.sim.episode import build
from anchordp3.sim.expert import GRIPPER_SECONDS, HOLD_MAX_STEPS, HOLD_STEPS, HOLD_TOLERANCE

MIN_MOVE_STEPS = 8  # shortest anchor motion, control steps
PEAK_OVER_MEAN = 1.875  # peak / mean speed of a minimum-jerk profile


def min_jerk(n: int) -> np.ndarray:
    """Fractions ``(n,)`` of a minimum-jerk move at steps 1..n, rising from ~0 to exactly 1."""
    s = np.arange(1, n + 1, dtype=np.float64) / max(n, 1)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def gripper_command(value: np.ndarray) -> np.ndarray:
    """Normalised gripper targets ``(arms,)`` -> the command carried out: open (1) or closed (0),
    whichever is nearer. The anchors' grippers are labelled 0 or 1 (the expert opens and closes
    fully); a prediction in between, carried out as it is, drifts over many decisions where the
    policy predicts it relative to the state (an idle gripper closing by a few per cent per
    decision until the policy takes it for a grasp, ladder rung D5)."""
    return (np.asarray(value, dtype=np.float64) >= 0.5).astype(np.float64)


@dataclass
class Observation:
    """What the policy sees at one decision: per-view captures and the measured ``state (32,)``."""

    views: list[ViewCapture]
    state: np.ndarray


class EvalEpisode:
    """The scene of ``(task, seed)`` built with rendering and settled; ``stable`` says whether the
    settled scene passed the stability check. ``steps`` counts control steps executed so far."""

    def __init__(self, task: str, seed: int, cfg: WorldConfig):
        self.task_name, self.seed = task, seed
        self.world, self.task = build(task, seed, cfg, render=True)
        self.stable = self.world.settle_and_check()
        self.robot = self.world.robot
        self.layout = self.robot.layout
        self.dt = cfg.sim.control_dt
        self.steps = 0
        self._rest_z = self._object_heights()

    @property
    def step_limit(self) -> int:
        return int(self.task.step_limit)

    @property
    def steps_left(self) -> int:
        return max(0, self.step_limit - self.steps)

    def instruction(self) -> str:
        """The task's own instruction for this scene (the evaluation uses held-out phrasings)."""
        return self.task.instruction()

    def observe(self) -> Observation:
        """Render all views now (no segmentation: the policy uses the segmenter) and read the state."""
        return Observation(views=self.world.capture(segmentation=False), state=self.robot.state())

    def joint_goal(self, target_state: np.ndarray) -> np.ndarray:
        """The joint-space action ``(2 * (dof + 1),)`` of a 32-d anchor state: both arms' joints and
        grippers (clipped to [0, 1])."""
        target_state = np.asarray(target_state, dtype=np.float64)
        if target_state.shape != (self.layout.dim,):
            raise ValueError(f"target_state: expected ({self.layout.dim},), got {target_state.shape}")
        goal = np.zeros(self.layout.joint_dim)
        for arm in ARMS:
            goal[self.layout.qpos(arm)] = target_state[self.layout.qpos(arm)]
            goal[self.layout.gripper(arm)] = np.clip(target_state[self.layout.gripper(arm)], 0.0, 1.0)
        return goal

    def pose_goal(self, target_state: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """The joint-space action of a 32-d anchor state executed through its end-effector poses:
        each arm's joints solve IK for the anchor's pose, seeded from the anchor's own joints, so a
        small joint error far up the arm does not move the gripper. An arm whose pose has no IK
        solution keeps the anchor's joints. Returns the action and the arms that fell back."""
        goal = self.joint_goal(target_state)
        fell_back = []
        for arm in ARMS:
            pose = self.layout.ee_matrix(np.asarray(target_state, dtype=np.float64), arm)
            q = self.robot.ik(arm, pose, seed_q=goal[self.layout.qpos(arm)])
            if q is None:
                fell_back.append(arm)
            else:
                goal[self.layout.qpos(arm)] = q
        return goal, fell_back

    def execute(self, target_state: np.ndarray, through: str = "joints") -> int:
        """Move from the commanded joint target to the anchor's joint and gripper targets along a
        minimum-jerk profile, timed as the expert times its moves: no faster than the robot's joint
        speed limit, a full gripper stroke in ``GRIPPER_SECONDS``; then hold the target as the
        expert does before it tags an anchor (a few steps, then until the arms have reached it).
        Stops at the step limit; returns the control steps used. An anchor's gripper is a command
        to open or to close (``gripper_command``).

        through: ``joints`` executes the anchor's joint angles (the report); ``pose`` its
        end-effector poses by IK (``pose_goal``)."""
        if through not in ("joints", "pose"):
            raise ValueError(f"through: expected joints or pose, got {through!r}")
        start = self.robot.joint_target()
        end = self.joint_goal(target_state) if through == "joints" else self.pose_goal(target_state)[0]
        q = np.concatenate([np.arange(self.layout.dim)[self.layout.qpos(a)] for a in ARMS])
        g = [self.layout.gripper(a) for a in ARMS]
        end[g] = gripper_command(end[g])
        joint_steps = float(np.abs(end[q] - start[q]).max()) / self.robot.spec.max_joint_speed / self.dt * PEAK_OVER_MEAN
        grip_steps = float(np.abs(end[g] - start[g]).max()) * GRIPPER_SECONDS / self.dt
        n = max(int(np.ceil(max(joint_steps, grip_steps))), MIN_MOVE_STEPS)
        used = 0
        for f in min_jerk(n):
            if self.steps >= self.step_limit:
                return used
            self._step(start + f * (end - start))
            used += 1
        for i in range(HOLD_MAX_STEPS):
            if self.steps >= self.step_limit:
                break
            if i >= HOLD_STEPS and float(np.abs(self.robot.state()[q] - end[q]).max()) < HOLD_TOLERANCE:
                break
            self._step(end)
            used += 1
        return used

    def _step(self, action: np.ndarray) -> None:
        self.world.control_step(action)
        self.steps += 1

    def follow(self, targets: np.ndarray, steps_each: int) -> int:
        """Execute an action chunk, the dense baseline's way: ``targets (n, 32)`` commanded states
        whose joints and grippers are reached in turn, each by linear interpolation over
        ``steps_each`` control steps from the previous command. Stops at the step limit; returns
        the control steps used."""
        used = 0
        start = self.robot.joint_target()
        for target in np.asarray(targets, dtype=np.float64):
            end = self.joint_goal(target)
            for k in range(1, steps_each + 1):
                if self.steps >= self.step_limit:
                    return used
                self._step(start + (k / steps_each) * (end - start))
                used += 1
            start = end
        return used

    def conditions(self) -> dict[str, bool]:
        """The task's success conditions now, by name (``Task.evaluate``)."""
        return {name: bool(met) for name, met in self.task.evaluate().items()}

    def success(self) -> bool:
        return all(self.conditions().values())

    def _object_heights(self) -> dict[str, float]:
        objects = self.world.objects
        return {n: float(objects[n].pose.p[2]) for n in self.task.critical_objects() if n in objects}

    def lift(self) -> float:
        """How far the highest-raised task-critical object is above where it settled, metres
        (about 0 until something is picked up)."""
        now = self._object_heights()
        return max((now[n] - self._rest_z[n] for n in now), default=0.0)

    def gripper_commands(self) -> np.ndarray:
        """The commanded gripper openings of both arms ``(2,)``, 0 closed, 1 open."""
        target = self.robot.joint_target()
        return np.array([target[self.layout.gripper(a)] for a in ARMS])
