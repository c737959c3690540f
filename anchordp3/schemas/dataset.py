"""The sharded training dataset: write config, on-disk layout, per-shard records and statistics.

One sample = one frame of one kept episode. Samples are stored in shards, one zarr v3 group per
shard (``shards/<k:05d>.zarr``), each holding the arrays of ``LAYOUT`` with the sample axis first.
``dataset.json`` (a ``DatasetInfo``) is written last; ``index.parquet`` maps episodes to sample
ranges and ``instructions.parquet`` lists the instruction texts.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from anchordp3.schemas.state import StateLayout

SCHEMA_VERSION = 2  # 2: labels hold roles (0 not critical); 1: labels 0/1, still read (critical: not 0 in both)
READABLE_SCHEMA_VERSIONS = (1, 2)

POINT_CHANNELS = 11  # x, y, z (m, world), r, g, b in [0, 1], nx, ny, nz (unit), c1, c2 (curvature logs)
STATE_DIM = StateLayout().dim  # 32 for two 6-DoF arms
HORIZON = 8  # anchors predicted per frame

SHARDS_DIR = "shards"
INDEX_FILE = "index.parquet"
INSTRUCTIONS_FILE = "instructions.parquet"
INFO_FILE = "dataset.json"

SPLITS = ("train", "validation")
Split = Literal["train", "validation"]
Codec = Literal["zstd", "blosc-zstd", "blosc-lz4", "gzip", "none"]


class ArraySpec(BaseModel):
    """One per-sample array of a shard: name, per-sample shape (``"N"`` = points per cloud), dtype."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(description="Array name inside each shard group.")
    sample_shape: tuple[int | Literal["N"], ...] = Field(description="Shape of one sample; 'N' is the cloud size.")
    dtype: str = Field(description="numpy dtype string, little-endian.")
    description: str = Field(description="Meaning and units.")

    def shape(self, n_points: int) -> tuple[int, ...]:
        """The per-sample shape with ``N`` replaced by ``n_points``."""
        return tuple(n_points if d == "N" else d for d in self.sample_shape)


ROBOT_ROLE = 255  # a point of the robot, critical with ``render.include_robot`` (labels' value)
MAX_OBJECT_ROLES = 16  # labels 1..16: the task's critical objects, in its order


LAYOUT: tuple[ArraySpec, ...] = (
    ArraySpec(name="points", sample_shape=("N", POINT_CHANNELS), dtype="<f4",
              description="Cloud: x,y,z m world; r,g,b in [0,1]; nx,ny,nz unit normal; c1,c2 curvature logs."),
    ArraySpec(name="labels", sample_shape=("N",), dtype="|u1",
              description="The point's role: 0 not task-critical; k the task's k-th critical object (Task.critical_objects() order); 255 the robot (render.include_robot). Critical: not 0."),
    ArraySpec(name="state", sample_shape=(STATE_DIM,), dtype="<f4", description="Robot state at the frame (schemas.state)."),
    ArraySpec(name="anchors", sample_shape=(HORIZON, STATE_DIM), dtype="<f4", description="Next H anchors as states."),
    ArraySpec(name="task_id", sample_shape=(), dtype="<i2", description="Index into DatasetInfo.tasks."),
    ArraySpec(name="episode_index", sample_shape=(), dtype="<i4", description="Index of the episode in the plan."),
    ArraySpec(name="timestep", sample_shape=(), dtype="<i4", description="Control step of the frame."),
    ArraySpec(name="kind", sample_shape=(), dtype="|u1", description="Frame kind code: 0 = expert frame, 1 = DAgger frame, 2 = rest frame (at rest at an anchor)."),
    ArraySpec(name="instruction_index", sample_shape=(), dtype="<i4",
              description="Index into the shard group's 'instructions' attribute."),
)
ARRAYS: dict[str, ArraySpec] = {s.name: s for s in LAYOUT}
STATS_ARRAYS = ("points", "state", "anchors")  # statistics are per last dimension (11, 32, 32)
META_ARRAYS = ("task_id", "episode_index", "timestep", "kind", "instruction_index")


class WriteConfig(BaseModel):
    """How the write stage shards, splits and compresses the dataset."""

    model_config = ConfigDict(extra="forbid")

    episodes_per_shard: int = Field(default=32, ge=1, description="Planned episodes per shard (failed ones leave gaps).")
    validation_fraction: float = Field(default=0.1, ge=0.0, lt=1.0, description="Share of each task's episodes held out.")
    split_seed: int = Field(default=0, ge=0, description="Seed of the train/validation split by episode.")
    codec: Codec = Field(default="zstd", description="Compression of each inner chunk.")
    level: int = Field(default=3, ge=0, le=22, description="Compression level of the codec.")
    inner_chunk: int = Field(default=1, ge=1, description="Samples per zarr inner chunk (the unit of a random read).")

    @model_validator(mode="after")
    def _level_in_codec_range(self) -> WriteConfig:
        top = {"zstd": 22, "blosc-zstd": 9, "blosc-lz4": 9, "gzip": 9, "none": 22}[self.codec]
        if self.level > top:
            raise ValueError(f"level: codec {self.codec!r} takes levels 0-{top}, got {self.level}")
        return self


