"""DAgger perturbations: send one arm to a wrong pose so that an off-trajectory frame can be observed.

Two kinds, as in the AnchorDP3 report ("deviate from the optimal trajectory or are about to engage
with incorrect affordances"):

* ``near_target``: the arm's next anchor pose, moved 3–8 cm in a random direction and turned about
  the approach axis;
* ``wrong_affordance``: a top-down pose hovering over another object than the one the next anchor
  is at (a clutter object or another task object).

The caller packs the simulator state before and restores it after observing (see ``frames.py``).
"""

from __future__ import annotations

import numpy as np

from anchordp3.schemas.stages import DaggerConfig
from anchordp3.schemas.state import ARMS
from anchordp3.sim.expert import top_down_pose
from anchordp3.sim.world import World

_MIN_OBJECT_DISTANCE = 0.08  # a wrong object is at least this far (metres) from the right target
_REACH_ACROSS = 0.1  # an arm reaches objects up to this far (metres) past the table's centre line


def _yaw(pose: np.ndarray, angle: float) -> np.ndarray:
    """``pose`` turned by ``angle`` radians about its own approach (z) axis."""
    c, s = np.cos(angle), np.sin(angle)
    out = pose.copy()
    out[:3, :3] = pose[:3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return out


def wrong_pose(world: World, arm: str, target_state: np.ndarray, mode: str, rng: np.random.Generator, cfg: DaggerConfig) -> np.ndarray:
    """A ``(4, 4)`` world TCP pose for ``arm`` that is wrong with respect to the next anchor
    ``target_state (32,)``; falls back to ``near_target`` when no wrong object is in reach."""
    layout = world.robot.layout
    target = layout.ee_matrix(target_state, arm)
    yaw = np.deg2rad(rng.uniform(-1, 1) * cfg.yaw_range_deg)
    if mode == "wrong_affordance":
        side = -1.0 if arm == "left" else 1.0  # the left arm stands at -x
        cands = sorted(
            name for name, e in world.objects.items()
            if np.linalg.norm(np.asarray(e.pose.p[:2]) - target[:2, 3]) > _MIN_OBJECT_DISTANCE and side * e.pose.p[0] > -_REACH_ACROSS
        )
        if cands:
            p = np.asarray(world.objects[cands[int(rng.integers(len(cands)))]].pose.p, dtype=np.float64)
            p[2] += rng.uniform(*cfg.hover)
            finger_yaw = float(np.arctan2(target[1, 1], target[0, 1])) + yaw
            return top_down_pose(p, finger_yaw)
    direction = rng.normal(size=3)
    direction[2] = abs(direction[2])  # never into the table
    direction /= np.linalg.norm(direction)
    out = _yaw(target, yaw)
    out[:3, 3] = target[:3, 3] + direction * rng.uniform(*cfg.offset_range)
    return out


def perturb(world: World, arm: str, target_state: np.ndarray, mode: str, seed: int, cfg: DaggerConfig) -> bool:
    """Drive ``arm`` from where it is to a wrong pose over ``cfg.steps`` control steps (smooth
    joint-space motion; the other arm and both grippers keep their commands). Returns False when
    no wrong pose was reachable (the world is then unchanged)."""
    if arm not in ARMS:
        raise ValueError(f"dagger arm must be one of {ARMS}, got {arm!r}")
    rng = np.random.default_rng(seed)
    robot, layout = world.robot, world.robot.layout
    start = robot.joint_target()
    q = None
    for _ in range(5):
        q = robot.ik(arm, wrong_pose(world, arm, target_state, mode, rng, cfg), seed_q=start[layout.qpos(arm)])
        if q is not None:
            break
    if q is None:
        return False
    end = start.copy()
    end[layout.qpos(arm)] = q
    for i in range(1, cfg.steps + 1):
        s = i / cfg.steps
        f = 10 * s**3 - 15 * s**4 + 6 * s**5
        world.control_step(start + f * (end - start))
    return True
