"""Train/validation split by episode: seeded, deterministic, independent of any ordering."""

from __future__ import annotations

import hashlib
from collections import defaultdict
from collections.abc import Iterable

from anchordp3.schemas.dataset import Split


def _rank_key(split_seed: int, task: str, seed: int) -> bytes:
    return hashlib.blake2b(f"{split_seed}:{task}:{seed}".encode(), digest_size=16).digest()


def split_episodes(episodes: Iterable[tuple[str, int]], fraction: float, split_seed: int) -> dict[tuple[str, int], Split]:
    """Assign each ``(task, seed)`` to ``train`` or ``validation``.

    Per task (stratified), episodes are ranked by a keyed hash of ``(split_seed, task, seed)`` and
    the first ``round(fraction * n)`` go to validation (at least one when ``fraction > 0`` and the
    task has two or more episodes). The result depends on the set of episodes only, never on their
    order, so every episode lands in exactly one split."""
    by_task: dict[str, list[int]] = defaultdict(list)
    for task, seed in episodes:
        by_task[task].append(seed)
    out: dict[tuple[str, int], Split] = {}
    for task, seeds in by_task.items():
        ranked = sorted(set(seeds), key=lambda s: _rank_key(split_seed, task, s))
        n_val = round(fraction * len(ranked))
        if fraction > 0 and len(ranked) >= 2:
            n_val = max(1, n_val)
        n_val = min(n_val, len(ranked) - 1) if len(ranked) >= 2 else 0
        for i, s in enumerate(ranked):
            out[(task, s)] = "validation" if i < n_val else "train"
    return out
