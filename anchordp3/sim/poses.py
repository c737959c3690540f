"""Table-top pose helpers shared by tasks: yaw poses, grasp yaw choice, placing a held object."""

from __future__ import annotations

import numpy as np
import sapien

from anchordp3.sim.expert import top_down_pose

HOME_FINGER_YAW = -np.pi / 2  # finger axis along -y at home: the wrist's most comfortable orientation


def yaw_pose(x: float, y: float, z: float, yaw: float) -> sapien.Pose:
    """A SAPIEN pose at (x, y, z) metres rotated ``yaw`` radians about z."""
    return sapien.Pose([x, y, z], [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def entity_yaw(pose: sapien.Pose) -> float:
    """Yaw (radians about z) of a pose whose z axis is (nearly) vertical."""
    m = pose.to_transformation_matrix()
    return float(np.arctan2(m[1, 0], m[0, 0]))


def grasp_yaw(obj_yaw: float, symmetry: int, preferred: float = HOME_FINGER_YAW) -> float:
    """The finger yaw among ``obj_yaw + k * 2π / symmetry``-equivalent grasps (a parallel gripper is
    itself 2-fold symmetric) closest to ``preferred``."""
    step = 2 * np.pi / max(symmetry, 2)
    k = np.round((preferred - obj_yaw) / step)
    return float(obj_yaw + k * step)


def wrap_angle(a: float) -> float:
    """``a`` radians wrapped to [-π, π)."""
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def held_place_pose(obj: sapien.Pose, tcp: np.ndarray, finger_yaw: float, goal_xyz, goal_yaw: float | None) -> np.ndarray:
    """The top-down TCP pose ``(4, 4)`` that puts a held object's origin at ``goal_xyz`` (metres)
    with yaw ``goal_yaw`` (radians; None keeps the object's present yaw), from where the object
    sits in the hand now: ``obj`` its pose, ``tcp`` the TCP pose ``(4, 4)`` whose fingers open
    along ``finger_yaw``. The wrist turns by the object's yaw error, wrapped to [-π, π)."""
    turn = 0.0 if goal_yaw is None else wrap_angle(goal_yaw - entity_yaw(obj))
    offset = np.asarray(obj.p, dtype=np.float64) - tcp[:3, 3]
    c, s = np.cos(turn), np.sin(turn)
    offset[:2] = [c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]]
    return top_down_pose(np.asarray(goal_xyz, dtype=np.float64) - offset, finger_yaw + turn)
