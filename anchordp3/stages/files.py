"""Durable, deterministic file writes (temporary name, fsync, rename) and where each episode stage's files lie."""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np

_EPOCH = (1980, 1, 1, 0, 0, 0)  # fixed zip timestamps: the same arrays give the same bytes


# Where each episode stage puts an episode's output, relative to the stage folder. They live here, in
# a module that imports nothing of the package, so that a stage naming another's files does not
# take on that stage's code (and its code fingerprint).
def plan_file(task: str, seed: int) -> str:
    """Path of an episode's frame plan (anchors stage)."""
    return f"plans/{task}/{seed:06d}.parquet"


def frames_file(task: str, seed: int) -> str:
    """Path of an episode's rendered frames (render stage)."""
    return f"frames/{task}/{seed:06d}.npz"


def features_file(task: str, seed: int) -> str:
    """Path of an episode's point-cloud features (features stage)."""
    return f"features/{task}/{seed:06d}.npz"


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a crash leaves either the old file or the new one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """A compressed ``.npz`` archive of ``arrays`` whose bytes depend only on the arrays."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            with zf.open(info, "w") as f:
                np.lib.format.write_array(f, np.ascontiguousarray(arrays[name]), allow_pickle=False)
    return buf.getvalue()


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Atomically write ``arrays`` as a deterministic ``.npz`` file."""
    atomic_write_bytes(path, npz_bytes(arrays))
