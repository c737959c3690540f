"""Helpers: small real episodes through rollout → anchors → render → features, shared by the stage tests."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


from anchordp3.schemas.camera import CameraRigConfig
from anchordp3.schemas.episode import EpisodeRecord
from anchordp3.schemas.sim import WorldConfig, world_config
from anchordp3.schemas.stages import AnchorsConfig, FeaturesConfig, RenderConfig
from anchordp3.stages.anchors import run_anchors
from anchordp3.stages.features import run_features
from anchordp3.stages.render import run_render
from anchordp3.stages.rollout import rollout

SMALL_WORLD: WorldConfig = world_config("randomized", cameras=CameraRigConfig(width=80, height=60))
ANCHORS = AnchorsConfig(dagger={"fraction": 0.25})
FEATURES = FeaturesConfig(n_points=512)
FIRST_TASKS = ("stack_blocks_three", "blocks_ranking_rgb", "place_mouse")


@dataclass
class StagedEpisode:
    """One kept episode and the outputs of every data stage (paths are absolute)."""

    record: EpisodeRecord
    root: Path
    plan: Path
    frames: Path
    features: Path


def stage_episode(root: Path, task: str, seed: int, anchors: AnchorsConfig = ANCHORS, render: RenderConfig = RenderConfig()) -> StagedEpisode:
    rec = rollout(task, seed, SMALL_WORLD, "randomized", root / "rollout")
    assert rec.success, rec.reason
    plan = root / "anchors" / run_anchors(rec, root / "rollout", root / "anchors", anchors)
    frames = root / "render" / run_render(rec, root / "rollout", plan, root / "render", SMALL_WORLD, render, anchors)
    feats = root / "features" / run_features(task, seed, frames, root / "features", FEATURES)
    return StagedEpisode(rec, root, plan, frames, feats)
