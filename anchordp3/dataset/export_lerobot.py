"""Write a dataset as a LeRobotDataset in LeRobot's v3.0 layout: ``LeRobotDataset(repo_id,
root=OUT)`` loads it, and a LeRobot training script gets state, action and images where it
expects them.

How the sparse anchor dataset maps onto LeRobot's time series (also recorded in
``meta/info.json`` under ``anchordp3``):

- one LeRobot episode per written episode: the train split first, then validation (each in
  ``episode_index`` order), so ``info.json``'s ``splits`` are two ranges of episode indices;
- one LeRobot frame per sample, i.e. per *keyframe* of the frame plan, in its time order (rest,
  expert and DAgger frames; a DAgger frame follows the expert frame of its step). The time axis
  counts keyframes: ``frame_index`` is the position in the episode, ``timestamp = frame_index /
  fps`` with ``fps = 1``, so LeRobot's ``delta_timestamps`` of k / fps reach k keyframes away;
  the simulator step of a frame is ``control_step`` (its time: control_step / control_hz);
- ``observation.state (32,)``: the robot state (``schemas.state`` layout, one name per
  dimension); ``action (32,)``: the *next anchor*, the state the robot should be in when the
  current atomic operation ends (``anchors[0]``), so a LeRobot policy learns frame -> next
  anchor; ``next_anchors (8, 32)``: the whole label horizon;
- ``observation.points (N, 11)``: the cloud (x, y, z m world; r, g, b in [0, 1]; unit normal;
  curvature logs); ``points_critical (N,) uint8``: each point's role (0 not critical, k the task's k-th critical object, 255 the robot); ``frame_kind``: 0
  expert, 1 DAgger, 2 rest;
- ``observation.images.<view> (H, W, 3)``: each camera's RGB as PNG image features (LeRobot's
  ``image`` dtype, bytes in the parquet), when the run kept its rendered frames;
- ``task`` (``meta/tasks.parquet``): the episode's language instruction; its anchordp3 task,
  seed, split and source ``episode_index`` are extra ``anchordp3/...`` columns of the episodes table.

Files: ``meta/info.json``, ``meta/stats.json``, ``meta/tasks.parquet`` (task string as the
pandas index, ``task_index`` column), ``meta/episodes/chunk-000/file-000.parquet`` (one row per
episode: tasks, length, where its frames lie, its own ``stats/<feature>/<stat>``) and
``data/chunk-CCC/file-FFF.parquet`` (one row per frame; a file holds whole episodes and is
closed once it holds about 100 MB; 1000 files per chunk folder).

Statistics (min, max, mean, std, count, q01, q10, q50, q90, q99): exact per episode; over the
dataset min/max/mean/std exact from running sums, and the quantiles the frame-weighted mean of the
episodes' quantiles (LeRobot's own rule for combining episodes). Vectors have one value per
dimension, ``observation.points`` and ``next_anchors`` one per channel / state dimension,
``points_critical`` and the scalar columns one; images one per colour channel in [0, 1], shape
(3, 1, 1), over pixels subsampled to at most 64 per side.

Memory: one episode (its samples, images and PNG bytes) at a time, plus a few vectors per feature.
The same dataset gives the same bytes (for a given pyarrow and Pillow).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

from anchordp3.dataset.reader import EpisodeEntry
from anchordp3.schemas.dataset import HORIZON, POINT_CHANNELS, STATE_DIM, ArrayStats, DatasetInfo
from anchordp3.schemas.export import label_meaning
from anchordp3.schemas.stages import FRAME_KINDS
from anchordp3.schemas.state import StateLayout

CODEBASE_VERSION = "v3.0"
FPS = 1  # one keyframe per "second": the time axis counts keyframes
ROBOT_TYPE = "anchordp3_dual_arm"
CHUNKS_SIZE = 1000  # files per chunk folder
DATA_FILE_MB = 100  # a data file is closed once it holds this much (arrow bytes)
VIDEO_FILE_MB = 200  # LeRobot's default, recorded only (no videos are written)
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
INFO_PATH, STATS_PATH, TASKS_PATH = "meta/info.json", "meta/stats.json", "meta/tasks.parquet"
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
STAT_KEYS = ("min", "max", "mean", "std", "count", *QUANTILES)
IMAGE_STAT_SIDE = 64  # image statistics use pixels subsampled to about this many per side
PNG_LEVEL = 1  # zlib level of the PNG images (LeRobot's own: fast, a little larger)
EPISODE_ROWS_PER_GROUP = 256
POINT_NAMES = ("x", "y", "z", "r", "g", "b", "nx", "ny", "nz", "c1", "c2")
IMAGE_STRUCT = pa.struct([("bytes", pa.binary()), ("path", pa.string())])
IMAGE_PREFIX = "observation.images."
_MB = 1024**2


@dataclass(frozen=True)
class Feature:
    """One LeRobot feature: a column of the data files and an entry of ``info.json``.

    dtype: LeRobot's dtype (``float32``, ``int64``, ``uint8`` or ``image``); shape: per frame;
    stat_dim: statistics are per this many trailing values (1: over every value)."""

    name: str
    dtype: str
    shape: tuple[int, ...]
    names: list[str] | None
    stat_dim: int

    @property
    def is_image(self) -> bool:
        return self.dtype == "image"

    def info(self) -> dict:
        """The ``info.json`` entry."""
        return {"dtype": self.dtype, "shape": list(self.shape), "names": self.names}

    def arrow_type(self) -> pa.DataType:
        """The parquet column type ``datasets`` reads back as this feature (Image, Value,
        fixed-length Sequence, Array2D)."""
        if self.is_image:
            return IMAGE_STRUCT
        t = pa.from_numpy_dtype(np.dtype(self.dtype))
        if self.shape == (1,):
            return t
        if len(self.shape) == 1:
            return pa.list_(t, self.shape[0])
        return pa.list_(pa.list_(t))

    def column(self, values: np.ndarray) -> pa.Array:
        """``values (F, *shape)`` (images ``(F, H, W, 3) uint8``) as this feature's column."""
        if self.is_image:
            return pa.array([{"bytes": png_bytes(v), "path": None} for v in values], type=IMAGE_STRUCT)
        x = np.ascontiguousarray(values, dtype=self.dtype)
        flat = pa.array(x.reshape(-1))
        if self.shape == (1,):
            return flat
        if len(self.shape) == 1:
            return pa.FixedSizeListArray.from_arrays(flat, self.shape[0])
        rows, cols = self.shape
        inner = pa.ListArray.from_arrays(pa.array(np.arange(0, x.size + 1, cols, dtype=np.int32)), flat)
        return pa.ListArray.from_arrays(pa.array(np.arange(0, len(x) * rows + 1, rows, dtype=np.int32)), inner)

    def stat_rows(self, values: np.ndarray) -> np.ndarray:
        """The values statistics reduce over, ``(M, stat_dim) float64`` (images in [0, 1])."""
        if self.is_image:
            step = -(-max(self.shape[:2]) // IMAGE_STAT_SIDE)
            return values[:, ::step, ::step, :].reshape(-1, 3).astype(np.float64) / 255.0
        return np.asarray(values, dtype=np.float64).reshape(-1, self.stat_dim)

    def shaped(self, v: np.ndarray) -> np.ndarray:
        """A per-channel statistic in LeRobot's shape: ``(3, 1, 1)`` for images, else as is."""
        return np.reshape(v, (3, 1, 1)) if self.is_image else np.asarray(v)

    def stats_type(self, stat: str) -> pa.DataType:
        """Column type of ``stats/<name>/<stat>`` in the episodes table."""
        if stat == "count":
            return pa.list_(pa.int64())
        return pa.list_(pa.list_(pa.list_(pa.float64()))) if self.is_image else pa.list_(pa.float64())


def png_bytes(rgb: np.ndarray) -> bytes:
    """PNG file bytes of an ``(H, W, 3) uint8`` image (no timestamps: same pixels, same bytes)."""
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8)).save(buf, format="PNG", compress_level=PNG_LEVEL)
    return buf.getvalue()


