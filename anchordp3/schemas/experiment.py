"""Configuration of ``anchordp3 experiment anchors-vs-dense``: the data, training and evaluation
settings shared by the two arms of the comparison."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from anchordp3.schemas.run import RunConfig
from anchordp3.schemas.training import TrainingConfig
from anchordp3.schemas.yaml_files import read_yaml_mapping, validate_mapping


class ExperimentEvalConfig(BaseModel):
    """Closed-loop evaluation of both arms, on the same seeds and instructions."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    episodes: int = Field(default=3, ge=1, description="Evaluation episodes per task and arm.")
    workers: int = Field(default=2, ge=1, description="Ray actors running episodes in parallel.")
    max_decisions: int | None = Field(default=None, ge=1, description="Cap on policy calls per episode (None: only the task's step limit).")
    through: Literal["pose", "joints"] = Field(default="pose", description="Carry out an anchor through its end-effector poses (IK) or its joint angles (the report).")


class ExperimentConfig(BaseModel):
    """The anchors arm is ``run`` as written (its ``anchors.plan`` must be ``anchors``); the dense
    arm is the same run with ``anchors.plan: dense`` on as many of its seeds as fit in the anchors
    arm's render budget."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    run: RunConfig = Field(description="The anchors arm's data run (tasks, seeds, world, stages, execution).")
    training: TrainingConfig = Field(default_factory=TrainingConfig, description="Training of the three models, the same for both arms.")
    eval: ExperimentEvalConfig = Field(default_factory=ExperimentEvalConfig, description="Closed-loop evaluation of both arms.")


def load_experiment_config(path: Path) -> ExperimentConfig:
    """Read and validate a YAML experiment config. Errors name the file and the field path."""
    cfg = validate_mapping(ExperimentConfig, read_yaml_mapping(path, "experiment config"), path)
    if cfg.run.anchors.plan != "anchors":
        raise ValueError(f"{path}: run.anchors.plan: the anchors arm must use plan 'anchors' (the dense arm is derived from it)")
    return cfg
