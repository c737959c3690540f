"""Sparse rendering: replay an episode's recorded actions and render only the planned frames.

Expert frames observe the replayed state at step t. A DAgger frame at step t copies the exact
simulator state and drive targets into a second world of the same seed (the "shadow"), drives one
arm there to a wrong pose and renders it. The replayed world itself is never perturbed, so the
rest of the episode (its outcome and later frames) is unchanged bit for bit; PhysX's own
pack/unpack restores poses and velocities but not its solver caches, which after a perturbation
changes later steps by ~1e-4.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from anchordp3.schemas.sim import WorldConfig
from anchordp3.schemas.stages import DaggerConfig, RenderConfig
from anchordp3.sim.cameras import ViewCapture
from anchordp3.sim.dagger import perturb
from anchordp3.sim.episode import build
from anchordp3.sim.masks import critical_entities, depth_diff_masks, segmentation_masks
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
    """What one frame saw: per-view captures, critical masks ``(V, H, W) uint8``, the robot's
    measured ``state (32,)``, and whether a DAgger perturbation was actually applied."""

    views: list[ViewCapture]
    masks: np.ndarray
    state: np.ndarray
    perturbed: bool


def observe(world: World, entities: list, cfg: RenderConfig) -> tuple[list[ViewCapture], np.ndarray]:
    """Render every view now and the critical-object masks by the configured method."""
    caps = world.capture(segmentation=cfg.mask_method == "segmentation")
    if cfg.mask_method == "segmentation":
        return caps, segmentation_masks(caps, entities)
    return caps, depth_diff_masks(world, caps, entities, cfg.depth_diff_tolerance)


def render_frames(task: str, seed: int, world_cfg: WorldConfig, actions: np.ndarray, requests: list[FrameRequest],
                  cfg: RenderConfig = RenderConfig(), dagger: DaggerConfig = DaggerConfig(),
                  on_frame=None) -> tuple[list[RenderedFrame], np.ndarray]:
    """Replay ``actions (T, 14)`` on ``(task, seed)`` and render ``requests`` (sorted by t).

    on_frame(i): called after request i was rendered (progress). Returns the frames in request
    order and the replayed measured states ``(T + 1, 32)``."""
    ts = [r.t for r in requests]
    if ts != sorted(ts) or (ts and (ts[0] < 0 or ts[-1] > len(actions))):
        raise ValueError(f"frame steps must be sorted and within 0..{len(actions)}")
    world, task_obj = build(task, seed, world_cfg, render=True)
    world.settle_and_check()
    entities = critical_entities(world, task_obj.critical_objects(), cfg.include_robot)
    shadow = None
    if any(r.kind == "dagger" for r in requests):
        shadow, shadow_task = build(task, seed, world_cfg, render=True)
        shadow_entities = critical_entities(shadow, shadow_task.critical_objects(), cfg.include_robot)
    frames: list[RenderedFrame] = []
    states = [world.robot.state()]
    k = 0
    for t in range(len(actions) + 1):
        while k < len(requests) and requests[k].t == t:
            req = requests[k]
            if req.kind != "dagger":
                caps, masks = observe(world, entities, cfg)
                frames.append(RenderedFrame(caps, masks, world.robot.state(), False))
            else:
                frames.append(_render_dagger(world, shadow, shadow_entities, req, cfg, dagger))
            if on_frame:
                on_frame(k)
            k += 1
        if t < len(actions):
            world.control_step(actions[t])
            states.append(world.robot.state())
    return frames, np.asarray(states)


def _render_dagger(world: World, shadow: World, entities: list, req: FrameRequest, cfg: RenderConfig, dagger: DaggerConfig) -> RenderedFrame:
    """Copy ``world``'s exact state into ``shadow``, perturb it there, and observe."""
    if req.target_state is None:
        raise ValueError(f"DAgger frame at step {req.t} needs the next anchor's state")
    shadow.unpack(world.pack())
    shadow.robot.restore_drive_targets(world.robot.drive_targets())
    moved = perturb(shadow, req.arm, req.target_state, req.mode, req.seed, dagger)
    caps, masks = observe(shadow, entities, cfg)
    return RenderedFrame(caps, masks, shadow.robot.state(), moved)