class ShardMember(BaseModel):
    """One planned episode of a shard; ids come from the plan, never from completion order."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    task: str = Field(description="Task name.")
    seed: int = Field(ge=0, description="Episode seed.")
    episode_index: int = Field(ge=0, description="Position of the episode in the plan sorted by (task, seed).")
    task_id: int = Field(ge=0, description="Index of the task in the plan's sorted task list.")
    instruction: str = Field(default="", description="Language instruction of the episode.")


class EpisodeSpan(BaseModel):
    """Where one written episode's samples lie inside its shard: ``[start, stop)``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    task: str = Field(description="Task name.")
    seed: int = Field(ge=0, description="Episode seed.")
    episode_index: int = Field(ge=0, description="Position of the episode in the plan.")
    task_id: int = Field(ge=0, description="Index into the task list.")
    instruction: str = Field(description="Language instruction of the episode.")
    start: int = Field(ge=0, description="First sample of the episode in the shard.")
    stop: int = Field(ge=0, description="One past its last sample in the shard.")


class ArrayStats(BaseModel):
    """Running moments of one array over samples, per last dimension (float64 sums)."""

    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="constants")

    count: int = Field(default=0, ge=0, description="Vectors reduced per dimension.")
    sum: list[float] = Field(description="Sum per dimension.")
    sumsq: list[float] = Field(description="Sum of squares per dimension.")
    min: list[float] = Field(description="Minimum per dimension (+inf when empty).")
    max: list[float] = Field(description="Maximum per dimension (-inf when empty).")

    @classmethod
    def empty(cls, dim: int) -> ArrayStats:
        """Statistics of no data for ``dim`` dimensions."""
        return cls(count=0, sum=[0.0] * dim, sumsq=[0.0] * dim, min=[float("inf")] * dim, max=[float("-inf")] * dim)

    @classmethod
    def of(cls, x: np.ndarray) -> ArrayStats:
        """Statistics of ``x (..., D)`` reduced over all leading axes, in float64."""
        d = x.shape[-1]
        v = np.asarray(x, dtype=np.float64).reshape(-1, d)
        if len(v) == 0:
            return cls.empty(d)
        return cls(count=len(v), sum=v.sum(0).tolist(), sumsq=np.square(v).sum(0).tolist(),
                   min=v.min(0).tolist(), max=v.max(0).tolist())

    def merge(self, other: ArrayStats) -> ArrayStats:
        """Statistics of both data sets together."""
        if len(self.sum) != len(other.sum):
            raise ValueError(f"cannot merge stats of {len(self.sum)} and {len(other.sum)} dimensions")
        return ArrayStats(
            count=self.count + other.count,
            sum=(np.add(self.sum, other.sum)).tolist(), sumsq=(np.add(self.sumsq, other.sumsq)).tolist(),
            min=np.minimum(self.min, other.min).tolist(), max=np.maximum(self.max, other.max).tolist(),
        )

    @property
    def mean(self) -> np.ndarray:
        """Mean per dimension, float64 ``(D,)`` (NaN when empty)."""
        return np.asarray(self.sum) / self.count if self.count else np.full(len(self.sum), np.nan)

    @property
    def std(self) -> np.ndarray:
        """Population standard deviation per dimension, float64 ``(D,)``."""
        if not self.count:
            return np.full(len(self.sum), np.nan)
        var = np.asarray(self.sumsq) / self.count - np.square(self.mean)
        return np.sqrt(np.maximum(var, 0.0))

    def agrees(self, other: ArrayStats, rtol: float = 1e-6) -> bool:
        """Equal counts and extrema; sums equal within ``rtol`` of their magnitude."""
        if self.count != other.count or self.min != other.min or self.max != other.max:
            return False
        for a, b in ((self.sum, other.sum), (self.sumsq, other.sumsq)):
            a, b = np.asarray(a), np.asarray(b)
            scale = max(1.0, float(np.abs(a).max(initial=0.0)), float(np.abs(b).max(initial=0.0)))
            if not np.allclose(a, b, rtol=rtol, atol=rtol * scale):
                return False
        return True


def _empty_stats() -> dict[str, ArrayStats]:
    dims = {"points": POINT_CHANNELS, "state": STATE_DIM, "anchors": STATE_DIM}
    return {k: ArrayStats.empty(dims[k]) for k in STATS_ARRAYS}


