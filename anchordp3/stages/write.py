"""Write stage: features files -> sharded zarr dataset + parquet index + dask statistics.

Input item: one kept episode's features file ``<features_dir>/features/<task>/<seed:06d>.npz``
(``features_dir`` is the features stage folder) holding ``F`` frames:

- ``points (F, N, 11) float32``, ``labels (F, N) uint8``, ``state (F, 32) float32``,
- ``anchors (F, 8, 32) float32``, ``t (F,) int64`` control step, ``kind (F,) uint8`` (0 expert, 1 DAgger).

Work items are shards. ``shard_plan`` fixes every shard's membership up front from the planned
episode ids alone (sorted by ``(task, seed)``, cut into groups), so a shard can be written as soon
as its members are done or failed, by exactly one writer, and its bytes do not depend on completion
order or worker count. ``finalize`` runs once all shards are written: it verifies them, writes the
index and instruction tables, computes the normalisers with dask, checks them against the merged
per-shard statistics, and writes ``dataset.json`` last, atomically.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Collection, Iterable
from pathlib import Path

import numpy as np

from anchordp3.dataset.files import tree_checksum
from anchordp3.dataset.index import build_tables, parquet_bytes
from anchordp3.dataset.shard import shard_path, write_shard_group
from anchordp3.dataset.split import split_episodes
from anchordp3.dataset.stats import dask_stats
from anchordp3.schemas.dataset import (
    HORIZON,
    INDEX_FILE,
    INFO_FILE,
    INSTRUCTIONS_FILE,
    LAYOUT,
    MAX_OBJECT_ROLES,
    POINT_CHANNELS,
    ROBOT_ROLE,
    SCHEMA_VERSION,
    STATE_DIM,
    STATS_ARRAYS,
    DatasetCounts,
    DatasetInfo,
    EpisodeSpan,
    NormStats,
    ShardEntry,
    ShardMember,
    ShardRecord,
    ShardStats,
    WriteConfig,
)
from anchordp3.schemas.stages import FRAME_KINDS
from anchordp3.stages.files import atomic_write_bytes, features_file

__all__ = ["FEATURE_ARRAYS", "finalize", "load_features", "plan_tasks", "shard_plan", "write_shard"]

# name -> (shape with F = frames and N = points, dtype)
FEATURE_ARRAYS: dict[str, tuple[tuple[int | str, ...], np.dtype]] = {
    "points": (("F", "N", POINT_CHANNELS), np.dtype(np.float32)),
    "labels": (("F", "N"), np.dtype(np.uint8)),
    "state": (("F", STATE_DIM), np.dtype(np.float32)),
    "anchors": (("F", HORIZON, STATE_DIM), np.dtype(np.float32)),
    "t": (("F",), np.dtype(np.int64)),
    "kind": (("F",), np.dtype(np.uint8)),
}


def load_features(path: Path) -> dict[str, np.ndarray]:
    """Read and check one features file; ValueError naming the file and field when it does not fit."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise
    except Exception as e:  # noqa: BLE001 - zip/npy errors of many kinds
        raise ValueError(f"{path}: not a readable features file ({type(e).__name__})") from None
    dims: dict[str, int] = {}
    for name, (shape, dtype) in FEATURE_ARRAYS.items():
        if name not in arrays:
            raise ValueError(f"{path}: missing array {name!r}")
        a = arrays[name]
        if a.dtype != dtype or a.ndim != len(shape):
            raise ValueError(f"{path}: {name} must be {dtype} of shape {shape}, got {a.dtype} {a.shape}")
        for d, n in zip(shape, a.shape):
            if isinstance(d, str):
                if dims.setdefault(d, n) != n:
                    raise ValueError(f"{path}: {name} has {d}={n}, other arrays have {d}={dims[d]}")
            elif d != n:
                raise ValueError(f"{path}: {name} must be {dtype} of shape {shape}, got {a.dtype} {a.shape}")
    for name in ("points", "state", "anchors"):
        if not np.isfinite(arrays[name]).all():
            raise ValueError(f"{path}: {name} holds NaN or inf")
    if arrays["kind"].size and arrays["kind"].max() >= len(FRAME_KINDS):
        raise ValueError(f"{path}: kind must be a code of {list(FRAME_KINDS)} (0..{len(FRAME_KINDS) - 1})")
    labels = arrays["labels"]
    if labels.size and ((labels > MAX_OBJECT_ROLES) & (labels != ROBOT_ROLE)).any():
        raise ValueError(f"{path}: labels must be roles: 0, a critical object's 1..{MAX_OBJECT_ROLES}, or {ROBOT_ROLE} (the robot)")
    t = arrays["t"]
    if t.size and (t.min() < 0 or t.max() > np.iinfo(np.int32).max):
        raise ValueError(f"{path}: t must be a non-negative control step below 2**31")
    return arrays