def frame_features(n_points: int, cameras: dict[str, tuple[int, int]]) -> list[Feature]:
    """The features of the export, in column order; ``cameras``: view name -> (H, W)."""
    state_names = StateLayout.of_length(STATE_DIM).names()
    feats = [
        Feature("observation.state", "float32", (STATE_DIM,), state_names, STATE_DIM),
        Feature("action", "float32", (STATE_DIM,), state_names, STATE_DIM),
        Feature("next_anchors", "float32", (HORIZON, STATE_DIM), ["anchor", "state"], STATE_DIM),
        Feature("observation.points", "float32", (n_points, POINT_CHANNELS), ["points", "channels"], POINT_CHANNELS),
        Feature("points_critical", "uint8", (n_points,), ["points"], 1),
        Feature("control_step", "int64", (1,), None, 1),
        Feature("frame_kind", "int64", (1,), None, 1),
    ]
    feats += [Feature(f"{IMAGE_PREFIX}{v}", "image", (h, w, 3), ["height", "width", "channels"], 3)
              for v, (h, w) in cameras.items()]
    feats += [Feature("timestamp", "float32", (1,), None, 1)]
    feats += [Feature(n, "int64", (1,), None, 1) for n in ("frame_index", "episode_index", "index", "task_index")]
    return feats


