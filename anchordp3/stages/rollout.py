"""CPU rollout stage: play the expert on a seed's scene with rendering off and keep successes.

Input item: ``(task, seed)``. Output item: an ``EpisodeRecord`` and, for kept episodes, an
``episodes/<task>/<seed:06d>.npz`` file holding

- ``states (T + 1, 32) float64``: measured state before each action and after the last;
- ``actions (T, 14) float64``: commanded joint-space targets, enough to replay the episode;
- ``physx (T + 1, P) uint8``: the packed PhysX state at the same instants as ``states`` (every
  body's pose and velocity, every joint's): the render stage sets a planned step's state from it
  instead of stepping the physics there (files without it are replayed);
- ``anchor_t (A,) int64`` and ``anchor_name (A,) str``: the atomic-operation boundaries.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from anchordp3.schemas.episode import EpisodeRecord
from anchordp3.schemas.sim import WorldConfig
from anchordp3.sim.episode import run_expert
from anchordp3.stages.files import save_npz


def episode_file(task: str, seed: int) -> str:
    """Path of an episode's arrays relative to the stage folder."""
    return f"episodes/{task}/{seed:06d}.npz"


def rollout(task: str, seed: int, world: WorldConfig, preset: str, out_dir: Path | None = None) -> EpisodeRecord:
    """Run the expert on ``(task, seed)``; when it succeeds and ``out_dir`` is given, write its arrays."""
    res = run_expert(task, seed, world)
    arrays = None
    if res.success and out_dir is not None:
        arrays = episode_file(task, seed)
        save_npz(Path(out_dir) / arrays, {
            "states": res.states,
            "actions": res.actions,
            "physx": res.physx,
            "anchor_t": np.array([a.t for a in res.anchors], dtype=np.int64),
            "anchor_name": np.array([a.name for a in res.anchors]),
        })
    return EpisodeRecord(
        task=task, seed=seed, preset=preset, success=res.success, reason=res.reason, detail=res.detail,
        instruction=res.instruction, steps=len(res.actions), anchors=res.anchors, seconds=res.seconds, arrays=arrays,
    )


def load_episode(stage_dir: Path, record: EpisodeRecord) -> dict[str, np.ndarray]:
    """The arrays of a kept episode (see the module docstring)."""
    if record.arrays is None:
        raise ValueError(f"episode {record.episode_id} has no arrays (it failed or was not saved)")
    with np.load(Path(stage_dir) / record.arrays, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
