"""Simulation timing and the settle / stability protocol (RoboTwin's numbers, scaled)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from anchordp3.schemas.camera import CameraRigConfig
from anchordp3.schemas.randomization import RandomizationConfig
from anchordp3.schemas.robot import RobotSpec, default_robot


class SimConfig(BaseModel):
    """Physics rate, control rate and scene-acceptance thresholds."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    physics_hz: int = Field(default=250, ge=50, description="PhysX steps per second.")
    substeps: int = Field(default=5, ge=1, description="Physics steps per control step (control rate = physics_hz / substeps).")
    settle_steps: int = Field(default=250, ge=0, description="Physics steps to let a new scene come to rest.")
    stability_steps: int = Field(default=125, ge=0, description="Physics steps over which object rotation is checked after settling.")
    stability_max_rot_deg: float = Field(default=3.0, gt=0, description="An object rotating more than this during the check rejects the scene.")

    @property
    def control_hz(self) -> float:
        """Control steps per second."""
        return self.physics_hz / self.substeps

    @property
    def control_dt(self) -> float:
        """Seconds per control step."""
        return self.substeps / self.physics_hz


class WorldConfig(BaseModel):
    """Everything a simulated episode needs besides the task: robot, cameras, physics, randomization."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    robot: RobotSpec = Field(default_factory=default_robot, description="The robot and its URDF.")
    cameras: CameraRigConfig = Field(default_factory=CameraRigConfig, description="The four RGB-D views.")
    sim: SimConfig = Field(default_factory=SimConfig, description="Physics and control timing.")
    randomization: RandomizationConfig = Field(default_factory=RandomizationConfig, description="Domain randomization.")


def world_config(preset_name: str = "clean", **overrides) -> WorldConfig:
    """A default ``WorldConfig`` with the named randomization preset and optional field overrides."""
    from anchordp3.schemas.randomization import preset

    return WorldConfig(randomization=preset(preset_name), **overrides)
