"""The parquet tables of a dataset: the episode index and the instruction table.

``index.parquet``, one row per written episode, sorted by ``episode_index``:
    episode_index i32, task str, task_id i16, seed i64, split str (train|validation),
    instruction_id i32, instruction str, shard i32, shard_start i64, shard_stop i64 (sample range
    inside the shard), start i64, stop i64 (global sample range), frames i32.
``instructions.parquet``, one row per distinct (task, text), sorted by (task, text):
    instruction_id i32, task str, text str, episodes i32.
Both are written deterministically (same rows -> same bytes for a given pyarrow version).
"""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from anchordp3.schemas.dataset import ShardRecord, Split

INDEX_SCHEMA = pa.schema([
    ("episode_index", pa.int32()), ("task", pa.string()), ("task_id", pa.int16()), ("seed", pa.int64()),
    ("split", pa.string()), ("instruction_id", pa.int32()), ("instruction", pa.string()),
    ("shard", pa.int32()), ("shard_start", pa.int64()), ("shard_stop", pa.int64()),
    ("start", pa.int64()), ("stop", pa.int64()), ("frames", pa.int32()),
])
INSTRUCTION_SCHEMA = pa.schema([
    ("instruction_id", pa.int32()), ("task", pa.string()), ("text", pa.string()), ("episodes", pa.int32()),
])


def build_tables(records: list[ShardRecord], shard_starts: dict[int, int],
                 splits: dict[tuple[str, int], Split]) -> tuple[pa.Table, pa.Table]:
    """The episode index and instruction tables of ``records``.

    shard_starts: global index of each shard's first sample; splits: per ``(task, seed)``."""
    spans = [(r.index, e) for r in records for e in r.episodes]
    spans.sort(key=lambda x: x[1].episode_index)
    texts = sorted({(e.task, e.instruction) for _, e in spans})
    text_id = {t: i for i, t in enumerate(texts)}
    uses = [0] * len(texts)
    cols: dict[str, list] = {f.name: [] for f in INDEX_SCHEMA}
    for k, e in spans:
        iid = text_id[(e.task, e.instruction)]
        uses[iid] += 1
        row = (e.episode_index, e.task, e.task_id, e.seed, splits[(e.task, e.seed)], iid, e.instruction, k,
               e.start, e.stop, shard_starts[k] + e.start, shard_starts[k] + e.stop, e.stop - e.start)
        for name, v in zip(INDEX_SCHEMA.names, row, strict=True):
            cols[name].append(v)
    index = pa.table(cols, schema=INDEX_SCHEMA)
    instructions = pa.table({
        "instruction_id": list(range(len(texts))), "task": [t for t, _ in texts],
        "text": [x for _, x in texts], "episodes": uses,
    }, schema=INSTRUCTION_SCHEMA)
    return index, instructions


def parquet_bytes(table: pa.Table) -> bytes:
    """The table as parquet file bytes (zstd, no timestamps)."""
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()


def read_table(path: Path, schema: pa.Schema) -> pa.Table:
    """Read a parquet table and check its columns; ValueError naming the file when it does not fit."""
    try:
        table = pq.read_table(path)
    except Exception as e:  # noqa: BLE001 - pyarrow raises many kinds on bad files
        raise ValueError(f"{path}: not a readable parquet table ({type(e).__name__})") from None
    if not table.schema.equals(schema, check_metadata=False):
        raise ValueError(f"{path}: unexpected columns {table.schema.names}")
    return table
