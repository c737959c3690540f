"""Configuration of the data stages after rollout: anchors (frame plan), render, features."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

FrameKind = Literal["expert", "dagger", "rest"]
FRAME_KINDS: tuple[str, ...] = ("expert", "dagger", "rest")
"""Index = the ``kind`` code stored in arrays. ``rest`` is an expert frame observed exactly at an
anchor, where the robot rests when a closed-loop decision is taken."""


class KinematicTagConfig(BaseModel):
    """Anchor tagging from motion alone, for demonstrations without operation labels."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rest_joint_speed: float = Field(default=2e-3, gt=0, description="Arm joint change per control step below which an arm is at rest, radians.")
    rest_gripper_speed: float = Field(default=2e-3, gt=0, description="Normalised gripper change per control step below which a gripper is at rest.")
    rest_command_change: float = Field(default=1e-4, gt=0, description="Change of a commanded joint or gripper per control step below which the command holds still.")
    use_commands: bool = Field(default=True, description="Tag from the commanded actions when the data has them (else from measured states).")
    min_rest_steps: int = Field(default=2, ge=1, description="Control steps the robot must stay at rest for a rest period to count.")


class DaggerConfig(BaseModel):
    """Off-trajectory (DAgger) frames: the arm is sent to a wrong pose, observed, then restored."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    fraction: float = Field(default=0.1, ge=0, le=1, description="Probability that an expert frame also gets a DAgger frame at the same step.")
    wrong_affordance_prob: float = Field(default=0.5, ge=0, le=1, description="Share of DAgger frames aimed at a wrong object rather than near the right target.")
    offset_range: tuple[float, float] = Field(default=(0.03, 0.08), description="Distance of a near-target perturbation from the target, metres (min, max).")
    yaw_range_deg: float = Field(default=25.0, ge=0, description="Largest extra gripper yaw of a perturbation, degrees.")
    hover: tuple[float, float] = Field(default=(0.02, 0.08), description="Height above a wrong object that the gripper is sent to, metres (min, max).")
    steps: int = Field(default=20, ge=2, description="Control steps of the motion to the wrong pose.")

    @model_validator(mode="after")
    def _check(self) -> "DaggerConfig":
        for name in ("offset_range", "hover"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"{name}: expected 0 <= min <= max, got {(lo, hi)}")
        return self


class DenseConfig(BaseModel):
    """The dense baseline's frame plan, in the style of DP3 on RoboTwin: a frame every few control
    steps, labelled with the next H commanded actions."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    frame_stride: int = Field(default=3, ge=1, description="Control steps between frames (RoboTwin records at ~16.7 Hz: every 3rd of our 50 Hz steps).")
    action_stride: int = Field(default=3, ge=1, description="Control steps between consecutive label actions.")
    execute: int = Field(default=6, ge=1, description="Predicted actions executed per closed-loop decision (DP3's n_action_steps: 6 of horizon 8).")


class AnchorsConfig(BaseModel):
    """Anchor tagging and the frame plan of every kept episode."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    plan: Literal["anchors", "dense"] = Field(default="anchors", description="AnchorDP3's sparse anchor frames, or the dense DP3-style baseline (`dense`).")
    source: Literal["symbolic", "kinematic"] = Field(default="symbolic", description="Anchors from the expert's operation tags, or from motion alone.")
    horizon: int = Field(default=8, ge=1, description="H: next anchors each frame is labelled with (padded with the last anchor).")
    frames_per_interval: int = Field(default=2, ge=1, description="Random frames drawn inside each interval between consecutive anchors.")
    rest_frames: bool = Field(
        default=True,
        description="Also observe each interval's start, the robot at rest at the previous anchor (home for the first): "
                    "the state every closed-loop decision is taken in. False: the report's random frames only.")
    relabel_reached: bool = Field(
        default=True,
        description="A random frame where the robot has already reached the interval's anchor (arm joints within "
                    "reached_tolerance, grippers within 0.05) is labelled with the anchors after it, as a decision there "
                    "would be. False: the report's labels (the interval's anchor first).")
    reached_tolerance: float = Field(default=0.01, gt=0, description="Largest arm-joint distance to an anchor at which it counts as reached, radians (the executor's hold tolerance).")
    seed: int = Field(default=0, ge=0, description="Seed of the frame draws (combined with task and episode seed).")
    dagger: DaggerConfig = Field(default_factory=DaggerConfig, description="DAgger frames.")
    kinematic: KinematicTagConfig = Field(default_factory=KinematicTagConfig, description="Kinematic tagging thresholds.")
    dense: DenseConfig = Field(default_factory=DenseConfig, description="The dense baseline's plan (used when plan is dense).")


class RenderConfig(BaseModel):
    """Sparse rendering of the planned frames."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mask_method: Literal["segmentation", "depth_diff"] = Field(default="segmentation", description="Critical-object masks from SAPIEN's segmentation buffer (one render) or the report's re-render-with-objects-hidden depth difference.")
    depth_diff_tolerance: float = Field(default=1e-5, gt=0, description="Depth change (metres) above which a pixel counts as critical in the depth-difference method.")
    include_robot: bool = Field(default=True, description="Whether the robot's links count as task-critical (the report includes the robot body).")
    keep_frames: bool = Field(default=True, description="Keep RGB/depth/mask per frame after features are durable (auditability); False discards them (disk).")


class FeaturesConfig(BaseModel):
    """Back-projection, fusion, cropping, per-point features and downsampling."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    n_points: int = Field(default=4096, ge=16, description="N: points per frame after farthest point sampling.")
    k: int = Field(default=16, ge=3, description="K: neighbours of the PCA normal and curvature features.")
    eps: float = Field(default=1e-5, gt=0, description="ε in the curvature features log(λ + ε).")
    workspace_lo: tuple[float, float, float] = Field(default=(-0.65, -0.55, 0.55), description="Lower corner of the crop box, world frame, metres.")
    workspace_hi: tuple[float, float, float] = Field(default=(0.65, 0.5, 1.5), description="Upper corner of the crop box, world frame, metres.")
    normal_view: str = Field(default="head", description="Normals are oriented towards the centre of this camera.")
    table_margin: float | None = Field(
        default=0.005, ge=0,
        description="Drop the table: points below the table top (estimated from the cloud, the densest horizontal slab) "
                    "plus this many metres, as RoboTwin crops z > table + eps. None keeps the table (box crop only).")

    @model_validator(mode="after")
    def _check(self) -> "FeaturesConfig":
        if any(lo >= hi for lo, hi in zip(self.workspace_lo, self.workspace_hi)):
            raise ValueError(f"workspace_lo must be below workspace_hi on every axis, got {self.workspace_lo} / {self.workspace_hi}")
        return self
