"""The simulator's task classes, by name: one class per registered task (``schemas/tasks.py``)."""

from __future__ import annotations

from anchordp3.schemas.tasks import TASK_NAMES
from anchordp3.sim.tasks.base import Task
from anchordp3.sim.tasks.blocks import BlocksRankingRGB, StackBlocksThree
from anchordp3.sim.tasks.bottles_dustbin import PutBottlesDustbin
from anchordp3.sim.tasks.dual_shoes import PlaceDualShoes
from anchordp3.sim.tasks.phone_stand import PlacePhoneStand
from anchordp3.sim.tasks.place_object_scale import PlaceBell, PlaceMouse, PlaceStapler

_CLASSES = (PlaceMouse, PlaceStapler, PlaceBell, BlocksRankingRGB, StackBlocksThree, PlaceDualShoes, PutBottlesDustbin,
            PlacePhoneStand)
TASKS: dict[str, type[Task]] = {name: next(c for c in _CLASSES if c.spec.name == name) for name in TASK_NAMES}
"""Every registered task's class, in model-id order (a registered task without a class fails here, at import)."""


def get_task(name: str) -> type[Task]:
    """The task class called ``name``; a clear error lists the known tasks."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"task: unknown task {name!r}; choose one of {sorted(TASKS)}") from None
