"""Write a dataset in DP3's zarr layout, zarr format 2 (DP3 reads with zarr 2:
``ReplayBuffer.copy_from_path`` opens the folder with ``zarr.open(path, 'r')``, reads
``meta/episode_ends`` and every ``data/<key>``).

    OUT.zarr/
      data/point_cloud   (T, N, 6) float32  x, y, z (metres, world frame) and r, g, b in [0, 1]
      data/state         (T, 32)   float32  the robot state (``schemas.state`` layout)
      data/action        (T, 32)   float32  the next anchor (``anchors[0]``): the state to reach
                                            when the current atomic operation ends
      data/next_anchors  (T, 8, 32) float32 the whole label horizon (DP3 ignores it)
      meta/episode_ends  (E,) int64         one past each episode's last frame
      meta/episode_task_id, meta/episode_seed (E,) int64; meta/episode_validation (E,) bool

Frames are ordered by episode (``episode_index``), and within an episode as the dataset holds
them: the frame plan's time order (a DAgger frame right after the expert frame of its step). Every
episode is written, train and validation (DP3 draws its own validation episodes); the split is in
``meta/episode_validation``. The root's attributes describe the mapping and name the tasks.

Colours stay in [0, 1], this project's range (and that of the SAPIEN colour texture RoboTwin's
clouds come from), not 0-255: DP3 reads only x, y, z by default (``use_pc_color: false``), and with
colour on its normaliser fits each channel's limits to the data, so the scale does not matter to it.

Arrays are chunked by ``CHUNK_FRAMES`` frames and compressed with Blosc (zstd, bit shuffle), which
zarr 2 reads; rows are buffered a chunk at a time, so memory does not grow with the dataset.
"""

from __future__ import annotations

from pathlib import Path

import numcodecs
import numpy as np
import zarr

from anchordp3.dataset.reader import EpisodeEntry
from anchordp3.schemas.dataset import HORIZON, STATE_DIM, DatasetInfo
from anchordp3.schemas.export import label_meaning

CHUNK_FRAMES = 100
COMPRESSOR = numcodecs.Blosc(cname="zstd", clevel=3, shuffle=numcodecs.Blosc.BITSHUFFLE)
DATA_ARRAYS = {  # name -> (per-frame shape with N = points per cloud, dtype)
    "point_cloud": (("N", 6), "<f4"),
    "state": ((STATE_DIM,), "<f4"),
    "action": ((STATE_DIM,), "<f4"),
    "next_anchors": ((HORIZON, STATE_DIM), "<f4"),
}
EPISODE_ARRAYS = {"episode_ends": "<i8", "episode_task_id": "<i8", "episode_seed": "<i8", "episode_validation": "|b1"}


class _Rows:
    """Rows appended to a zarr array whole chunks at a time (at most one chunk held in memory)."""

    def __init__(self, array: zarr.Array):
        self.array, self.step = array, array.chunks[0]
        self.held: list[np.ndarray] = []
        self.at = 0  # rows written

    def append(self, rows: np.ndarray) -> None:
        self.held.append(rows)
        if sum(len(r) for r in self.held) >= self.step:
            self._write(final=False)

    def close(self) -> None:
        self._write(final=True)
        if self.at != self.array.shape[0]:
            raise ValueError(f"{self.array.path}: {self.at} rows written, the array has {self.array.shape[0]}")

    def _write(self, final: bool) -> None:
        if not self.held:
            return
        rows = np.concatenate(self.held)
        n = len(rows) if final else len(rows) // self.step * self.step
        self.array[self.at:self.at + n] = rows[:n]
        self.at += n
        self.held = [rows[n:]] if n < len(rows) else []


class DP3Writer:
    """Writes the DP3 export into ``root`` (an empty folder, made the zarr group): ``add`` each
    episode of ``self.entries`` in that order, then ``close``. info: the source ``dataset.json``;
    entries: its episodes; plan: the run's ``anchors.plan`` (None: unknown)."""

    def __init__(self, root: Path, info: DatasetInfo, entries: list[EpisodeEntry], plan: str | None = None):
        self.root, self.info, self.plan = Path(root), info, plan
        self.entries = sorted(entries, key=lambda e: e.episode_index)
        total = sum(e.frames for e in self.entries)
        group = zarr.open_group(str(self.root), mode="w", zarr_format=2)
        data = group.create_group("data")
        self.rows = {
            name: _Rows(data.create_array(name, shape=(total, *_shape(shape, info.n_points)), dtype=dtype,
                                          chunks=(CHUNK_FRAMES, *_shape(shape, info.n_points)),
                                          compressors=COMPRESSOR, fill_value=0))
            for name, (shape, dtype) in DATA_ARRAYS.items()
        }
        self.meta = group.create_group("meta")
        group.attrs.update(self._attrs())
        self.ends: list[int] = []
        self.frames = 0

    def add(self, entry: EpisodeEntry, arrays: dict[str, np.ndarray]) -> None:
        """Write one episode; ``arrays`` holds its ``points, state, anchors`` (``ShardedDataset.episode_arrays``)."""
        expected = self.entries[len(self.ends)]
        if entry.episode_index != expected.episode_index:
            raise ValueError(f"episodes must be added in export order: expected {expected.episode_index}, got {entry.episode_index}")
        cols = {"point_cloud": arrays["points"][..., :6], "state": arrays["state"], "action": arrays["anchors"][:, 0],
                "next_anchors": arrays["anchors"]}
        for name, rows in self.rows.items():
            rows.append(np.ascontiguousarray(cols[name], dtype=DATA_ARRAYS[name][1]))
        self.frames += len(arrays["state"])
        self.ends.append(self.frames)

    def close(self) -> None:
        """Flush the data arrays and write the episode arrays."""
        if len(self.ends) != len(self.entries):
            raise ValueError(f"{self.root}: {len(self.ends)} of {len(self.entries)} episodes were added")
        for rows in self.rows.values():
            rows.close()
        values = {"episode_ends": self.ends, "episode_task_id": [e.task_id for e in self.entries],
                  "episode_seed": [e.seed for e in self.entries],
                  "episode_validation": [e.split == "validation" for e in self.entries]}
        for name, dtype in EPISODE_ARRAYS.items():
            a = np.asarray(values[name], dtype=dtype)
            self.meta.create_array(name, shape=a.shape, dtype=dtype, chunks=(max(len(a), 1),), compressors=COMPRESSOR,
                                   fill_value=0)[...] = a

    def _attrs(self) -> dict:
        return {"anchordp3": {
            "source_fingerprint": self.info.fingerprint,
            "point_cloud": "x, y, z metres world frame; r, g, b in [0, 1]",
            "state": "schemas.state layout (32-d): qpos and gripper per arm, end-effector xyz and R[:3,:2] per arm",
            "plan": self.plan,
            **label_meaning(self.plan),
            "order": "episodes by episode_index; frames in the frame plan's time order",
            "tasks": list(self.info.tasks),
        }}


def _shape(shape: tuple, n_points: int) -> tuple[int, ...]:
    return tuple(n_points if d == "N" else d for d in shape)
