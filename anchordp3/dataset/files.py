"""Directory-level helpers: content checksums, fsync of a tree, swapping a finished folder in."""

from __future__ import annotations

import hashlib
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_BLOCK = 1 << 20


def tree_files(root: Path) -> list[str]:
    """Relative POSIX paths of every regular file under ``root``, sorted."""
    root = Path(root)
    out = []
    for dirpath, _, names in os.walk(root):
        for n in names:
            out.append((Path(dirpath) / n).relative_to(root).as_posix())
    return sorted(out)


def file_sha256(path: Path) -> str:
    """sha256 hex digest of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_BLOCK):
            h.update(block)
    return h.hexdigest()


def tree_checksum(root: Path) -> tuple[str, int]:
    """sha256 over (relative name, size, bytes) of every file under ``root``; and the total bytes.

    Two folders have the same checksum iff they hold the same files with the same contents."""
    root = Path(root)
    h = hashlib.sha256()
    total = 0
    for rel in tree_files(root):
        p = root / rel
        size = p.stat().st_size
        total += size
        h.update(rel.encode() + b"\0" + size.to_bytes(8, "little"))
        with open(p, "rb") as f:
            while block := f.read(_BLOCK):
                h.update(block)
    return h.hexdigest(), total


def fsync_tree(root: Path) -> None:
    """fsync every file and folder under ``root`` (and ``root`` itself)."""
    for dirpath, _, names in os.walk(root):
        for n in names:
            fd = os.open(Path(dirpath) / n, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        fsync_dir(Path(dirpath))


def fsync_dir(path: Path) -> None:
    """fsync a folder so that renames inside it are durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def swap_in(tmp: Path, final: Path) -> None:
    """Rename the finished folder ``tmp`` to ``final``.

    An existing ``final`` is first renamed aside and deleted afterwards, so at every instant
    ``final`` is either absent, the old complete folder, or the new complete folder."""
    old = None
    if final.exists():
        old = final.with_name(f".{final.name}.old-{os.getpid()}")
        shutil.rmtree(old, ignore_errors=True)
        os.rename(final, old)
    os.rename(tmp, final)
    fsync_dir(final.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def remove_stale(final: Path) -> None:
    """Delete leftovers (``.<name>.tmp-*`` / ``.<name>.old-*``) of earlier crashed writes of ``final``."""
    if not final.parent.is_dir():
        return
    for p in final.parent.glob(f".{final.name}.*-*"):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def refuse_existing(final: Path) -> Path:
    """``final`` as a Path; ValueError naming it when something is already there."""
    final = Path(final)
    if final.exists() or final.is_symlink():
        raise ValueError(f"{final}: already exists; remove it or choose another output path")
    return final


@contextmanager
def new_folder(final: Path) -> Iterator[Path]:
    """``with new_folder(OUT) as tmp:`` fill ``tmp``, a hidden sibling ``.<name>.tmp-<pid>``; when the
    block ends without error it is made durable and renamed to ``OUT``, otherwise deleted, so ``OUT``
    is either absent or complete. ValueError naming ``OUT`` when it already exists (never replaced)."""
    final = refuse_existing(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    remove_stale(final)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    tmp.mkdir()
    try:
        yield tmp
        fsync_tree(tmp)
        if final.exists():  # appeared meanwhile: rename would replace an empty folder silently
            raise ValueError(f"{final}: appeared while exporting; remove it or choose another output path")
        os.rename(tmp, final)
        fsync_dir(final.parent)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