def lerobot_order(entries: list[EpisodeEntry]) -> list[EpisodeEntry]:
    """The export's episode order: train episodes, then validation ones, each by ``episode_index``."""
    return sorted(entries, key=lambda e: (e.split != "train", e.episode_index))


def prompt(entry: EpisodeEntry) -> str:
    """The LeRobot task of an episode: its instruction (the task name when it has none)."""
    return entry.instruction or entry.task.replace("_", " ")


class _Stats:
    """Statistics of one feature: per episode exactly, and merged over the episodes so far."""

    def __init__(self, feature: Feature):
        self.feature = feature
        self.moments = ArrayStats.empty(feature.stat_dim)
        self.quantile_sums = {k: np.zeros(feature.stat_dim) for k in QUANTILES}
        self.frames = 0

    def episode(self, values: np.ndarray) -> dict[str, np.ndarray]:
        """The episode's statistics (and add them to the running ones)."""
        rows = self.feature.stat_rows(values)
        m = ArrayStats.of(rows)
        q = np.quantile(rows, list(QUANTILES.values()), axis=0) if len(rows) else np.full((len(QUANTILES), rows.shape[1]), np.nan)
        frames = len(values)
        self.moments = self.moments.merge(m)
        for k, qk in zip(QUANTILES, q):
            self.quantile_sums[k] += qk * frames
        self.frames += frames
        return self._shaped(m, dict(zip(QUANTILES, q)), frames)

    def total(self) -> dict[str, np.ndarray]:
        """The dataset's statistics."""
        q = {k: s / max(self.frames, 1) for k, s in self.quantile_sums.items()}
        return self._shaped(self.moments, q, self.frames)

    def _shaped(self, m: ArrayStats, q: dict[str, np.ndarray], frames: int) -> dict[str, np.ndarray]:
        f = self.feature
        out = {"min": f.shaped(m.min), "max": f.shaped(m.max), "mean": f.shaped(m.mean), "std": f.shaped(m.std),
               "count": np.array([frames], dtype=np.int64)}
        out.update({k: f.shaped(v) for k, v in q.items()})
        return out


class _ParquetFiles:
    """Tables appended to the files of ``pattern`` (``chunk_index``, ``file_index``) in order; a
    table is never split, and a file is closed once it holds ``limit_mb`` (arrow bytes). Tables
    are buffered into row groups of at least ``group_rows`` rows."""

    def __init__(self, root: Path, pattern: str, schema: pa.Schema, limit_mb: float, group_rows: int = 1):
        self.root, self.pattern, self.schema = Path(root), pattern, schema
        self.limit, self.group_rows = limit_mb * _MB, group_rows
        self.chunk = self.file = 0
        self.held = 0  # bytes in the current file, buffered ones included
        self.writer: pq.ParquetWriter | None = None
        self.buffer: list[pa.Table] = []
        self.paths: list[Path] = []

    def place(self, nbytes: int) -> tuple[int, int]:
        """Where a table of ``nbytes`` will go: the current file, or the next once that is full."""
        if self.held and self.held + nbytes > self.limit:
            self._close_file()
            self.file += 1
            if self.file == CHUNKS_SIZE:
                self.chunk, self.file = self.chunk + 1, 0
        return self.chunk, self.file

    def write(self, table: pa.Table) -> None:
        """Append ``table`` (placed with ``place``) to the current file."""
        self.buffer.append(table)
        self.held += table.nbytes
        if sum(len(t) for t in self.buffer) >= self.group_rows:
            self._flush()

    def close(self) -> None:
        self._close_file()

    def _flush(self) -> None:
        if not self.buffer:
            return
        if self.writer is None:
            path = self.root / self.pattern.format(chunk_index=self.chunk, file_index=self.file)
            path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = pq.ParquetWriter(path, self.schema, compression="zstd")
            self.paths.append(path)
        self.writer.write_table(pa.concat_tables(self.buffer))
        self.buffer = []

    def _close_file(self) -> None:
        self._flush()
        if self.writer is not None:
            self.writer.close()
            self.writer = None
        self.held = 0


