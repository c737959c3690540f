"""The task registry: name → ``Task`` class."""

from __future__ import annotations

from anchordp3.sim.tasks.base import Task
from anchordp3.sim.tasks.blocks import BlocksRankingRGB, StackBlocksThree
from anchordp3.sim.tasks.place_object_scale import PlaceBell, PlaceMouse, PlaceStapler

TASKS: dict[str, type[Task]] = {t.name: t for t in (StackBlocksThree, BlocksRankingRGB, PlaceMouse, PlaceStapler, PlaceBell)}


def get_task(name: str) -> type[Task]:
    """The task class called ``name``; a clear error lists the known tasks."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"task: unknown task {name!r}; choose one of {sorted(TASKS)}") from None
