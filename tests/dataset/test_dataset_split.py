"""Train/validation split by episode: disjoint, seeded, deterministic."""

from __future__ import annotations

from anchordp3.dataset.reader import open_dataset
from anchordp3.dataset.split import split_episodes


def test_split_is_by_episode_and_disjoint(built):
    out, info, _, _ = built
    ds = open_dataset(out)
    train, val = ds.episodes("train"), ds.episodes("validation")
    assert {e.episode_index for e in train}.isdisjoint(e.episode_index for e in val)
    assert len(train) + len(val) == info.counts.episodes
    assert {e.task for e in val} == set(info.tasks)  # stratified: every task has held-out episodes
    ti, vi = set(ds.indices("train").tolist()), set(ds.indices("validation").tolist())
    assert ti.isdisjoint(vi) and ti | vi == set(range(len(ds)))
    assert len(vi) == info.counts.validation_samples


def test_split_is_deterministic_and_order_free():
    eps = [("a", s) for s in range(40)] + [("b", s) for s in range(10)]
    one = split_episodes(eps, 0.2, split_seed=7)
    assert one == split_episodes(list(reversed(eps)), 0.2, split_seed=7)
    assert sum(v == "validation" for (t, _), v in one.items() if t == "a") == 8
    assert sum(v == "validation" for (t, _), v in one.items() if t == "b") == 2
    assert one != split_episodes(eps, 0.2, split_seed=8)
    assert set(split_episodes(eps, 0.0, 1).values()) == {"train"}
    assert split_episodes([("c", 1)], 0.5, 0) == {("c", 1): "train"}
