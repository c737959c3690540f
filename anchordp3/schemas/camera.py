"""Camera rig configuration: four calibrated RGB-D views (head, front, left and right wrist)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Mount = Literal["world", "left_ee", "right_ee"]


class CameraSpec(BaseModel):
    """One pinhole camera. World-mounted cameras look from ``position`` along ``forward``; wrist
    cameras use the same fields in the end-effector frame (x, y: palm axes, z: approach)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(description="Unique view name, e.g. 'head'.")
    mount: Mount = Field(default="world", description="Frame the camera is fixed to.")
    position: tuple[float, float, float] = Field(description="Camera centre in the mount frame, metres.")
    forward: tuple[float, float, float] = Field(description="Viewing direction in the mount frame.")
    up: tuple[float, float, float] = Field(default=(0.0, 0.0, 1.0), description="Approximate image-up direction in the mount frame.")

    @model_validator(mode="after")
    def _check(self) -> "CameraSpec":
        if sum(v * v for v in self.forward) < 1e-12:
            raise ValueError("forward must be a non-zero vector")
        return self


class CameraRigConfig(BaseModel):
    """Resolution, intrinsics and placement of every view (defaults: RoboTwin's D435 preset)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    width: int = Field(default=320, ge=8, le=4096, description="Image width, pixels.")
    height: int = Field(default=240, ge=8, le=4096, description="Image height, pixels.")
    fovy_deg: float = Field(default=37.0, gt=1, lt=170, description="Vertical field of view, degrees.")
    near: float = Field(default=0.1, gt=0, description="Near clipping plane, metres.")
    far: float = Field(default=100.0, gt=0, description="Far clipping plane, metres.")
    shader: Literal["lambert", "minimal", "default"] = Field(
        default="lambert",
        description="Shader pack: 'lambert' (the project's: one forward pass, Lambertian surfaces), SAPIEN's 'minimal' "
                    "(a forward and a composite pass) or 'default' (deferred shading). The same segmentation, depth and, "
                    "within one level of 255, colours; on a CPU renderer 'lambert' takes under half of 'minimal''s time.")
    views: list[CameraSpec] = Field(
        default_factory=lambda: [
            CameraSpec(name="head", position=(-0.032, -0.45, 1.35), forward=(0.0, 0.6, -0.8)),
            CameraSpec(name="front", position=(0.0, 0.75, 1.15), forward=(0.0, -0.8, -0.55)),
            CameraSpec(name="left_wrist", mount="left_ee", position=(0.0, -0.07, -0.08), forward=(0.0, 0.35, 1.0), up=(0.0, -1.0, 0.0)),
            CameraSpec(name="right_wrist", mount="right_ee", position=(0.0, -0.07, -0.08), forward=(0.0, 0.35, 1.0), up=(0.0, -1.0, 0.0)),
        ],
        description="The views, in the order their images are stacked.",
    )

    @model_validator(mode="after")
    def _check(self) -> "CameraRigConfig":
        names = [v.name for v in self.views]
        if len(set(names)) != len(names):
            raise ValueError(f"views: duplicate view names {names}")
        if self.far <= self.near:
            raise ValueError("far must be greater than near")
        return self