def shard_plan(episodes: Iterable[tuple[str, int] | tuple[str, int, str]], cfg: WriteConfig) -> list[list[ShardMember]]:
    """Cut the planned episodes into shards.

    episodes: ``(task, seed)`` or ``(task, seed, instruction)``, in any order, unique. They are
    sorted by ``(task, seed)``; ``episode_index`` is the position in that order and ``task_id`` the
    position of the task in the sorted task list; consecutive groups of ``cfg.episodes_per_shard``
    form the shards. The plan depends on the set of ids only."""
    rows = []
    for e in episodes:
        task, seed = str(e[0]), int(e[1])
        rows.append((task, seed, str(e[2]) if len(e) > 2 else ""))
    rows.sort(key=lambda r: (r[0], r[1]))
    ids = [(t, s) for t, s, _ in rows]
    if len(set(ids)) != len(ids):
        dup = next(i for i in ids if ids.count(i) > 1)
        raise ValueError(f"episodes: ({dup[0]!r}, {dup[1]}) is listed twice")
    tasks = sorted({t for t, _ in ids})
    members = [ShardMember(task=t, seed=s, episode_index=i, task_id=tasks.index(t), instruction=text)
               for i, (t, s, text) in enumerate(rows)]
    n = cfg.episodes_per_shard
    return [members[i:i + n] for i in range(0, len(members), n)]


def plan_tasks(plan: list[list[ShardMember]]) -> list[str]:
    """The sorted task list a plan's ``task_id`` values index."""
    return sorted({m.task for shard in plan for m in shard})


def write_shard(k: int, members: list[ShardMember], features_dir: Path, out_dir: Path, cfg: WriteConfig,
                *, tasks: list[str] | None = None, failed: Collection[tuple[str, int]] = ()) -> ShardRecord:
    """Write shard ``k`` of the plan into ``out_dir/shards/<k:05d>.zarr`` and describe it.

    members: the plan's shard ``k``; failed: ``(task, seed)`` of members that failed upstream (they
    are skipped and listed as dropped; any other missing features file is an error); tasks: the
    plan's task list (``plan_tasks``), default the tasks of ``members`` in task_id order."""
    failed = {(t, int(s)) for t, s in failed}
    tasks = list(tasks) if tasks is not None else _member_tasks(members)
    parts: list[dict[str, np.ndarray]] = []
    spans: list[EpisodeSpan] = []
    dropped: list[str] = []
    members = sorted(members, key=lambda m: m.episode_index)
    texts = sorted({m.instruction for m in members if (m.task, m.seed) not in failed})
    start = 0
    n_points = None
    for m in members:
        if (m.task, m.seed) in failed:
            dropped.append(f"{m.task}/{m.seed:06d}")
            continue
        path = Path(features_dir) / features_file(m.task, m.seed)
        if not path.exists():
            raise FileNotFoundError(f"{path}: features of episode {m.task}/{m.seed:06d} not found (not marked failed)")
        f = load_features(path)
        if n_points is None:
            n_points = f["points"].shape[1]
        elif f["points"].shape[1] != n_points:
            raise ValueError(f"{path}: points has N={f['points'].shape[1]}, earlier episodes of shard {k} have N={n_points}")
        frames = len(f["t"])
        parts.append({
            "points": f["points"], "labels": f["labels"], "state": f["state"], "anchors": f["anchors"],
            "task_id": np.full(frames, m.task_id, dtype="<i2"),
            "episode_index": np.full(frames, m.episode_index, dtype="<i4"),
            "timestep": f["t"].astype("<i4"), "kind": f["kind"],
            "instruction_index": np.full(frames, texts.index(m.instruction), dtype="<i4"),
        })
        spans.append(EpisodeSpan(task=m.task, seed=m.seed, episode_index=m.episode_index, task_id=m.task_id,
                                 instruction=m.instruction, start=start, stop=start + frames))
        start += frames
    arrays = _concat(parts, n_points or 0)
    attrs = {"schema_version": SCHEMA_VERSION, "shard": k, "n_points": n_points or 0, "tasks": tasks,
             "instructions": texts, "episodes": [s.model_dump() for s in spans], "dropped": dropped}
    written = write_shard_group(Path(out_dir) / shard_path(k), arrays, attrs, cfg)
    return ShardRecord(index=k, path=shard_path(k), samples=start, n_points=n_points or 0, tasks=tasks,
                       episodes=spans, dropped=dropped, checksum=written.checksum, nbytes=written.nbytes,
                       stats=written.stats)


