"""Records of expert episodes: anchors (keypose tags) and the per-episode rollout record."""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Iterable, Iterator, Sequence
from itertools import accumulate
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


class SeedSet(Sequence[int]):
    """Sorted, unique seeds held as disjoint inclusive ranges, never expanded: ``"0-999999999"``
    takes a few bytes. A read-only sequence: ``len``, indexing (``seeds[i]``, ``seeds[:n]`` gives
    a list), iteration in ascending order, ``in``; ``first`` / ``last``; ``str()`` is the canonical
    spec (``"0-49,60"``). Build it with ``parse_seed_set``."""

    def __init__(self, ranges: Iterable[tuple[int, int]]):
        merged: list[list[int]] = []
        for lo, hi in sorted(ranges):
            if merged and lo <= merged[-1][1] + 1:
                merged[-1][1] = max(merged[-1][1], hi)
            else:
                merged.append([lo, hi])
        self.ranges: tuple[tuple[int, int], ...] = tuple((lo, hi) for lo, hi in merged)
        self._ends = list(accumulate(hi - lo + 1 for lo, hi in self.ranges))  # seeds up to each range's end

    def __len__(self) -> int:
        return self._ends[-1] if self._ends else 0

    def __getitem__(self, i):
        if isinstance(i, slice):
            start, stop, step = i.indices(len(self))
            return [self[j] for j in range(start, stop, step)]
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"seed index {i} out of range for {n} seeds")
        r = bisect_right(self._ends, i)
        before = self._ends[r - 1] if r else 0
        return self.ranges[r][0] + i - before

    def __iter__(self) -> Iterator[int]:
        for lo, hi in self.ranges:
            yield from range(lo, hi + 1)

    def __contains__(self, seed: object) -> bool:
        if not isinstance(seed, int):
            return False
        r = bisect_right(self.ranges, (seed, float("inf"))) - 1
        return r >= 0 and self.ranges[r][0] <= seed <= self.ranges[r][1]

    def __eq__(self, other: object) -> bool:
        if isinstance(other, SeedSet):
            return self.ranges == other.ranges
        return isinstance(other, (list, tuple)) and len(other) == len(self) and list(self) == list(other)

    def __hash__(self) -> int:
        return hash(self.ranges)

    @property
    def first(self) -> int:
        """The smallest seed."""
        return self.ranges[0][0]

    @property
    def last(self) -> int:
        """The largest seed."""
        return self.ranges[-1][1]

    def __str__(self) -> str:
        return ",".join(f"{lo}" if lo == hi else f"{lo}-{hi}" for lo, hi in self.ranges)

    def __repr__(self) -> str:
        return f"SeedSet({str(self)!r})"


def parse_seed_set(text: str, field: str = "seeds") -> SeedSet:
    """Seeds from ``"0-49"``, ``"3"`` or ``"0-9,20,30-31"`` (ranges inclusive) without expanding
    them. Raises ValueError naming ``field`` on malformed input."""
    ranges: list[tuple[int, int]] = []
    try:
        for part in text.split(","):
            part = part.strip()
            lo, hi = (int(x) for x in part.split("-", 1)) if "-" in part else (int(part), int(part))
            if hi < lo or lo < 0:
                raise ValueError
            ranges.append((lo, hi))
    except ValueError:
        raise ValueError(f"{field}: expected seeds like '0-49' or '0,3,7-9' (non-negative), got {text!r}") from None
    return SeedSet(ranges)


def parse_seeds(text: str, field: str = "seeds") -> list[int]:
    """Seeds from ``"0-49"``, ``"3"`` or ``"0-9,20,30-31"`` (ranges inclusive), sorted and unique, as a
    list (for short lists: command-line seeds; a run's seeds are a ``SeedSet``).

    Raises ValueError naming ``field`` on malformed input."""
    return list(parse_seed_set(text, field))
