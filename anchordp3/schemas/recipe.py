"""Configuration of ``anchordp3 experiment recipe``: one command from a clean clone to a trained,
evaluated policy (data, training, evaluation on unseen and on training seeds)."""

from __future__ import annotations

from pathlib import Path
from pydantic import BaseModel, ConfigDict, Field

from anchordp3.schemas.experiment import ExperimentEvalConfig
from anchordp3.schemas.run import RunConfig
from anchordp3.schemas.training import TrainingConfig
from anchordp3.schemas.yaml_files import read_yaml_mapping, validate_mapping


class RecipeEvalConfig(ExperimentEvalConfig):
    """Closed-loop evaluation of the recipe's models: on unseen seeds and again on training seeds."""

    episodes: int = Field(default=50, ge=1, description="Unseen evaluation seeds per task (from max training seed + 1000).")
    train_episodes: int = Field(default=20, ge=0, description="Training seeds per task evaluated again, to check the policy does what it was shown (0: skip).")


class RecipeConfig(BaseModel):
    """The data run, the training of the three models and their evaluation."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    run: RunConfig = Field(description="The data run (tasks, seeds, world, stages, execution).")
    training: TrainingConfig = Field(default_factory=TrainingConfig, description="Training of the segmenter, classifier and policy.")
    eval: RecipeEvalConfig = Field(default_factory=RecipeEvalConfig, description="Closed-loop evaluation.")


def load_recipe_config(path: Path) -> RecipeConfig:
    """Read and validate a YAML recipe config. Errors name the file and the field path."""
    return validate_mapping(RecipeConfig, read_yaml_mapping(path, "recipe config"), path)
