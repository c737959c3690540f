"""Render stage: replay a kept episode and render only its planned frames from every camera.

Input item: a kept episode (rollout arrays) and its frame plan (anchor stage). Output item:
``frames/<task>/<seed:06d>.npz`` with F planned frames and V views (deflated when the frames are
kept, stored as they are when ``keep_frames: false`` prunes their images once featurised):

- ``rgb (F, V, H, W, 3) uint8``; ``depth (F, V, H, W) float32`` metres, 0 = no hit;
- ``mask (F, V, H, W) uint8``: each pixel's role (``sim.masks``): 0 not critical, k the task's k-th
  critical object, 255 the robot (``include_robot``);
- ``K (F, V, 3, 3) float64`` OpenCV intrinsics; ``cam2world (F, V, 4, 4) float64``;
- ``state (F, 32) float32`` the robot state observed (perturbed for DAgger frames);
- ``anchors (F, H, 32) float32`` labels; ``t (F,) int64``; ``kind (F,) uint8`` (0 expert, 1 DAgger);
- ``perturbed (F,) bool`` whether a DAgger frame's wrong pose was reached; ``views (V,)`` names.

Each frame's world is set to the rollout's recorded PhysX state of its step (older rollouts:
replayed through the physics); its robot state must equal the recorded one (checked), so the
frames show the episode that was kept.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from anchordp3.schemas.episode import EpisodeRecord
from anchordp3.schemas.sim import WorldConfig
from anchordp3.schemas.stages import FRAME_KINDS, AnchorsConfig, RenderConfig
from anchordp3.sim.frames import FrameRequest, render_frames
from anchordp3.stages.anchors import load_plan
from anchordp3.stages.files import frames_file, save_npz
from anchordp3.stages.rollout import load_episode

REPLAY_TOLERANCE = 1e-5  # largest |rendered - recorded| state difference accepted at a frame's step


def run_render(record: EpisodeRecord, rollout_dir: Path, plan_path: Path, out_dir: Path, world: WorldConfig,
               cfg: RenderConfig, anchors_cfg: AnchorsConfig = AnchorsConfig(),
               on_frame: Callable[[int], None] | None = None) -> str:
    """Render one episode's planned frames and write them; returns the output's relative path."""
    episode = load_episode(rollout_dir, record)
    plan = load_plan(plan_path)
    requests = [
        FrameRequest(t=int(t), kind=kind, arm=arm, mode=mode, seed=int(s), target_state=labels[0].astype(np.float64))
        for t, kind, arm, mode, s, labels in zip(plan.t, plan.kind, plan.dagger_arm, plan.dagger_mode, plan.dagger_seed, plan.anchors)
    ]
    frames = render_frames(record.task, record.seed, world, episode["actions"], requests, cfg, anchors_cfg.dagger, on_frame,
                           physx=episode.get("physx"))
    for f, req in zip(frames, requests):
        err = float(np.abs(f.episode_state - episode["states"][req.t]).max())
        if err > REPLAY_TOLERANCE:
            raise RuntimeError(f"{record.episode_id}: the rendered world left the recorded episode at step {req.t} by {err:.2e}")
    arrays = {
        "rgb": np.stack([np.stack([v.rgb for v in f.views]) for f in frames]),
        "depth": np.stack([np.stack([v.depth for v in f.views]) for f in frames]).astype(np.float32),
        "mask": np.stack([f.masks for f in frames]).astype(np.uint8),
        "K": np.stack([np.stack([v.K for v in f.views]) for f in frames]).astype(np.float64),
        "cam2world": np.stack([np.stack([v.cam2world for v in f.views]) for f in frames]).astype(np.float64),
        "state": np.stack([f.state for f in frames]).astype(np.float32),
        "anchors": plan.anchors.astype(np.float32),
        "t": plan.t.astype(np.int64),
        "kind": np.array([FRAME_KINDS.index(k) for k in plan.kind], dtype=np.uint8),
        "perturbed": np.array([f.perturbed for f in frames], dtype=bool),
        "views": np.array([v.name for v in frames[0].views]) if frames else np.array([], dtype=str),
    }
    rel = frames_file(record.task, record.seed)
    save_npz(Path(out_dir) / rel, arrays, compress=cfg.keep_frames)  # transient images: read once, then pruned
    return rel


def load_frames(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a rendered-frames file (see the module docstring)."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


AUDIT_ARRAYS = ("rgb", "depth", "mask")  # what ``prune_frames`` drops


def prune_frames(path: Path) -> None:
    """Drop the images (RGB, depth, masks) of a rendered-frames file once its features are
    durable, keeping calibration, states and labels (``render.keep_frames: false``). Idempotent."""
    arrays = load_frames(path)
    if not any(k in arrays for k in AUDIT_ARRAYS):
        return
    save_npz(path, {k: v for k, v in arrays.items() if k not in AUDIT_ARRAYS})
