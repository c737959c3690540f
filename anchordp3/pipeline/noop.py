"""A synthetic stage graph whose stages do no work: the runner and the manifest store measured on
their own (``benchmarks/orchestration_scale.py``), and the generic loop tested without a simulator.

``noop_graph(steps)``: a first episode stage that stops every episode whose seed is a multiple of
``NOOP_STOP_EVERY`` (as a rollout whose expert failed), ``steps - 1`` more episode stages, then a
group stage over groups of ``NOOP_GROUP`` episodes and one finishing item. Items write no files;
their payloads carry the seed, so a test can check what reached each stage.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from anchordp3.pipeline.graph import EpisodeItem, Graph, GroupItem, Stage, StageOutput
from anchordp3.schemas.records import Payload
from anchordp3.schemas.run import PoolConfig, RunConfig

NOOP_STOP_EVERY = 10
NOOP_GROUP = 16
LIGHT = PoolConfig(workers=1, cpus=0.1)  # an actor per stage that barely reserves a CPU


class NoopFirstInfo(Payload):
    seed: int = Field(description="The episode's seed.")
    kept: bool = Field(description="Whether the episode goes on (False for every NOOP_STOP_EVERY-th seed).")

    @property
    def continues(self) -> bool:
        return self.kept


class NoopStepInfo(Payload):
    seed: int = Field(description="The episode's seed, read from the first stage's payload.")


class NoopGroupInfo(Payload):
    episodes: int = Field(ge=0, description="Members that went through every episode stage.")


class NoopFinalInfo(Payload):
    groups: int = Field(ge=0, description="Groups finished.")
    episodes: int = Field(ge=0, description="Episodes through every stage, over all groups.")


class _Member:
    """A planned member of a group (what a group function returns: ``.task``, ``.seed``)."""

    __slots__ = ("task", "seed")

    def __init__(self, task: str, seed: int):
        self.task, self.seed = task, seed


def _first(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    return StageOutput(None, None, NoopFirstInfo(seed=item.seed, kept=item.seed % NOOP_STOP_EVERY != 0))


def _step(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    return StageOutput(None, None, NoopStepInfo(seed=item.get(NoopFirstInfo).seed))


def _groups(cfg: RunConfig, episodes) -> list[list[_Member]]:
    members = [_Member(t, s) for t, s in sorted(episodes)]
    return [members[i:i + NOOP_GROUP] for i in range(0, len(members), NOOP_GROUP)]


def _group(run: Path, cfg: RunConfig, item: GroupItem) -> StageOutput:
    return StageOutput(None, None, NoopGroupInfo(episodes=sum(ep.ok for ep in item.episodes)))


def _final(run: Path, cfg: RunConfig, records: list) -> StageOutput:
    return StageOutput(None, None, NoopFinalInfo(groups=len(records), episodes=sum(r.payload(NoopGroupInfo).episodes for r in records)))


def _config(cfg: RunConfig) -> dict:
    return {"tasks": cfg.tasks}


def noop_graph(steps: int = 4) -> Graph:
    """``steps`` episode stages (``noop0`` … ``noop{steps-1}``) and the group stage ``noop_group``."""
    if steps < 1:
        raise ValueError(f"steps: expected >= 1, got {steps}")
    chain = [Stage("noop0", "noop0", _first, NoopFirstInfo, __name__, _config, resources=LIGHT)]
    chain += [Stage(f"noop{i}", f"noop{i}", _step, NoopStepInfo, __name__, _config, needs=(NoopFirstInfo,), resources=LIGHT)
              for i in range(1, steps)]
    group = Stage("noop_group", "noop_group", _group, NoopGroupInfo, __name__, _config, group=_groups, finish=_final,
                  finish_item="final", resources=LIGHT)
    return Graph((*chain, group))
