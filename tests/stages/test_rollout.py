"""The CPU rollout stage: records, saved arrays, determinism, failure reasons."""

from __future__ import annotations

import numpy as np
import pytest

from anchordp3.schemas.episode import EpisodeRecord
from anchordp3.schemas.sim import world_config
from anchordp3.sim.expert import KEYPOSES
from anchordp3.sim.tasks.blocks import StackBlocksThree
from anchordp3.stages.rollout import load_episode, rollout

TASK = "stack_blocks_three"


@pytest.fixture(scope="module")
def kept(tmp_path_factory):
    out = tmp_path_factory.mktemp("rollout")
    return out, rollout(TASK, 0, world_config("randomized"), "randomized", out)


def test_kept_episode_saves_states_actions_and_anchors(kept):
    out, rec = kept
    assert rec.success and rec.reason is None and rec.arrays is not None
    arr = load_episode(out, rec)
    assert arr["states"].shape == (rec.steps + 1, 32)
    assert arr["actions"].shape == (rec.steps, 14)
    assert arr["physx"].shape[0] == rec.steps + 1 and arr["physx"].dtype == np.uint8
    assert list(arr["anchor_t"]) == [a.t for a in rec.anchors]
    assert set(arr["anchor_name"]) <= set(KEYPOSES)
    assert np.all(np.diff(arr["anchor_t"]) > 0)


def test_record_round_trips_through_json(kept):
    _, rec = kept
    assert EpisodeRecord.model_validate_json(rec.model_dump_json()) == rec
    assert rec.episode_id == f"{TASK}/000000"


def test_same_seed_writes_identical_bytes(kept, tmp_path):
    out, rec = kept
    again = rollout(TASK, 0, world_config("randomized"), "randomized", tmp_path)
    assert (tmp_path / again.arrays).read_bytes() == (out / rec.arrays).read_bytes()


def test_step_limit_is_reported_and_nothing_saved(tmp_path, monkeypatch):
    monkeypatch.setattr(StackBlocksThree, "step_limit", 40)
    rec = rollout(TASK, 0, world_config("clean"), "clean", tmp_path)
    assert not rec.success and rec.reason == "step_limit" and rec.arrays is None
    assert not any(tmp_path.rglob("*.npz"))
