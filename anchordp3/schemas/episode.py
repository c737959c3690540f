"""Records of expert episodes: anchors (keypose tags) and the per-episode rollout record."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

FailureReason = Literal["unstable", "ik_failure", "grasp_lost", "step_limit", "success_check_failed", "layout_failure", "error"]


class AnchorTag(BaseModel):
    """The end of one atomic operation: keypose ``name`` of ``arm`` reached at control step ``t``,
    i.e. after ``actions[:t]`` were executed; its 32-d label derives from ``actions[t - 1]``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(description="Keypose name: PG, TGO, TGC, PP, TPC, TPO, HM, or a task's own.")
    arm: Literal["left", "right", "both"] = Field(description="Which arm the operation moved.")
    t: int = Field(ge=0, description="Control step index at which the keypose is reached.")


class EpisodeRecord(BaseModel):
    """What the CPU rollout of one ``(task, seed)`` produced."""

    model_config = ConfigDict(extra="forbid")

    task: str = Field(description="Task name.")
    seed: int = Field(description="Episode seed; every random draw of the scene derives from it.")
    preset: str = Field(description="Randomization preset name.")
    success: bool = Field(description="The expert finished and the success check passed.")
    reason: FailureReason | None = Field(default=None, description="Why the episode failed (None on success).")
    detail: str = Field(default="", description="Human-readable detail of the failure.")
    instruction: str = Field(description="Language instruction of the episode.")
    steps: int = Field(ge=0, description="Control steps executed by the expert.")
    anchors: list[AnchorTag] = Field(default_factory=list, description="Atomic-operation boundaries in time order.")
    seconds: float = Field(ge=0, description="Wall time of the rollout, seconds.")
    arrays: str | None = Field(default=None, description="File (relative to the stage folder) with states and actions.")

    @property
    def episode_id(self) -> str:
        """Derived, never random: ``<task>/<seed:06d>``."""
        return episode_id(self.task, self.seed)


def episode_id(task: str, seed: int) -> str:
    """The identity of an episode: ``<task>/<seed:06d>``."""
    return f"{task}/{seed:06d}"


def parse_seeds(text: str, field: str = "seeds") -> list[int]:
    """Seeds from ``"0-49"``, ``"3"`` or ``"0-9,20,30-31"`` (ranges inclusive), sorted and unique.

    Raises ValueError naming ``field`` on malformed input."""
    seeds: set[int] = set()
    try:
        for part in text.split(","):
            part = part.strip()
            if "-" in part:
                lo, hi = (int(x) for x in part.split("-", 1))
                if hi < lo or lo < 0:
                    raise ValueError
                seeds.update(range(lo, hi + 1))
            else:
                s = int(part)
                if s < 0:
                    raise ValueError
                seeds.add(s)
    except ValueError:
        raise ValueError(f"{field}: expected seeds like '0-49' or '0,3,7-9' (non-negative), got {text!r}") from None
    return sorted(seeds)
