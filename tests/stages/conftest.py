"""The three first tasks through every data stage, once per session."""

from __future__ import annotations

import pytest
from stage_helpers import FIRST_TASKS, StagedEpisode, stage_episode


@pytest.fixture(scope="session")
def staged(tmp_path_factory) -> dict[str, StagedEpisode]:
    """The three first tasks, seed 0 each, through every data stage."""
    root = tmp_path_factory.mktemp("staged")
    return {task: stage_episode(root, task, 0) for task in FIRST_TASKS}
