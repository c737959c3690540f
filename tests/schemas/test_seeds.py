"""Seed lists from the command line."""

import pytest

from anchordp3.schemas.episode import episode_id, parse_seeds


def test_ranges_and_lists_parse_sorted_unique():
    assert parse_seeds("0-3") == [0, 1, 2, 3]
    assert parse_seeds("7,0-2,2") == [0, 1, 2, 7]


@pytest.mark.parametrize("bad", ["", "a", "3-1", "-2", "1-x"])
def test_malformed_seeds_name_the_field(bad):
    with pytest.raises(ValueError, match="--seeds"):
        parse_seeds(bad, "--seeds")


def test_episode_ids_are_derived_from_task_and_seed():
    assert episode_id("stack_blocks_three", 42) == "stack_blocks_three/000042"
