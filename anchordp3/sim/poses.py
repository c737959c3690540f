"""Table-top pose helpers shared by tasks: yaw poses and grasp yaw choice."""

from __future__ import annotations

import numpy as np
import sapien

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
