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


def test_a_seed_set_is_ranges_and_behaves_like_the_sorted_list():
    from anchordp3.schemas.episode import parse_seed_set

    spec = "7,0-2,2,3-5,20-22"
    seeds, full = parse_seed_set(spec), parse_seeds(spec)
    assert str(seeds) == "0-5,7,20-22" and seeds.ranges == ((0, 5), (7, 7), (20, 22))
    assert list(seeds) == full and len(seeds) == len(full) and seeds == full
    assert [seeds[i] for i in range(-len(full), len(full))] == full + full
    assert seeds[2:6] == full[2:6] and seeds[:100] == full
    assert all((s in seeds) == (s in full) for s in range(-1, 30))
    assert (seeds.first, seeds.last) == (0, 22)
    with pytest.raises(IndexError):
        seeds[len(full)]


def test_a_billion_seeds_validate_without_being_expanded():
    from anchordp3.schemas.run import RunConfig

    cfg = RunConfig(tasks=["place_mouse"], seeds="0-999999999")
    seeds = cfg.seed_list
    assert len(seeds) == 10**9 and seeds[-1] == 999_999_999 and 123_456_789 in seeds
    assert cfg.stage_config("write")["episodes"]["seeds"] == "0-999999999"  # fingerprints hash the ranges


def test_more_seeds_change_only_the_write_stages_part_of_the_config():
    from anchordp3.pipeline.work import DATA_STAGES
    from anchordp3.schemas.run import RunConfig

    few, more = (RunConfig(tasks=["place_mouse"], seeds=s) for s in ("0-9", "0-19"))
    differ = [s for s in DATA_STAGES if few.stage_config(s) != more.stage_config(s)]
    assert differ == ["write"]  # an episode's outputs do not depend on the run's other episodes
    assert few.stage_config("rollout", layout=1) != more.stage_config("rollout", layout=1)  # they did before
