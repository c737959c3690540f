"""Every task's ``evaluate()``: named success conditions, unmet in the scene as built and all met
once the expert has finished; success is exactly all of them."""

import pytest

from anchordp3.schemas.sim import world_config
from anchordp3.schemas.tasks import TASK_NAMES
from anchordp3.sim.episode import build
from anchordp3.sim.expert import Expert


@pytest.mark.parametrize("name", TASK_NAMES)
def test_the_expert_meets_every_named_condition_that_the_scene_as_built_does_not(name):
    world, task = build(name, 0, world_config("clean"), render=False)
    assert world.settle_and_check()
    before = task.evaluate()
    assert before and all(isinstance(k, str) and isinstance(v, bool) for k, v in before.items()), before
    assert not all(before.values()) and not task.check_success()
    task.plan(Expert(world, task.step_limit))
    after = task.evaluate()
    assert list(after) == list(before)  # the same conditions, in the same order
    assert all(after.values()), {k: v for k, v in after.items() if not v}
    assert task.check_success()
