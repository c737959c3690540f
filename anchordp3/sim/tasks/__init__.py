"""The simulator's task classes, by name: one class per registered task (``schemas/tasks.py``).

Every module of this package is imported here, so a task class anywhere in it registers itself
(``Task.registered``) by setting its ``spec``: adding a task is one spec and one class.
"""

from __future__ import annotations

import importlib
import pkgutil

from anchordp3.schemas.tasks import TASK_NAMES
from anchordp3.sim.tasks.base import Task

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")


def _by_id() -> dict[str, type[Task]]:
    missing = [n for n in TASK_NAMES if n not in Task.registered]
    if missing:
        raise ImportError(f"tasks {missing} are registered in schemas/tasks.py but no class in sim/tasks/ sets their spec")
    return {name: Task.registered[name] for name in TASK_NAMES}


TASKS: dict[str, type[Task]] = _by_id()
"""Every registered task's class, in model-id order."""


def get_task(name: str) -> type[Task]:
    """The task class called ``name``; a clear error lists the known tasks."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"task: unknown task {name!r}; choose one of {sorted(TASKS)}") from None
