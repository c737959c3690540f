"""The task registry: name → ``Task`` class."""

from __future__ import annotations

from anchordp3.sim.tasks.base import Task
from anchordp3.sim.tasks.blocks import BlocksRankingRGB, StackBlocksThree
from anchordp3.sim.tasks.bottles_dustbin import PutBottlesDustbin
from anchordp3.sim.tasks.dual_shoes import PlaceDualShoes
from anchordp3.sim.tasks.phone_stand import PlacePhoneStand
from anchordp3.sim.tasks.place_object_scale import PlaceBell, PlaceMouse, PlaceStapler

TASKS: dict[str, type[Task]] = {t.name: t for t in (StackBlocksThree, BlocksRankingRGB, PlaceMouse, PlaceStapler, PlaceBell,
                                                  PlaceDualShoes, PutBottlesDustbin, PlacePhoneStand)}


def get_task(name: str) -> type[Task]:
    """The task class called ``name``; a clear error lists the known tasks."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"task: unknown task {name!r}; choose one of {sorted(TASKS)}") from None
