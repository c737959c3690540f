"""Running one episode: build the scene for a seed, settle, run the expert, check success; and
replaying recorded actions from the same seed."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from anchordp3.schemas.sim import WorldConfig
from anchordp3.sim.expert import AnchorTag, Expert, ExpertFailure
from anchordp3.sim.tasks import get_task
from anchordp3.sim.tasks.base import LayoutFailure, Task
from anchordp3.sim.world import World


@dataclass
class EpisodeResult:
    """One expert rollout. states ``(T + 1, 32)``, actions ``(T, 14)``, physx ``(T + 1, P) uint8``
    (the packed PhysX state at each state's instant; ``(0, 0)`` without a trajectory; see
    ``expert.Trajectory``);
    ``reason`` is None on success, else ``layout_failure``, ``unstable``, ``ik_failure``,
    ``grasp_lost``, ``step_limit`` or ``success_check_failed``."""

    task: str
    seed: int
    success: bool
    reason: str | None
    detail: str
    instruction: str
    states: np.ndarray
    actions: np.ndarray
    physx: np.ndarray
    anchors: list[AnchorTag] = field(default_factory=list)
    seconds: float = 0.0


def build(task_name: str, seed: int, cfg: WorldConfig, render: bool) -> tuple[World, Task]:
    """A fresh world with the task's scene for ``seed`` (not yet settled)."""
    world = World(cfg, seed, render=render)
    task = get_task(task_name)(world)
    task.setup()
    return world, task


def run_expert(task_name: str, seed: int, cfg: WorldConfig) -> EpisodeResult:
    """The CPU rollout of one seed: no rendering; settle, stability check, expert, success check.

    A seed whose objects find no free layout (``LayoutFailure``) is a failed episode with reason
    ``layout_failure``, not an error."""
    t0 = time.perf_counter()
    world = World(cfg, seed, render=False)
    task = get_task(task_name)(world)
    reason, detail = None, ""
    expert = None
    try:
        task.setup()
    except LayoutFailure as e:
        reason, detail = "layout_failure", str(e)
    if reason is None and not world.settle_and_check():
        reason, detail = "unstable", "an object moved or rotated while settling"
    elif reason is None:
        expert = Expert(world, task.step_limit)
        try:
            task.plan(expert)
        except ExpertFailure as e:
            reason, detail = e.reason, e.detail
        else:
            if not task.check_success():
                reason, detail = "success_check_failed", "the expert finished but the goal is not met"
    traj = expert.traj if expert is not None else None
    dim, jdim = world.robot.layout.dim, world.robot.layout.joint_dim
    return EpisodeResult(
        task=task_name, seed=seed, success=reason is None, reason=reason, detail=detail,
        instruction=task.description if reason == "layout_failure" else task.instruction(),
        states=np.asarray(traj.states) if traj else np.zeros((0, dim)),
        actions=np.asarray(traj.actions) if traj else np.zeros((0, jdim)),
        physx=packed_states(traj.physx) if traj else np.zeros((0, 0), np.uint8),
        anchors=list(traj.anchors) if traj else [],
        seconds=time.perf_counter() - t0,
    )


def packed_states(packs: list[bytes]) -> np.ndarray:
    """``(T + 1, P) uint8``: one packed PhysX state (``World.pack``) a row. A scene's pack has one
    length for its whole episode (its bodies and joints do not change)."""
    if len({len(p) for p in packs}) > 1:
        raise ValueError(f"packed states of different lengths: {sorted({len(p) for p in packs})}")
    return np.frombuffer(b"".join(packs), np.uint8).reshape(len(packs), -1).copy()


def replay(task_name: str, seed: int, cfg: WorldConfig, actions: np.ndarray, render: bool = False,
           on_step: Callable[[int, World], None] | None = None) -> np.ndarray:
    """Rebuild the seed's scene, settle it, and execute ``actions (T, 14)``; returns the measured
    states ``(T + 1, 32)``. ``on_step(t, world)`` is called at every state index t (before action t
    and after the last), e.g. to render planned frames."""
    world, _ = build(task_name, seed, cfg, render=render)
    world.settle_and_check()
    states = [world.robot.state()]
    if on_step:
        on_step(0, world)
    for t, a in enumerate(actions):
        world.control_step(a)
        states.append(world.robot.state())
        if on_step:
            on_step(t + 1, world)
    return np.asarray(states)
