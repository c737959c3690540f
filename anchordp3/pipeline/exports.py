"""``anchordp3 export lerobot|dp3``: a run's dataset in another project's format.

``export_lerobot(RUN, OUT)`` writes a LeRobotDataset (v3.0 layout, ``dataset.export_lerobot``),
with each camera's images when the run kept its rendered frames (``render.keep_frames``);
``export_dp3(RUN, OUT.zarr)`` writes DP3's zarr (format 2, ``dataset.export_dp3``).

Both check first, and refuse with a one-line ValueError naming the path: an existing OUT, a run
without a complete dataset, a dataset that is foreign, of another schema version, or damaged
(every shard and table against its recorded checksum, as ``anchordp3 verify``). Then they read
the dataset one episode at a time (memory does not grow with the dataset), print a progress line
(episodes, rate, ETA), and write into a hidden sibling of OUT that is renamed to OUT only once
complete (``dataset.files.new_folder``): an interrupted export leaves no OUT.
"""

from __future__ import annotations

import logging
import sys
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

import numpy as np

from anchordp3.dataset.export_dp3 import DP3Writer
from anchordp3.dataset.export_lerobot import LeRobotWriter
from anchordp3.dataset.files import new_folder, refuse_existing, tree_files
from anchordp3.dataset.reader import EpisodeEntry, ShardedDataset, open_dataset, read_dataset_info
from anchordp3.dataset.verify import verify_dataset
from anchordp3.pipeline.progress import Progress
from anchordp3.pipeline.graph import CONFIG_FILE
from anchordp3.pipeline.work import stage_dir
from anchordp3.schemas.dataset import INFO_FILE
from anchordp3.schemas.export import ExportFormat, ExportResult
from anchordp3.schemas.run import RunConfig, load_run_config
from anchordp3.stages.files import frames_file

log = logging.getLogger(__name__)

LEROBOT_KEYS = ("points", "labels", "state", "anchors")
DP3_KEYS = ("points", "state", "anchors")


def export_lerobot(run_dir: Path, out: Path, *, images: bool = True, stream: TextIO | None = None) -> ExportResult:
    """Export the run's dataset to ``out`` as a LeRobotDataset; ``images``: include the kept
    camera frames (skipped, with a warning, when the run did not keep them for every episode);
    ``stream``: where progress lines go (default: stderr)."""
    out = refuse_existing(out)  # before the checksum pass
    ds, cfg = open_run_dataset(run_dir)
    entries = ds.episodes()
    frames = RenderedImages.scan(run_dir, entries) if images else None
    cameras = frames.cameras if frames else {}
    control_hz = cfg.sim.control_hz if cfg else None

    def writer(tmp: Path) -> LeRobotWriter:
        return LeRobotWriter(tmp, ds.info, entries, cameras, control_hz, _plan(cfg))

    def add(w: LeRobotWriter, e: EpisodeEntry, arrays: dict[str, np.ndarray]) -> None:
        w.add(e, arrays, frames.load(e, arrays) if frames else None)

    return _export("lerobot", ds, out, writer, add, LEROBOT_KEYS, stream, list(cameras))


def export_dp3(run_dir: Path, out: Path, *, stream: TextIO | None = None) -> ExportResult:
    """Export the run's dataset to ``out`` (a ``.zarr`` folder) in DP3's layout."""
    out = refuse_existing(out)  # before the checksum pass
    ds, cfg = open_run_dataset(run_dir)
    entries = ds.episodes()
    return _export("dp3", ds, out, lambda tmp: DP3Writer(tmp, ds.info, entries, _plan(cfg)),
                   lambda w, e, arrays: w.add(e, arrays), DP3_KEYS, stream)