class LeRobotWriter:
    """Writes the LeRobot export into ``root`` (an empty folder): ``add`` each episode of
    ``self.entries`` in that order, then ``close``.

    info: the source ``dataset.json``; entries: its episodes; cameras: view -> (H, W) of the
    images every episode brings (empty: none); control_hz: control steps per second and plan:
    the run's ``anchors.plan`` (None: unknown)."""

    def __init__(self, root: Path, info: DatasetInfo, entries: list[EpisodeEntry],
                 cameras: dict[str, tuple[int, int]], control_hz: float | None = None, plan: str | None = None):
        self.root, self.info, self.control_hz, self.plan = Path(root), info, control_hz, plan
        self.entries = lerobot_order(entries)
        self.features = frame_features(info.n_points, cameras)
        self.stats = {f.name: _Stats(f) for f in self.features}
        self.tasks = sorted({prompt(e) for e in self.entries})
        self._task_index = {t: i for i, t in enumerate(self.tasks)}
        data_schema = pa.schema([(f.name, f.arrow_type()) for f in self.features])
        self.data = _ParquetFiles(self.root, DATA_PATH, data_schema, DATA_FILE_MB)
        self.episodes = _ParquetFiles(self.root, EPISODES_PATH, self._episodes_schema(), DATA_FILE_MB, EPISODE_ROWS_PER_GROUP)
        self.added = 0
        self.frames = 0

    def add(self, entry: EpisodeEntry, arrays: dict[str, np.ndarray], images: dict[str, np.ndarray] | None = None) -> None:
        """Write one episode: ``arrays`` holds its ``points, labels, state, anchors, timestep,
        kind`` (``ShardedDataset.episode_arrays``), ``images`` an ``(F, H, W, 3) uint8`` array per camera."""
        expected = self.entries[self.added]
        if entry.episode_index != expected.episode_index:
            raise ValueError(f"episodes must be added in export order: expected {expected.episode_index}, got {entry.episode_index}")
        cols = self._columns(entry, arrays, images or {})
        table = pa.table({f.name: f.column(cols[f.name]) for f in self.features}, schema=self.data.schema)
        chunk, file = self.data.place(table.nbytes)
        self.data.write(table)
        ep_stats = {f.name: self.stats[f.name].episode(cols[f.name]) for f in self.features}
        self._add_episode_row(entry, len(table), (chunk, file), ep_stats)
        self.added += 1
        self.frames += len(table)

    def close(self) -> None:
        """Finish the data and episode files and write ``tasks.parquet``, ``stats.json``, ``info.json``."""
        if self.added != len(self.entries):
            raise ValueError(f"{self.root}: {self.added} of {len(self.entries)} episodes were added")
        self.data.close()
        self.episodes.close()
        write_tasks(self.root / TASKS_PATH, self.tasks)
        stats = {name: {k: v.tolist() for k, v in s.total().items()} for name, s in self.stats.items()}
        _write_json(self.root / STATS_PATH, stats)
        _write_json(self.root / INFO_PATH, self._info())

    # ---- pieces ----------------------------------------------------------------------------
    def _columns(self, entry: EpisodeEntry, arrays: dict[str, np.ndarray], images: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        n = len(arrays["timestep"])
        fi = np.arange(n, dtype=np.int64)
        cols = {
            "observation.state": arrays["state"], "action": arrays["anchors"][:, 0], "next_anchors": arrays["anchors"],
            "observation.points": arrays["points"], "points_critical": arrays["labels"],
            "control_step": arrays["timestep"], "frame_kind": arrays["kind"],
            "timestamp": (fi / FPS).astype(np.float32), "frame_index": fi,
            "episode_index": np.full(n, self.added, dtype=np.int64), "index": self.frames + fi,
            "task_index": np.full(n, self._task_index[prompt(entry)], dtype=np.int64),
        }
        for f in self.features:
            if f.is_image:
                view = f.name[len(IMAGE_PREFIX):]
                got = images[view].shape if view in images else None
                if got != (n, *f.shape):
                    raise ValueError(f"episode {entry.task}/{entry.seed}: images of {view} must be {(n, *f.shape)}, got {got}")
                cols[f.name] = images[view]
        return cols

    def _episodes_schema(self) -> pa.Schema:
        fields = [("episode_index", pa.int64()), ("tasks", pa.list_(pa.string())), ("length", pa.int64()),
                  ("data/chunk_index", pa.int64()), ("data/file_index", pa.int64()),
                  ("dataset_from_index", pa.int64()), ("dataset_to_index", pa.int64()),
                  ("meta/episodes/chunk_index", pa.int64()), ("meta/episodes/file_index", pa.int64()),
                  ("anchordp3/task", pa.string()), ("anchordp3/seed", pa.int64()), ("anchordp3/split", pa.string()),
                  ("anchordp3/episode_index", pa.int64())]
        fields += [(f"stats/{f.name}/{s}", f.stats_type(s)) for f in self.features for s in STAT_KEYS]
        return pa.schema(fields)

    def _add_episode_row(self, entry: EpisodeEntry, length: int, data_at: tuple[int, int],
                         ep_stats: dict[str, dict[str, np.ndarray]]) -> None:
        row = {"episode_index": self.added, "tasks": [prompt(entry)], "length": length,
               "data/chunk_index": data_at[0], "data/file_index": data_at[1],
               "dataset_from_index": self.frames, "dataset_to_index": self.frames + length,
               "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
               "anchordp3/task": entry.task, "anchordp3/seed": entry.seed, "anchordp3/split": entry.split,
               "anchordp3/episode_index": entry.episode_index}
        row.update({f"stats/{name}/{k}": v.tolist() for name, st in ep_stats.items() for k, v in st.items()})
        nbytes = pa.Table.from_pylist([row], schema=self.episodes.schema).nbytes
        row["meta/episodes/chunk_index"], row["meta/episodes/file_index"] = self.episodes.place(nbytes)
        self.episodes.write(pa.Table.from_pylist([row], schema=self.episodes.schema))

    def _info(self) -> dict:
        n_train = sum(e.split == "train" for e in self.entries)
        splits = {"train": f"0:{n_train}"}
        if n_train < len(self.entries):
            splits["validation"] = f"{n_train}:{len(self.entries)}"
        return {
            "codebase_version": CODEBASE_VERSION, "robot_type": ROBOT_TYPE,
            "total_episodes": len(self.entries), "total_frames": self.frames, "total_tasks": len(self.tasks),
            "chunks_size": CHUNKS_SIZE, "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB,
            "fps": FPS, "splits": splits, "data_path": DATA_PATH, "video_path": None,
            "features": {f.name: f.info() for f in self.features},
            "anchordp3": self._mapping(),
        }

    def _mapping(self) -> dict:
        return {
            "source_fingerprint": self.info.fingerprint,
            "time_axis": "frames are the keyframes of the sparse frame plan in time order; timestamp = frame_index / fps "
                         "counts keyframes, not seconds; control_step is the simulator step (seconds = control_step / control_hz)",
            "control_hz": self.control_hz,
            "plan": self.plan,
            **label_meaning(self.plan),
            "state_layout": "schemas.state: left qpos (6), left gripper, right qpos (6), right gripper, left ee xyz, "
                            "left ee R[:3,:2] row-major, right ee xyz, right ee R[:3,:2]; grippers 0 closed 1 open; metres, world frame",
            "point_channels": list(POINT_NAMES),
            "points": "x, y, z metres world frame; r, g, b in [0, 1]; unit normal; curvature logs",
            "points_critical": "the point's role from the simulator's masks: 0 not critical, k the task's k-th critical object, 255 the robot",
            "frame_kinds": list(FRAME_KINDS),
            "tasks": "the episode's language instruction; its anchordp3 task, seed and split are the anchordp3/* columns of meta/episodes",
            "anchordp3_tasks": list(self.info.tasks),
        }


def write_tasks(path: Path, tasks: list[str]) -> None:
    """``tasks.parquet``: column ``task_index``, with the task string as the pandas index (as
    ``pandas.read_parquet`` restores it, the way LeRobot reads it)."""
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": pa.array(tasks, pa.string())})
    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": None},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": None},
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.3",
    }
    table = table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression="zstd")


def _write_json(path: Path, obj: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=4, ensure_ascii=False) + "\n")