class ShardStats(BaseModel):
    """Statistics of the normalised arrays (points, state, anchors) over a set of samples."""

    model_config = ConfigDict(extra="forbid")

    arrays: dict[str, ArrayStats] = Field(default_factory=_empty_stats, description="Per array name.")

    @classmethod
    def of(cls, arrays: dict[str, np.ndarray]) -> ShardStats:
        """Statistics of the ``STATS_ARRAYS`` in ``arrays`` (sample axis first)."""
        return cls(arrays={k: ArrayStats.of(arrays[k]) for k in STATS_ARRAYS})

    def merge(self, other: ShardStats) -> ShardStats:
        """Statistics of both sample sets together."""
        return ShardStats(arrays={k: self.arrays[k].merge(other.arrays[k]) for k in STATS_ARRAYS})

    def disagreements(self, other: ShardStats, rtol: float = 1e-6) -> list[str]:
        """Names of the arrays whose statistics differ beyond ``rtol``."""
        return [k for k in STATS_ARRAYS if not self.arrays[k].agrees(other.arrays[k], rtol)]


class ShardRecord(BaseModel):
    """What writing one shard produced; enough for ``finalize`` without re-reading the samples."""

    model_config = ConfigDict(extra="forbid")

    index: int = Field(ge=0, description="Shard number k.")
    path: str = Field(description="Shard group relative to the dataset folder: shards/<k:05d>.zarr.")
    samples: int = Field(ge=0, description="Samples in the shard.")
    n_points: int = Field(ge=0, description="Points per cloud (0 when the shard is empty).")
    tasks: list[str] = Field(description="The plan's sorted task list (task_id indexes it).")
    episodes: list[EpisodeSpan] = Field(description="Written episodes in sample order.")
    dropped: list[str] = Field(default_factory=list, description="Planned episodes skipped because they failed.")
    checksum: str = Field(description="sha256 over the shard's file names and bytes.")
    nbytes: int = Field(ge=0, description="Bytes on disk.")
    stats: ShardStats = Field(description="Statistics of the shard's samples.")


class NormStats(BaseModel):
    """Normaliser of one array, per last dimension."""

    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="constants")

    count: int = Field(ge=0, description="Vectors reduced per dimension.")
    mean: list[float] = Field(description="Mean per dimension.")
    std: list[float] = Field(description="Population standard deviation per dimension.")
    min: list[float] = Field(description="Minimum per dimension.")
    max: list[float] = Field(description="Maximum per dimension.")

    @classmethod
    def of(cls, s: ArrayStats) -> NormStats:
        """Mean/std/min/max from running moments."""
        return cls(count=s.count, mean=s.mean.tolist(), std=s.std.tolist(), min=s.min, max=s.max)


class ShardEntry(BaseModel):
    """One shard as listed in ``dataset.json``."""

    model_config = ConfigDict(extra="forbid")

    index: int = Field(ge=0, description="Shard number k.")
    path: str = Field(description="Shard group relative to the dataset folder.")
    start: int = Field(ge=0, description="Global index of the shard's first sample.")
    samples: int = Field(ge=0, description="Samples in the shard.")
    checksum: str = Field(description="sha256 over the shard's file names and bytes.")


class DatasetCounts(BaseModel):
    """Sizes of the dataset."""

    model_config = ConfigDict(extra="forbid")

    samples: int = Field(ge=0, description="All samples.")
    episodes: int = Field(ge=0, description="Written episodes.")
    dropped: int = Field(ge=0, description="Planned episodes skipped because they failed.")
    train_episodes: int = Field(ge=0, description="Episodes in the train split.")
    validation_episodes: int = Field(ge=0, description="Episodes in the validation split.")
    train_samples: int = Field(ge=0, description="Samples in the train split.")
    validation_samples: int = Field(ge=0, description="Samples in the validation split.")


class DatasetInfo(BaseModel):
    """``dataset.json``: written last; its presence means the dataset is complete."""

    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="constants")

    schema_version: int = Field(default=SCHEMA_VERSION, description="Layout version of this file and the shards.")
    tasks: list[str] = Field(description="Task names; task_id indexes this list.")
    n_points: int = Field(ge=0, description="Points per cloud N.")
    config: WriteConfig = Field(description="The write config used.")
    shards: list[ShardEntry] = Field(description="Shards in global sample order.")
    counts: DatasetCounts = Field(description="Sizes.")
    stats: dict[str, NormStats] = Field(description="Normalisers of points, state and anchors over all samples.")
    files: dict[str, str] = Field(description="sha256 of index.parquet and instructions.parquet by file name.")
    fingerprint: str = Field(description="sha256 over schema version, config, shard and table checksums.")