def open_run_dataset(run_dir: Path) -> tuple[ShardedDataset, RunConfig | None]:
    """The run's complete, verified, non-empty dataset and its run config (None when the run has
    no ``config.yaml``); ValueError / FileNotFoundError naming the path otherwise."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: no such run directory")
    root = stage_dir(run_dir, "write")
    if not (root / INFO_FILE).is_file():
        raise ValueError(f"{root}: no complete dataset (no {INFO_FILE}); finish the data stages with `anchordp3 run` first")
    ds = open_dataset(root)
    report = verify_dataset(root)
    if not report.ok:
        raise ValueError(f"{report.problems[0].line()}: the dataset is damaged ({len(report.problems)} problem(s)); "
                         f"`anchordp3 verify {run_dir} --repair` redoes it")
    if len(ds) == 0:
        raise ValueError(f"{root}: the dataset holds no samples; nothing to export")
    cfg = load_run_config(run_dir / CONFIG_FILE) if (run_dir / CONFIG_FILE).is_file() else None
    return ds, cfg


class RenderedImages:
    """The kept RGB images of a run's episodes (``render/frames/<task>/<seed>.npz``), per camera."""

    def __init__(self, run_dir: Path, cameras: dict[str, tuple[int, int]]):
        self.root = stage_dir(run_dir, "render")
        self.cameras = cameras  # view -> (H, W), in the files' view order

    @classmethod
    def scan(cls, run_dir: Path, entries: list[EpisodeEntry]) -> RenderedImages | None:
        """Check every episode's frames file (headers only); None, with a warning, when any
        episode has no kept images. ValueError naming the file when one disagrees with the dataset."""
        root = stage_dir(run_dir, "render")
        heads = {root / frames_file(e.task, e.seed): e for e in entries}
        found = {path: _rgb_header(path) for path in heads}
        missing = sum(h is None for h in found.values())
        if missing:
            log.warning("%s: %d of %d episodes have no kept camera images (render.keep_frames: false); "
                        "exporting without images", root, missing, len(entries))
            return None
        cameras = None
        for path, (shape, views) in found.items():
            e = heads[path]
            if len(shape) != 5 or shape[0] != e.frames or shape[1] != len(views) or shape[4] != 3:
                raise ValueError(f"{path}: rgb is {shape}, the dataset has {e.frames} frames of {len(views)} views for "
                                 f"{e.task}/{e.seed} (rendered again after the dataset was written?)")
            here = {v: (int(shape[2]), int(shape[3])) for v in views}
            if cameras is not None and here != cameras:
                raise ValueError(f"{path}: cameras {here} differ from the other episodes' {cameras}")
            cameras = here
        return cls(run_dir, cameras or {})

    def load(self, entry: EpisodeEntry, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``view -> (F, H, W, 3) uint8`` of one episode; ValueError when its frames are not the
        dataset's samples (other steps or kinds)."""
        path = self.root / frames_file(entry.task, entry.seed)
        with np.load(path, allow_pickle=False) as z:
            rgb, t, kind = z["rgb"], z["t"], z["kind"]
        if not (np.array_equal(t, arrays["timestep"]) and np.array_equal(kind, arrays["kind"])):
            raise ValueError(f"{path}: its frames are not the dataset's samples of {entry.task}/{entry.seed} (other steps or kinds)")
        return {v: rgb[:, i] for i, v in enumerate(self.cameras)}


def _rgb_header(path: Path) -> tuple[tuple[int, ...], list[str]] | None:
    """``(shape of rgb, view names)`` of a frames file without decompressing the images; None
    when the file or its images are absent (pruned)."""
    if not path.is_file():
        return None
    try:
        with zipfile.ZipFile(path) as zf:
            if "rgb.npy" not in zf.namelist():
                return None
            with zf.open("rgb.npy") as f:
                version = np.lib.format.read_magic(f)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read(f)
        with np.load(path, allow_pickle=False) as z:
            views = [str(v) for v in z["views"]]
    except (zipfile.BadZipFile, ValueError, KeyError, OSError) as e:
        raise ValueError(f"{path}: not a readable rendered-frames file ({type(e).__name__})") from None
    if dtype != np.uint8:
        raise ValueError(f"{path}: rgb must be uint8, got {dtype}")
    return tuple(shape), views


def _plan(cfg: RunConfig | None) -> str | None:
    return cfg.anchors.plan if cfg else None


def _export(fmt: ExportFormat, ds: ShardedDataset, out: Path, make: Callable[[Path], object],
            add: Callable[[object, EpisodeEntry, dict[str, np.ndarray]], None], keys: tuple[str, ...],
            stream: TextIO | None, cameras: list[str] = ()) -> ExportResult:
    """Write every episode through the writer ``make(tmp)`` (``add`` per episode, then ``close``)
    into a fresh folder renamed to ``out`` at the end."""
    t0 = time.perf_counter()
    try:
        with new_folder(out) as tmp:
            writer = make(tmp)
            progress = Progress(f"export {fmt}", len(writer.entries), stream=stream or sys.stderr)
            for e in writer.entries:
                add(writer, e, ds.episode_arrays(e, keys))
                progress.update()
            writer.close()
            if read_dataset_info(ds.path).fingerprint != ds.info.fingerprint:
                raise ValueError(f"{ds.path}: the dataset was rewritten while exporting; export again")
    finally:
        ds.close()
    files = tree_files(out)
    return ExportResult(format=fmt, out=str(out), source=str(ds.path), fingerprint=ds.info.fingerprint,
                        episodes=len(writer.entries), frames=writer.frames, cameras=list(cameras), files=len(files),
                        nbytes=sum((out / f).stat().st_size for f in files), seconds=time.perf_counter() - t0)
