"""Domain randomization knobs, with RoboTwin-like ``clean`` and ``randomized`` presets.

Every random draw derives from the episode seed (see ``sim.seeding``), so one seed is one scene.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class RandomizationConfig(BaseModel):
    """What varies between episodes, and by how much."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    table_height_range: tuple[float, float] = Field(default=(0.0, 0.0), description="Table-top offset from 0.74 m, uniform range, metres.")
    textured_table: bool = Field(default=False, description="Procedural texture on the table top (else a plain colour).")
    textured_wall: bool = Field(default=False, description="Procedural texture on the wall (else a plain colour).")
    plain_texture_prob: float = Field(default=0.02, ge=0, le=1, description="Chance of a plain surface even when textures are on.")
    random_lights: bool = Field(default=False, description="One directional and two point lights with random colours and placement.")
    crazy_light_prob: float = Field(default=0.0, ge=0, le=1, description="Chance that lights are re-randomised wildly at every render.")
    clutter_max: int = Field(default=0, ge=0, le=10, description="Upper bound of distractor objects on the table (uniform 0..max).")
    object_pose_noise: float = Field(default=0.0, ge=0, description="Extra spread of task-object positions, metres.")
    object_yaw_range_deg: float = Field(default=0.0, ge=0, le=180, description="Task-object yaw range (uniform ±), degrees.")
    camera_jitter_pos: float = Field(default=0.0, ge=0, description="World-camera position jitter (uniform ±), metres.")
    camera_jitter_rot_deg: float = Field(default=0.0, ge=0, description="World-camera direction jitter (uniform ±), degrees.")


PRESETS: dict[str, RandomizationConfig] = {
    "clean": RandomizationConfig(object_yaw_range_deg=15.0),
    "randomized": RandomizationConfig(
        table_height_range=(-0.03, 0.0),
        textured_table=True,
        textured_wall=True,
        random_lights=True,
        crazy_light_prob=0.02,
        clutter_max=10,
        object_pose_noise=0.02,
        object_yaw_range_deg=30.0,
        camera_jitter_pos=0.01,
        camera_jitter_rot_deg=1.0,
    ),
}


def preset(name: str) -> RandomizationConfig:
    """The named preset; a clear error lists the known names."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"preset: unknown randomization preset {name!r}; choose one of {sorted(PRESETS)}") from None
