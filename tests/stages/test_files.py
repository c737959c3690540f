"""Crash-safe writes: a full disk keeps neither half-written bytes nor the temporary file and
names the file; leftovers of interrupted writes are swept."""

from __future__ import annotations

import errno
import os
import sqlite3

import pytest

from anchordp3.stages import files
from anchordp3.stages.files import atomic_write_bytes, no_space, sweep_interrupted_writes


def test_a_full_disk_leaves_the_old_file_and_no_temporary_one(tmp_path, monkeypatch):
    path = tmp_path / "a" / "x.npz"
    atomic_write_bytes(path, b"old")

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(files.os, "fsync", full)
    with pytest.raises(OSError) as e:
        atomic_write_bytes(path, b"new bytes")
    assert path.read_bytes() == b"old" and sorted(p.name for p in path.parent.iterdir()) == ["x.npz"]
    assert no_space(e.value) == f"{path}: no space left on device"


def test_no_space_knows_a_full_disk_from_other_errors(tmp_path):
    assert no_space(OSError(errno.EDQUOT, "quota"), tmp_path) == f"{tmp_path}: {os.strerror(errno.EDQUOT).lower()}"
    assert no_space(OSError(errno.EACCES, "denied")) is None
    assert no_space(ValueError("x")) is None
    full = sqlite3.OperationalError("database or disk is full")
    full.sqlite_errorcode = 13
    assert no_space(full, tmp_path).startswith(f"{tmp_path}: no space left on device")


def test_leftovers_of_interrupted_writes_are_swept_and_nothing_else(tmp_path):
    (tmp_path / "frames" / "t").mkdir(parents=True)
    kept = [tmp_path / "frames" / "t" / "000001.npz", tmp_path / ".lock", tmp_path / "records.sqlite.tmp"]
    for p in kept:
        p.write_bytes(b"x")
    (tmp_path / "frames" / "t" / ".000002.npz.tmp-4242").write_bytes(b"half")
    shard = tmp_path / "shards" / ".00001.zarr.tmp-77"
    (shard / "points").mkdir(parents=True)
    (shard / "points" / "c0").write_bytes(b"half")
    assert sweep_interrupted_writes(tmp_path) == 2
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()) == sorted(
        p.relative_to(tmp_path).as_posix() for p in kept)
    assert sweep_interrupted_writes(tmp_path / "absent") == 0
