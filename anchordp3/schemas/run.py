"""The run configuration: one YAML file describes a whole data run (and later, training)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from anchordp3.schemas.camera import CameraRigConfig
from anchordp3.schemas.dataset import WriteConfig
from anchordp3.schemas.episode import SeedSet, parse_seed_set
from anchordp3.schemas.evaluation import EvaluationConfig
from anchordp3.schemas.yaml_files import read_yaml_mapping, validate_mapping
from anchordp3.schemas.randomization import PRESETS
from anchordp3.schemas.robot import RobotSpec, default_robot
from anchordp3.schemas.sections import PartialSections
from anchordp3.schemas.sim import SimConfig, WorldConfig
from anchordp3.schemas.randomization import preset as preset_config
from anchordp3.schemas.stages import AnchorsConfig, FeaturesConfig, RenderConfig
from anchordp3.schemas.training import TrainingConfig

class PoolConfig(BaseModel):
    """A stage's pool of Ray actors."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    workers: int = Field(default=1, ge=1, description="Actors in the pool (items processed at once).")
    cpus: float = Field(default=1.0, ge=0, description="Logical CPUs reserved per actor.")
    gpus: float | None = Field(default=None, ge=0, description="GPUs per actor; None = automatic (render actors share the GPUs when the cluster has any, other stages use none).")


class PoolsConfig(PartialSections):
    """One pool per data stage (a pool given in part keeps the rest of its own default)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rollout: PoolConfig = Field(default_factory=PoolConfig, description="CPU rollouts (physics only).")
    anchors: PoolConfig = Field(default_factory=lambda: PoolConfig(cpus=0.25), description="Anchor tagging and frame plans (light).")
    render: PoolConfig = Field(default_factory=PoolConfig, description="Replays with rendering.")
    features: PoolConfig = Field(default_factory=PoolConfig, description="Point-cloud features.")
    write: PoolConfig = Field(default_factory=lambda: PoolConfig(cpus=0.5), description="Shard writers.")


class ExecutionConfig(BaseModel):
    """How the run is executed: retries, failure tolerance, in-flight bound."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    pools: PoolsConfig = Field(default_factory=PoolsConfig, description="Actor pools per stage.")
    max_attempts: int = Field(default=3, ge=1, description="Tries per item before it is recorded as failed.")
    max_failure_ratio: float = Field(default=0.1, ge=0, le=1, description="The run stops when more than this share of a stage's finished items failed (after 10 items).")
    in_flight_per_worker: int = Field(default=2, ge=1, description="Items queued per actor at most (bounds memory however large the run).")


