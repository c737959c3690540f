"""Configuration of ``anchordp3 experiment anchors-vs-dense``: the data, training and evaluation
settings shared by the two arms of the comparison."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field

from anchordp3.schemas.run import RunConfig
from anchordp3.schemas.training import TrainingConfig
from anchordp3.schemas.yaml_files import read_yaml_mapping, validate_mapping

if TYPE_CHECKING:
    from anchordp3.pipeline.evaluation import EvalOptions


class ExperimentEvalConfig(BaseModel):
    """Closed-loop evaluation of trained models (both arms of the comparison, on the same seeds
    and instructions; the recipe's, ``RecipeEvalConfig``, adds the training seeds)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    episodes: int = Field(default=3, ge=1, description="Unseen evaluation seeds per task (from max training seed + 1000).")
    workers: int = Field(default=2, ge=1, description="Ray actors running episodes in parallel.")
    max_decisions: int | None = Field(default=None, ge=1, description="Cap on policy calls per episode (None: only the task's step limit).")
    through: Literal["pose", "joints"] = Field(default="pose", description="Carry out an anchor through its end-effector poses (IK) or its joint angles (the report).")
    samples: int = Field(default=1, ge=1, le=64, description="Anchor sequences drawn per decision, their medoid carried out (1: one sample, as the report).")
    ddim_steps: int | None = Field(default=None, ge=1, le=100, description="DDIM steps per decision (None: the policy's own, its config's scheduler.num_inference_steps).")
    noise_scale: float | None = Field(default=None, ge=0, le=1, description="Scale of the noise each decision's sampling starts from: 1 a random draw (DP3, the report), 0 the prior's mean (None: the policy's own, its config's scheduler.init_noise_scale).")

    def options(self, **extra) -> EvalOptions:
        """These settings as ``EvalOptions``, with ``extra`` (seeds, out, address, ...) beside them."""
        from anchordp3.pipeline.evaluation import EvalOptions

        base = dict(episodes=self.episodes, workers=self.workers, max_decisions=self.max_decisions,
                    through=self.through, samples=self.samples, ddim_steps=self.ddim_steps, noise_scale=self.noise_scale)
        return EvalOptions(**{**base, **extra})


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
