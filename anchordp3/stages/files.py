"""Durable, deterministic file writes (temporary name, fsync, rename) and where each episode stage's files lie."""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import os
import shutil
import sqlite3
import tempfile
import zipfile
from pathlib import Path
from typing import BinaryIO, Callable

import numpy as np

_EPOCH = (1980, 1, 1, 0, 0, 0)  # fixed zip timestamps: the same arrays give the same bytes
_NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
_SQLITE_FULL = 13  # SQLITE_FULL: "database or disk is full"
TMP_MARK = ".tmp-"  # in the name of a write in progress: ``.<name>.tmp-<pid>`` (a file, or a folder of a zarr shard)

log = logging.getLogger(__name__)


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
    atomic_write(path, lambda f: f.write(data))


def atomic_write(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Let ``write(f)`` fill a temporary file beside ``path``, make it durable and rename it to
    ``path``: a crash leaves either the old file or the new one, never a part of it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}{TMP_MARK}{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)  # a full disk must not keep the half-written bytes
        e.filename = str(path)  # the file that was being written, not its temporary name
        raise


def user_path(filename: str | os.PathLike) -> str:
    """The path a user asked for, behind a write in progress: ``dir/.<name>.tmp-<pid>`` (a file, or
    a folder of a zarr shard or an export, or anything below it) is ``dir/<name>``; other paths
    are returned as they are."""
    parts = list(Path(filename).parts)
    for i, part in enumerate(parts):
        if part.startswith(".") and TMP_MARK in part:
            return str(Path(*parts[:i], part[1:part.index(TMP_MARK)]))
    return str(filename)


def check_destination(path: Path | str, folder: bool) -> None:
    """Refuse, before any work starts, a destination that cannot be written: raise ``OSError``
    naming ``path`` when it is a file where a folder is wanted (or the reverse), when a parent is a
    file, or when the nearest existing folder refuses a new file (read-only, permissions).
    Creates nothing: the probe is a temporary file, removed at once.

    folder: the destination is a folder (a run directory, an output folder), else a file."""
    path = Path(path)
    if path.exists() and folder and not path.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "not a directory", str(path))
    if path.is_dir() and not folder:
        raise IsADirectoryError(errno.EISDIR, "is a directory", str(path))
    where = path if path.is_dir() else path.parent
    while not where.exists() and where != where.parent:
        where = where.parent
    if not where.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, f"{where} is not a directory", str(path))
    try:
        fd, probe = tempfile.mkstemp(prefix=".probe", suffix=f"{TMP_MARK}{os.getpid()}", dir=where)
    except OSError as e:
        raise type(e)(e.errno, e.strerror, str(path)) from None
    os.close(fd)
    os.unlink(probe)


def os_error_line(e: OSError) -> str:
    """One line for an OS error while reading or writing: ``<path>: <reason>`` naming the path the
    user gave or the file that failed (never a temporary name), e.g. ``runs/x: read-only file system``."""
    if e.strerror is None:  # raised with a message of its own
        return str(e).splitlines()[0] if str(e) else type(e).__name__
    reason = e.strerror[0].lower() + e.strerror[1:]
    return f"{user_path(e.filename)}: {reason}" if e.filename is not None else reason


def no_space(e: BaseException, where: Path | str | None = None) -> str | None:
    """``"<path>: no space left on device"`` when ``e`` is a full disk (or quota) while writing,
    else None. ``<path>``: the file being written where the error knows it, else ``where``."""
    if isinstance(e, OSError) and e.errno in _NO_SPACE:
        return f"{user_path(e.filename) if e.filename else where or 'a file'}: {os.strerror(e.errno).lower()}"
    if isinstance(e, sqlite3.OperationalError) and getattr(e, "sqlite_errorcode", None) == _SQLITE_FULL:
        return f"{where or 'a manifest'}: no space left on device (SQLite: {e})"
    return None


def sweep_interrupted_writes(root: Path) -> int:
    """Delete what interrupted writes left under ``root`` (``.<name>.tmp-<pid>`` files and folders:
    a write killed before its rename); returns how many. Call it only while no one writes there
    (the run's lock held): the leftovers hold disk space a resumed run may need."""
    swept = 0
    for dirpath, dirnames, filenames in os.walk(root):
        for name in [n for n in dirnames if n.startswith(".") and TMP_MARK in n]:
            shutil.rmtree(Path(dirpath) / name, ignore_errors=True)
            dirnames.remove(name)
            swept += 1
        for name in filenames:
            if name.startswith(".") and TMP_MARK in name:
                (Path(dirpath) / name).unlink(missing_ok=True)
                swept += 1
    if swept:
        log.info(f"{root}: removed {swept} temporary file(s) of interrupted writes")
    return swept


def npz_bytes(arrays: dict[str, np.ndarray], compress: bool = True) -> bytes:
    """An ``.npz`` archive of ``arrays`` whose bytes depend only on the arrays (and ``compress``).

    compress: deflate every array (zlib level 6, ``np.savez_compressed``'s); False stores them as
    they are (``np.savez``'s), for files read once and dropped: no deflate to pay, nor inflate."""
    buf = io.BytesIO()
    _write_npz(buf, arrays, compress)
    return buf.getvalue()


def _write_npz(f: BinaryIO, arrays: dict[str, np.ndarray], compress: bool) -> None:
    """Write the archive ``npz_bytes`` describes into ``f`` (seekable), array by array."""
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(f, "w", method) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
            info.compress_type = method
            with zf.open(info, "w") as member:
                np.lib.format.write_array(member, np.ascontiguousarray(arrays[name]), allow_pickle=False)


def save_npz(path: Path, arrays: dict[str, np.ndarray], compress: bool = True) -> None:
    """Atomically write ``arrays`` as a deterministic ``.npz`` file (``compress``: see ``npz_bytes``),
    streamed into the file rather than assembled in memory first."""
    atomic_write(path, lambda f: _write_npz(f, arrays, compress))
