"""The task registry: one spec per task; names, model ids and phrases derive from it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from anchordp3.schemas.tasks import SPECS, TASK_NAMES, TaskSpec, register, task_id, task_spec


def test_model_ids_are_pinned_because_checkpoints_store_them() -> None:
    assert TASK_NAMES == ("place_mouse", "place_stapler", "place_bell", "blocks_ranking_rgb", "stack_blocks_three",
                          "place_dual_shoes", "put_bottles_dustbin", "place_phone_stand")
    assert [task_id(n) for n in TASK_NAMES] == list(range(8))


def test_every_registered_task_has_one_simulator_class_named_by_its_spec() -> None:
    from anchordp3.sim.tasks import TASKS

    assert list(TASKS) == list(TASK_NAMES)
    for name, cls in TASKS.items():
        assert cls.spec is SPECS[name] and cls.name == name


def test_a_class_that_sets_a_spec_registers_itself_and_takes_its_name_description_and_step_limit() -> None:
    code = """
from anchordp3.schemas.tasks import TaskSpec, register, task_spec
from anchordp3.sim.tasks import get_task
from anchordp3.sim.tasks.base import Task

CUP = register(TaskSpec(name="place_cup", task_id=8, description="Put the cup on the coaster.", step_limit=700,
                        phrases=task_spec("place_mouse").phrases))

class PlaceCup(Task):
    spec = CUP
    def build(self): pass
    def critical_objects(self): return ["cup"]
    def plan(self, expert): pass
    def evaluate(self): return {"cup_on_coaster": True, "released": False}

assert Task.registered["place_cup"] is PlaceCup
assert (PlaceCup.name, PlaceCup.description, PlaceCup.step_limit) == ("place_cup", "Put the cup on the coaster.", 700)
assert get_task("place_mouse").step_limit == 800
try:
    class Again(PlaceCup):
        spec = CUP
except TypeError as e:
    assert "two classes" in str(e)
else:
    raise SystemExit("a second class for one spec was accepted")
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_a_name_or_id_registered_twice_is_refused() -> None:
    mouse = task_spec("place_mouse")
    with pytest.raises(ValueError, match="already registered"):
        register(TaskSpec(name="place_mouse", task_id=99, description="", step_limit=1, phrases=mouse.phrases))
    with pytest.raises(ValueError, match="already registered"):
        register(TaskSpec(name="new_task", task_id=0, description="", step_limit=1, phrases=mouse.phrases))
    assert "new_task" not in SPECS


def test_an_unknown_task_is_one_clear_error() -> None:
    with pytest.raises(ValueError, match="unknown task 'place_moose'; choose one of"):
        task_id("place_moose")


def test_the_registry_and_the_instruction_bank_load_without_the_simulator() -> None:
    code = ("import sys, anchordp3.schemas.tasks, anchordp3.schemas.training, anchordp3.models.instructions; "
            "sys.exit('sapien' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0