class RunConfig(BaseModel):
    """A run: which tasks and seeds, the world, every data stage's settings and, when the run goes
    on to them, the training of its models and their closed-loop evaluation."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(default="run", description="Run name (shown in reports).")
    tasks: list[str] = Field(description="Task names (see `anchordp3 tasks`).")
    seeds: str = Field(default="0-9", description="Episode seeds per task, e.g. '0-49' or '0,3,7-9'.")
    preset: str = Field(default="randomized", description="Randomization preset: " + ", ".join(PRESETS) + ".")
    robot: RobotSpec = Field(default_factory=default_robot,
                             description="The robot: its URDF, each arm's joints, end-effector link and gripper, and drive gains.")
    cameras: CameraRigConfig = Field(default_factory=CameraRigConfig, description="Camera resolution, intrinsics and placement.")
    sim: SimConfig = Field(default_factory=SimConfig, description="Physics and control timing.")
    anchors: AnchorsConfig = Field(default_factory=AnchorsConfig, description="Anchor tagging and the frame plan.")
    render: RenderConfig = Field(default_factory=RenderConfig, description="Sparse rendering and masks.")
    features: FeaturesConfig = Field(default_factory=FeaturesConfig, description="Point-cloud features.")
    write: WriteConfig = Field(default_factory=WriteConfig, description="The sharded dataset.")
    execution: ExecutionConfig = Field(default_factory=ExecutionConfig, description="Actor pools, retries, failure bound (not part of any stage's fingerprint).")
    training: TrainingConfig | None = Field(default=None, description="Training of the segmenter, classifier and policy: the train stages (none: `anchordp3 run` makes the data only; `anchordp3 train` sets it).")
    evaluation: EvaluationConfig | None = Field(default=None, description="Closed-loop evaluation of the run's models: the evaluate stages (none: no evaluation; `anchordp3 eval` sets it).")

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v: str) -> str:
        parse_seed_set(v, "seeds")  # ranges only: any range validates at once
        return v

    @field_validator("preset")
    @classmethod
    def _preset(cls, v: str) -> str:
        if v not in PRESETS:
            raise ValueError(f"unknown preset {v!r}; choose one of {sorted(PRESETS)}")
        return v

    @field_validator("tasks")
    @classmethod
    def _tasks(cls, v: list[str]) -> list[str]:
        if not v:
            raise ValueError("at least one task is needed")
        if len(set(v)) != len(v):
            raise ValueError("a task is listed twice")
        return v

    @model_validator(mode="after")
    def _check(self) -> "RunConfig":
        if self.features.normal_view not in [v.name for v in self.cameras.views]:
            raise ValueError(f"features.normal_view: no camera named {self.features.normal_view!r}")
        return self

    @property
    def seed_list(self) -> SeedSet:
        """The seeds, sorted and unique, as ranges (never expanded; iterate, index, ``in``, ``len``)."""
        return parse_seed_set(self.seeds, "seeds")

    def world(self) -> WorldConfig:
        """The simulated world of every episode."""
        return WorldConfig(robot=self.robot, randomization=preset_config(self.preset), cameras=self.cameras, sim=self.sim)

    def _robot_part(self) -> dict:
        """The robot's share of the world's fingerprint: nothing for the shipped robot (runs made
        before the robot was configurable keep their outputs), else its settings and the URDF's
        SHA-256 (an edited URDF at the same path is a different robot)."""
        if self.robot.model_dump() == default_robot().model_dump():
            return {}
        digest = hashlib.sha256(self.robot.urdf_path.read_bytes()).hexdigest()
        return {"robot": {**self.robot.model_dump(mode="json"), "urdf_sha256": digest}}

    def stage_config(self, stage: str, layout: int = 2) -> dict:
        """What a stage's outputs depend on (its own settings and what it shares with the world);
        the fingerprint hashes this, so execution settings never invalidate outputs.

        An episode's outputs depend on its task, seed and world, not on the run's other episodes:
        the episode set is in the write stage's part only (the shard plan and the split follow
        it), so adding seeds redoes the shards and nothing else. ``layout=1``: the parts before
        that change (the episode set in the rollout's part), to recognise outputs made then."""
        world = {"preset": self.preset, "sim": self.sim.model_dump(mode="json"), **self._robot_part()}
        episodes = {"tasks": self.tasks, "seeds": str(self.seed_list)}
        if layout == 1:
            return {"rollout": {**world, **episodes}, "write": {"write": self.write.model_dump(mode="json")}}.get(stage) \
                or self.stage_config(stage)
        parts = {
            "rollout": world,
            "anchors": {"anchors": self.anchors.model_dump(mode="json")},
            "render": {**world, "cameras": self.cameras.model_dump(mode="json"), "render": self.render.model_dump(mode="json"),
                       "dagger": self.anchors.dagger.model_dump(mode="json")},
            "features": {"features": self.features.model_dump(mode="json")},
            "write": {"write": self.write.model_dump(mode="json"), "episodes": episodes},
        }
        return parts[stage]


def config_hash(obj) -> str:
    """sha256 of the canonical JSON of ``obj`` (sorted keys)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def load_run_config(path: Path) -> RunConfig:
    """Read and validate a YAML run config. Errors name the file and the field path."""
    return validate_mapping(RunConfig, read_yaml_mapping(path, "config"), path)
