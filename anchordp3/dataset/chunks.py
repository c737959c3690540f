"""Direct reads of one sample from a sharded zarr v3 array, without zarr's per-call overhead.

zarr's ``Array.__getitem__`` costs about 1.5 ms per call (async machinery), which dominates a
random read of one sample. The arrays written by ``dataset.shard`` have a simple, fixed layout:
codec ``sharding_indexed`` with the index at the end (``bytes`` + ``crc32c``), inner chunks that
split only the sample axis, and inner codecs ``bytes`` (little-endian) + at most one compressor
(zstd, blosc or gzip). For that layout this module parses the shard index once (checking its
crc32c), then serves a sample with one ``pread`` of its inner chunk and one decompression.

Any other layout falls back to zarr itself, so reads stay correct for arrays written otherwise.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import google_crc32c
import numpy as np
import zarr
from numcodecs import GZip, Zstd, blosc

_EMPTY = np.uint64(2**64 - 1)


class CorruptShardError(ValueError):
    """A shard file's index or chunk does not decode."""


def _decoder(codecs: list[dict]):
    """Bytes -> bytes decompressor for the inner codec list, or None when the layout is not ours."""
    if not codecs or codecs[0].get("name") != "bytes":
        return None
    if codecs[0].get("configuration", {}).get("endian", "little") != "little":
        return None
    rest = codecs[1:]
    if not rest:
        return lambda b: b
    if len(rest) != 1:
        return None
    name = rest[0].get("name")
    if name == "zstd":
        z = Zstd()
        return z.decode
    if name == "blosc":
        return blosc.decompress
    if name == "gzip":
        g = GZip()
        return g.decode
    return None


class ArrayReader:
    """Reads samples (rows along axis 0) of one zarr v3 array folder.

    ``sample(i)`` returns a fresh, writable array of shape ``shape[1:]``; ``read_all()`` the whole
    array. Safe to use after ``fork``: file descriptors are reopened in a new process."""

    def __init__(self, array_dir: Path):
        self.path = Path(array_dir)
        meta = json.loads((self.path / "zarr.json").read_text())
        self.shape = tuple(meta["shape"])
        self.dtype = np.dtype(meta["data_type"]).newbyteorder("<")
        self._zarr = None
        self._fast = self._parse(meta)
        self._fd: int | None = None
        self._pid = -1
        self._index: np.ndarray | None = None
        self._cached: tuple[int, np.ndarray] | None = None  # last decoded inner chunk

    def _parse(self, meta: dict) -> bool:
        codecs = meta.get("codecs", [])
        if len(codecs) != 1 or codecs[0].get("name") != "sharding_indexed":
            return False
        cfg = codecs[0]["configuration"]
        idx = cfg.get("index_codecs", [])
        if cfg.get("index_location", "end") != "end" or [c.get("name") for c in idx] != ["bytes", "crc32c"]:
            return False
        if meta.get("chunk_key_encoding", {}).get("configuration", {}).get("separator", "/") != "/":
            return False
        shard = tuple(meta["chunk_grid"]["configuration"]["chunk_shape"])
        inner = tuple(cfg["chunk_shape"])
        self._decode = _decoder(cfg.get("codecs", []))
        if self._decode is None or shard[1:] != self.shape[1:] or inner[1:] != self.shape[1:]:
            return False
        if self.shape and self.shape[0] > shard[0]:  # more than one zarr shard along samples
            return False
        self.inner = inner[0]
        self._n_inner = shard[0] // inner[0]
        self._chunk_shape = inner
        self._fill = meta.get("fill_value", 0)
        self._file = self.path / "c" / "/".join("0" * len(self.shape))
        return True

    # ---- low level -------------------------------------------------------------------------
    def _fd_now(self) -> int:
        if self._fd is None or self._pid != os.getpid():
            self._fd = os.open(self._file, os.O_RDONLY)
            self._pid = os.getpid()
        return self._fd

    def _load_index(self) -> np.ndarray:
        if self._index is None or self._pid != os.getpid():
            fd = self._fd_now()
            size = os.fstat(fd).st_size
            n = self._n_inner * 16 + 4
            if size < n:
                raise CorruptShardError(f"{self._file}: shard file too short for its index")
            raw = os.pread(fd, n, size - n)
            body, crc = raw[:-4], int.from_bytes(raw[-4:], "little")
            if google_crc32c.value(body) != crc:
                raise CorruptShardError(f"{self._file}: shard index checksum mismatch")
            self._index = np.frombuffer(body, dtype="<u8").reshape(self._n_inner, 2)
        return self._index

    def _chunk(self, c: int) -> np.ndarray:
        if self._cached is not None and self._cached[0] == c and self._pid == os.getpid():
            return self._cached[1]
        index = self._load_index()
        off, nbytes = index[c]
        if off == _EMPTY:
            arr = np.full(self._chunk_shape, self._fill, dtype=self.dtype)
        else:
            raw = os.pread(self._fd_now(), int(nbytes), int(off))
            try:
                data = self._decode(raw)
                arr = np.frombuffer(data, dtype=self.dtype).reshape(self._chunk_shape)
            except Exception as e:  # noqa: BLE001 - any decode failure means a corrupt chunk
                raise CorruptShardError(f"{self._file}: inner chunk {c} does not decode ({type(e).__name__})") from None
        self._cached = (c, arr)
        return arr

    # ---- public ----------------------------------------------------------------------------
    def sample(self, i: int) -> np.ndarray:
        """Row ``i`` (0 <= i < shape[0]) as a new array of shape ``shape[1:]``."""
        if not 0 <= i < self.shape[0]:
            raise IndexError(f"{self.path}: sample {i} out of range [0, {self.shape[0]})")
        if not self._fast:
            return np.asarray(self._zarr_array()[i])
        return self._chunk(i // self.inner)[i % self.inner].copy()

    def read_all(self) -> np.ndarray:
        """The whole array."""
        if not self._fast:
            return np.asarray(self._zarr_array()[...])
        n = self.shape[0]
        if n == 0:
            return np.zeros(self.shape, dtype=self.dtype)
        parts = [self._chunk(c) for c in range(-(-n // self.inner))]
        return np.concatenate(parts)[:n].copy()

    def _zarr_array(self):
        if self._zarr is None:
            self._zarr = zarr.open_array(self.path, mode="r")
        return self._zarr

    def close(self) -> None:
        """Close the file descriptor (reopened on the next read)."""
        if self._fd is not None and self._pid == os.getpid():
            os.close(self._fd)
        self._fd, self._index, self._cached, self._pid = None, None, None, -1

    def __getstate__(self):
        state = self.__dict__.copy()
        state.update(_fd=None, _pid=-1, _index=None, _cached=None, _zarr=None)
        return state
