"""Instruction bank: 10,000 distinct instructions, deterministic, family-held-out split, all tasks."""

from __future__ import annotations

from collections import Counter

import pytest

from anchordp3.models.instructions import (
    FAMILY_NAMES,
    _generate,
    episode_instruction,
    generate_instructions,
    normalise,
)
from anchordp3.schemas.tasks import TASK_NAMES
from anchordp3.schemas.training import InstructionConfig


@pytest.fixture(scope="module")
def bank():
    return generate_instructions(InstructionConfig())


def test_ten_thousand_distinct_instructions_cover_every_task(bank) -> None:
    assert len(bank) >= 10_000
    keys = [normalise(i.text) for i in bank.instructions]
    assert len(set(keys)) == len(keys)
    per_task = Counter(i.task for i in bank.instructions)
    assert set(per_task) == set(TASK_NAMES)
    assert min(per_task.values()) >= len(bank) // len(TASK_NAMES)
    assert [i.index for i in bank.instructions] == list(range(len(bank)))
    assert all(i.task_id == TASK_NAMES.index(i.task) for i in bank.instructions)
    assert {i.family for i in bank.instructions} == set(FAMILY_NAMES)
    # diverse: many different words, typos present but rare
    vocab = {w for i in bank.instructions for w in normalise(i.text).split()}
    assert len(vocab) > 400


def test_same_seed_same_bank_other_seed_other_bank(bank) -> None:
    again = _generate.__wrapped__(InstructionConfig())
    assert [i.text for i in again.instructions] == [i.text for i in bank.instructions]
    other = generate_instructions(InstructionConfig(seed=1, count=800))
    assert [i.text for i in other.instructions[:50]] != [i.text for i in bank.instructions[:50]]
    assert len(other) == 800


def test_validation_holds_out_whole_families_for_every_task(bank) -> None:
    train, val = bank.split("train"), bank.split("val")
    train_fam, val_fam = {i.family for i in train}, {i.family for i in val}
    assert val_fam == bank.val_families and train_fam.isdisjoint(val_fam)
    assert train_fam | val_fam == set(FAMILY_NAMES)
    assert 0.15 < len(val) / len(bank) < 0.4
    for task in TASK_NAMES:
        assert bank.by_task(task, "train") and bank.by_task(task, "val")
    texts, labels = bank.texts_and_labels("val")
    assert len(texts) == len(labels) == len(val)


def test_episode_instruction_is_deterministic_and_in_its_split() -> None:
    a = episode_instruction("place_bell", 17)
    assert a == episode_instruction("place_bell", 17)
    assert a.task == "place_bell" and a.split == "train"
    v = episode_instruction("place_bell", 17, split="val")
    assert v.split == "val" and v.task == "place_bell"
    assert episode_instruction("place_bell", 17, split="validation") == v
    assert len({episode_instruction("stack_blocks_three", s).text for s in range(50)}) > 40
    with pytest.raises(ValueError, match="unknown task"):
        episode_instruction("fold_laundry", 0)
    with pytest.raises(ValueError, match="split"):
        episode_instruction("place_bell", 0, split="test")
