"""Typed per-item payloads of stage records: what each stage tells the ones after it.

An ``ItemRecord`` (``schemas.manifest``) holds the generic part of an item's outcome (status,
output, checksum, seconds) and, in ``info``, the stage's own facts. On disk ``info`` is JSON; in
code it is read only through its stage's payload model: ``record.payload(RolloutInfo).record.steps``,
never ``info["record"]["steps"]``. A payload's ``continues`` says whether the item goes on to the
next stage (a rollout whose expert failed is done, and not kept).
"""

from __future__ import annotations

from typing import TypeVar

from pydantic import BaseModel, ConfigDict, Field

from anchordp3.schemas.dataset import ShardRecord
from anchordp3.schemas.episode import EpisodeRecord


class Payload(BaseModel):
    """Base of every stage's per-item payload."""

    model_config = ConfigDict(extra="forbid")

    @property
    def continues(self) -> bool:
        """Whether the item goes on to the next stage (False: it is resolved here)."""
        return True


P = TypeVar("P", bound=Payload)


class RolloutInfo(Payload):
    """A CPU rollout: the episode record, and whether the expert succeeded (kept)."""

    kept: bool = Field(description="The expert succeeded: the episode goes on to the later stages.")
    record: EpisodeRecord = Field(description="The rollout's episode record (instruction, anchors, arrays file).")

    @property
    def continues(self) -> bool:
        return self.kept


class AnchorsInfo(Payload):
    """A frame plan."""

    frames: int = Field(ge=0, description="Frames the plan renders.")
    dagger: int = Field(ge=0, description="Of which DAgger (off-trajectory) frames.")
    anchors: int = Field(ge=0, description="Anchors (atomic-operation boundaries) of the episode.")


class RenderInfo(Payload):
    """Rendered frames; ``pruned`` once the images were dropped after featurisation."""

    pruned: bool = Field(default=False, description="The images were dropped (render.keep_frames: false); "
                                                     "the record's checksum is the slim file's.")


class FeaturesInfo(Payload):
    """Point features of every frame (the output file says it all)."""


class ShardInfo(Payload):
    """A written dataset shard."""

    samples: int = Field(ge=0, description="Samples in the shard.")
    shard: ShardRecord = Field(description="What finalize needs of the shard without re-reading it.")


class IndexInfo(Payload):
    """The dataset's index, statistics and ``dataset.json`` (the write stage's last item)."""

    samples: int = Field(ge=0, description="Samples in the dataset.")
    episodes: int = Field(ge=0, description="Episodes in the dataset.")


class ModelInfo(Payload):
    """A trained model (the one item of a ``train-<name>`` stage)."""

    model_config = ConfigDict(extra="forbid", protected_namespaces=())

    metrics: dict[str, float] = Field(default_factory=dict, description="Final validation metrics (loss, iou, first_cm, ...).")
    steps: int = Field(ge=0, description="Optimizer steps trained.")
    train_seconds: float = Field(ge=0, description="Wall time of the training loop, seconds.")
    device: str = Field(description="Device trained on (cpu, cuda:0).")
    checkpoint: str = Field(description="The model file, relative to the run directory.")
    resumed_from: int = Field(default=0, ge=0, description="Step a resumed training started from (0: from scratch).")
    critical_channel: str | None = Field(default=None, description="Policy only: the source of the critical point channel "
                                                                   "in training (segmenter or ground_truth).")


class EvalEpisodeInfo(Payload):
    """One closed-loop evaluation episode."""

    success: bool = Field(description="The task's success check passed.")
    steps: int = Field(ge=0, description="Control steps executed.")
    decisions: int = Field(ge=0, description="Policy decisions taken.")
    failure: str | None = Field(default=None, description="Failure mode (stalled, grasp_missed, ...); None on success.")
    unmet: str = Field(default="", description="The task's success conditions unmet at the end, comma-separated (Task.evaluate); empty on success.")
