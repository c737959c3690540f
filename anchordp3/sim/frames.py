"""Sparse rendering: bring an episode's world to each planned step and render only those frames.

Two ways to reach step t, the same scene either way:

- **set** (the rollout recorded the PhysX state of every step, ``physx (T + 1, P) uint8``): the
  render world takes that state directly, with no physics stepped at all. Poses and joint states
  are the recorded ones; the robot's link poses are recomputed from its joint positions, which
  may differ from the stepped world's in the last float32 bit (measured: 2.4e-7 in the state).
- **replay** (older rollouts without it): the recorded actions are stepped through the physics
  from the settled scene, as the rollout did.

Expert frames observe the episode's world at step t. A DAgger frame at step t drives one arm to a
wrong pose from the exact simulator state and drive targets of step t and renders it. When steps
are set, the episode's world itself is perturbed: the next frame sets every body's recorded state
again, so nothing of the perturbation reaches it. When steps are replayed, the state and targets
are copied into a second world of the same seed (the "shadow") and perturbed there: the episode's
world must go on stepping unchanged bit for bit, and PhysX's own pack/unpack restores poses and
velocities but not its solver caches, which after a perturbation changes later steps by ~1e-4.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from anchordp3.schemas.sim import WorldConfig
from anchordp3.schemas.stages import DaggerConfig, RenderConfig
from anchordp3.sim.cameras import ViewCapture
from anchordp3.sim.dagger import perturb
from anchordp3.sim.episode import build
from anchordp3.sim.masks import critical_roles, depth_diff_masks, segmentation_masks
from anchordp3.sim.world import World


@dataclass(frozen=True)
class FrameRequest:
    """One planned frame: observe step ``t`` (state index); DAgger frames first send ``arm``
    to a wrong pose (``mode``, drawn from ``seed``) relative to the next anchor ``target_state (32,)``."""

    t: int
    kind: str = "expert"
    arm: str = ""
    mode: str = ""
    seed: int = 0
    target_state: np.ndarray | None = None


@dataclass
class RenderedFrame:
    """What one frame saw: per-view captures, role masks ``(V, H, W) uint8`` (``sim.masks``), the robot's
    measured ``state (32,)``, whether a DAgger perturbation was actually applied, and the
    episode's own ``episode_state (32,)`` at that step (the state before any perturbation)."""

    views: list[ViewCapture]
    masks: np.ndarray
    state: np.ndarray
    perturbed: bool
    episode_state: np.ndarray


def observe(world: World, roles: list, cfg: RenderConfig) -> tuple[list[ViewCapture], np.ndarray]:
    """Render every view now and the critical objects' role masks by the configured method."""
    caps = world.capture(segmentation=True)
    if cfg.mask_method == "segmentation":
        return caps, segmentation_masks(caps, roles)
    return caps, depth_diff_masks(world, caps, roles, cfg.depth_diff_tolerance)


def render_frames(task: str, seed: int, world_cfg: WorldConfig, actions: np.ndarray, requests: list[FrameRequest],
                  cfg: RenderConfig = RenderConfig(), dagger: DaggerConfig = DaggerConfig(),
                  on_frame=None, physx: np.ndarray | None = None) -> list[RenderedFrame]:
    """Render ``requests`` (sorted by t) of the episode ``(task, seed)`` whose ``actions (T, 14)``
    were recorded, at each request's step: set from ``physx (T + 1, P) uint8`` (the recorded PhysX
    state of every step) when given, else by replaying the actions (module docstring).

    on_frame(i): called after request i was rendered (progress). Returns the frames in request order."""
    ts = [r.t for r in requests]
    if ts != sorted(ts) or (ts and (ts[0] < 0 or ts[-1] > len(actions))):
        raise ValueError(f"frame steps must be sorted and within 0..{len(actions)}")
    if physx is not None and len(physx) != len(actions) + 1:
        raise ValueError(f"physx: expected {len(actions) + 1} recorded states, got {len(physx)}")
    world, task_obj = build(task, seed, world_cfg, render=True)
    if physx is None:
        world.settle_and_check()  # a set state needs no settling: it replaces every body's
    roles = critical_roles(world, task_obj.critical_objects(), cfg.include_robot)
    start_targets = world.robot.drive_targets()
    shadow, shadow_roles = world, roles  # set steps: a perturbation is undone by the next frame's set
    if physx is None and any(r.kind == "dagger" for r in requests):
        shadow, shadow_task = build(task, seed, world_cfg, render=True)
        shadow_roles = critical_roles(shadow, shadow_task.critical_objects(), cfg.include_robot)

    replayed = 0  # control steps the episode's world has executed (replay)

    def at_step(t: int) -> None:
        """Bring the episode's world, and its drive targets, to step ``t`` (never earlier than the last)."""
        nonlocal replayed
        if physx is None:
            for action in actions[replayed:t]:
                world.control_step(action)
            replayed = max(replayed, t)
            return
        world.unpack(physx[t].tobytes())
        if t == 0:
            world.robot.restore_drive_targets(start_targets)
        else:
            world.robot.command(actions[t - 1])  # the targets the recorded step left

    frames: list[RenderedFrame] = []
    for k, req in enumerate(requests):
        at_step(req.t)
        episode_state = world.robot.state()
        if req.kind != "dagger":
            caps, masks = observe(world, roles, cfg)
            frames.append(RenderedFrame(caps, masks, episode_state, False, episode_state))
        else:
            frames.append(_render_dagger(world, shadow, shadow_roles, req, cfg, dagger, episode_state))
        if on_frame:
            on_frame(k)
    return frames


def _render_dagger(world: World, shadow: World, roles: list, req: FrameRequest, cfg: RenderConfig, dagger: DaggerConfig,
                   episode_state: np.ndarray) -> RenderedFrame:
    """Copy ``world``'s exact state into ``shadow`` (unless they are one world), perturb it there,
    and observe."""
    if req.target_state is None:
        raise ValueError(f"DAgger frame at step {req.t} needs the next anchor's state")
    if shadow is not world:
        shadow.unpack(world.pack())
        shadow.robot.restore_drive_targets(world.robot.drive_targets())
    moved = perturb(shadow, req.arm, req.target_state, req.mode, req.seed, dagger)
    caps, masks = observe(shadow, roles, cfg)
    return RenderedFrame(caps, masks, shadow.robot.state(), moved, episode_state)
