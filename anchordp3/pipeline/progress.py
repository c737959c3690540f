"""Progress lines for long work: items done / failed, rate and ETA."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """Prints ``label  done/total  failed  rate/s  ETA`` at most every ``interval`` seconds (and at the end)."""

    def __init__(self, label: str, total: int, stream: TextIO = sys.stderr, interval: float = 1.0):
        self.label, self.total, self.stream, self.interval = label, total, stream, interval
        self.done = self.failed = 0
        self.t0 = time.perf_counter()
        self._last = 0.0

    def update(self, ok: bool = True) -> None:
        """Count one finished item."""
        self.done += 1
        self.failed += 0 if ok else 1
        now = time.perf_counter()
        if now - self._last >= self.interval or self.done == self.total:
            self._last = now
            self.stream.write(self.line() + "\n")
            self.stream.flush()

    def line(self) -> str:
        """The current progress line."""
        el = time.perf_counter() - self.t0
        rate = self.done / el if el > 0 else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        return (f"[{self.label}] {self.done}/{self.total} items, {self.failed} failed, "
                f"{rate:.2f} items/s, elapsed {el:.0f}s, ETA {eta:.0f}s")
