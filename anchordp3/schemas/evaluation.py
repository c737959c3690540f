"""Closed-loop evaluation settings, written once: ``EvalSettings`` (how episodes are decided and
run) is the ``eval:`` section of the experiment and recipe configs; ``EvaluationConfig`` adds what
is evaluated (models, tasks, seeds, preset) and is a run config's ``evaluation:`` section, read by
the evaluate stages; ``EvalOptions`` adds where and how to run it (folder, restart, cluster).
``anchordp3 eval``'s flags are made from ``EvalOptions``'s fields, their help from the
descriptions below.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

DEFAULT_EPISODES = 10  # unseen seeds per task when neither seeds nor episodes are given
SKIP_REACHED = 0.015  # metres: the executor steps past a predicted anchor the robot stands within this of (ladder rung D10)
DECISION_SAMPLES = 8  # anchor sequences drawn per decision, their medoid carried out (ladder rung D17)
Through = Literal["pose", "joints"]  # how an anchor is carried out: its end-effector poses by IK, or its joints


class EvalSettings(BaseModel):
    """How closed-loop evaluation decides and runs its episodes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    episodes: int | None = Field(default=None, ge=1, description=f"Episodes per task: unseen seeds (default {DEFAULT_EPISODES}), or the first of the training seeds with seeds 'train'.")
    workers: int = Field(default=2, ge=1, description="Ray actors running episodes in parallel.")
    cpus_per_worker: float = Field(default=1.0, gt=0, description="CPUs each actor reserves.")
    max_decisions: int | None = Field(default=None, ge=1, description="Cap on policy calls per episode (default: only the task's step limit).")
    through: Through = Field(default="pose", description="pose: carry out an anchor through its end-effector poses (IK); joints: through its joint angles (the report).")
    samples: int = Field(default=DECISION_SAMPLES, ge=1, le=64, description=f"Anchor sequences drawn per decision from one encoding; their medoid, the draw nearest the others, is carried out (default {DECISION_SAMPLES}; 1: one draw, as DP3 and the report).")
    ddim_steps: int | None = Field(default=None, ge=1, le=100, description="DDIM steps per decision (default: the policy's own, 10 as DP3; 5 costs half and, on the shipped policy, +0.1 cm first-anchor error).")
    device: str = Field(default="auto", pattern=r"^(auto|cpu|cuda(:\d+)?)$", description="Torch device of the actors: auto (CUDA when the cluster has GPUs, each actor an equal share), cpu or cuda.")
    first_seed: int | None = Field(default=None, ge=0, description="First unseen evaluation seed (default: max training seed + 1000; it must lie above every training seed).")
    skip_reached: float = Field(default=SKIP_REACHED, ge=0, le=0.1, description="Metres: the executor carries out the first predicted anchor the robot is not already at (an arm's end effector further than this, its rotation over about 6 degrees off, or its gripper to be opened or closed where it is not), so a first anchor where the robot stands does not hold it there (0: always the first anchor, as the report).")
    strips: int = Field(default=2, ge=0, description="Episodes per task (the first seeds) that also get a frame strip, strips/<task>/<seed>.png.")


class EvaluationConfig(EvalSettings):
    """One evaluation: the settings, and which models on which tasks, seeds and scenes."""

    models: str | None = Field(default=None, description="Models folder (segmenter/, classifier/, policy/) or 'pretrained' (default: the run's).")
    tasks: tuple[str, ...] | None = Field(default=None, description="Comma-separated tasks (default: every task the models were trained on).")
    seeds: str | None = Field(default=None, description="Seeds, e.g. 2000-2049, or 'train' for the training seeds (default: --episodes unseen seeds).")
    preset: str | None = Field(default=None, description="Randomization preset of the scenes (default: the training data's).")
    train_episodes: int = Field(default=0, ge=0, description="Training seeds per task evaluated again, into <evaluation folder>/train: does the policy redo what it was shown (0: none).")

    @field_validator("tasks", mode="before")
    @classmethod
    def _tasks(cls, v):
        """A comma-separated string (the command line's form) or a list of names."""
        if isinstance(v, str):
            v = [t.strip() for t in v.split(",") if t.strip()]
        return None if v is None or len(v) == 0 else tuple(v)


class EvalOptions(EvaluationConfig):
    """One evaluation as a command runs it: what, and in which folder, from scratch or not, where."""

    out: Path | None = Field(default=None, description="Evaluation folder (default: <run>/eval; without a run, runs/eval-<models folder name>).")
    force: bool = Field(default=False, description="Start over where the folder holds an evaluation of other models, settings or code (default: refuse; the same ones resume).")
    keep_outputs: bool = Field(default=False, description="Keep an evaluation that only older code made (same models and settings) instead of refusing it.")
    address: str | None = Field(default=None, description="Ray cluster address (default: $RAY_ADDRESS, else a local Ray).")

    def target(self) -> EvaluationConfig:
        """What is evaluated, without where and how it runs: a run config's ``evaluation:`` section."""
        return EvaluationConfig(**{k: getattr(self, k) for k in EvaluationConfig.model_fields})