def _member_tasks(members: list[ShardMember]) -> list[str]:
    by_id = {m.task_id: m.task for m in members}
    if not by_id:
        return []
    return [by_id.get(i, f"<task {i}>") for i in range(max(by_id) + 1)]


def _concat(parts: list[dict[str, np.ndarray]], n_points: int) -> dict[str, np.ndarray]:
    if parts:
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return {s.name: np.zeros((0, *s.shape(n_points)), dtype=s.dtype) for s in LAYOUT}


def finalize(dataset_dir: Path, shard_records: list[ShardRecord], cfg: WriteConfig,
             *, stats_rtol: float = 1e-6, verify: bool = True) -> DatasetInfo:
    """Verify the shards, write the tables and normalisers, then ``dataset.json`` (last, atomic).

    verify: recompute every shard's checksum first (one extra read pass over the data).
    Raises ValueError naming the shard when one is missing or its checksum changed, when records
    disagree on the task list or cloud size, or when dask's statistics over the shards disagree
    with the merged per-shard statistics beyond ``stats_rtol``."""
    root = Path(dataset_dir)
    (root / INFO_FILE).unlink(missing_ok=True)  # no dataset.json while the rest is being replaced
    records = sorted(shard_records, key=lambda r: r.index)
    _check_records(root, records, verify)
    tasks = records[0].tasks if records else []
    n_points = max((r.n_points for r in records), default=0)

    starts, entries, total = {}, [], 0
    for r in records:
        starts[r.index] = total
        entries.append(ShardEntry(index=r.index, path=r.path, start=total, samples=r.samples, checksum=r.checksum))
        total += r.samples

    spans = [e for r in records for e in r.episodes]
    splits = split_episodes([(e.task, e.seed) for e in spans], cfg.validation_fraction, cfg.split_seed)
    index, instructions = build_tables(records, starts, splits)
    files = {}
    for name, table in ((INDEX_FILE, index), (INSTRUCTIONS_FILE, instructions)):
        data = parquet_bytes(table)
        atomic_write_bytes(root / name, data)
        files[name] = hashlib.sha256(data).hexdigest()

    merged = ShardStats()
    for r in records:
        merged = merged.merge(r.stats)
    computed = dask_stats([root / r.path for r in records])
    bad = computed.disagreements(merged, rtol=stats_rtol)
    if bad:
        raise ValueError(f"{root}: dask statistics of {bad} disagree with the merged per-shard statistics")

    n_train = [e.stop - e.start for e in spans if splits[(e.task, e.seed)] == "train"]
    n_val = [e.stop - e.start for e in spans if splits[(e.task, e.seed)] == "validation"]
    counts = DatasetCounts(samples=total, episodes=len(spans), dropped=sum(len(r.dropped) for r in records),
                           train_episodes=len(n_train), validation_episodes=len(n_val),
                           train_samples=sum(n_train), validation_samples=sum(n_val))
    fingerprint = hashlib.sha256(json.dumps({
        "schema_version": SCHEMA_VERSION, "config": cfg.model_dump(mode="json"),
        "shards": [(e.path, e.checksum) for e in entries], "files": files,
    }, sort_keys=True).encode()).hexdigest()
    info = DatasetInfo(tasks=tasks, n_points=n_points, config=cfg, shards=entries, counts=counts,
                       stats={k: NormStats.of(computed.arrays[k]) for k in STATS_ARRAYS}, files=files,
                       fingerprint=fingerprint)
    atomic_write_bytes(root / INFO_FILE, (info.model_dump_json(indent=1) + "\n").encode())
    return info


def _check_records(root: Path, records: list[ShardRecord], verify: bool) -> None:
    n_points = max((r.n_points for r in records), default=0)
    seen = set()
    for r in records:
        if r.index in seen:
            raise ValueError(f"shard records: shard {r.index} listed twice")
        seen.add(r.index)
        if r.tasks != records[0].tasks:
            raise ValueError(f"{root / r.path}: task list differs from shard {records[0].index}'s "
                             "(pass tasks=plan_tasks(plan) to every write_shard)")
        if r.n_points and r.n_points != n_points:
            raise ValueError(f"{root / r.path}: clouds of N={r.n_points} differ from other shards' N={n_points}")
        path = root / r.path
        if not path.is_dir():
            raise ValueError(f"{path}: shard missing")
        if verify and tree_checksum(path)[0] != r.checksum:
            raise ValueError(f"{path}: shard content differs from its record (checksum mismatch)")
