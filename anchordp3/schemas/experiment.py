"""Configuration of ``anchordp3 experiment anchors-vs-dense``: the data, training and evaluation
settings shared by the two arms of the comparison."""

from __future__ import annotations

from pathlib import Path
from pydantic import BaseModel, ConfigDict, Field

from anchordp3.schemas.evaluation import EvalSettings, EvaluationConfig
from anchordp3.schemas.run import RunConfig
from anchordp3.schemas.training import TrainingConfig
from anchordp3.schemas.yaml_files import read_yaml_mapping, validate_mapping


class ExperimentEvalConfig(EvalSettings):
    """Closed-loop evaluation of trained models (both arms of the comparison, on the same seeds
    and instructions; the recipe's, ``RecipeEvalConfig``, adds the training seeds)."""

    episodes: int = Field(default=3, ge=1, description="Unseen evaluation seeds per task (from max training seed + 1000).")

    def target(self, **extra) -> EvaluationConfig:
        """These settings as a run config's ``evaluation`` section, with ``extra`` (first seed, ...)."""
        own = {k: getattr(self, k) for k in EvaluationConfig.model_fields if k in type(self).model_fields}
        return EvaluationConfig(**{**own, **extra})


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
