"""Wall time per phase of a long, resumable piece of work (an experiment arm's data, training,
evaluation), summed over the invocations that built it and kept in a JSON file, so a resumed run
reports what each phase cost in all."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from anchordp3.stages.files import atomic_write_bytes

log = logging.getLogger(__name__)

T = TypeVar("T")


class PhaseClock:
    """``seconds[group][phase]``, loaded from ``path`` when it exists and saved after every phase."""

    def __init__(self, path: Path, groups: tuple[str, ...]):
        self.path = Path(path)
        self.seconds: dict[str, dict[str, float]] = json.loads(self.path.read_text()) if self.path.is_file() else {}
        for g in groups:
            self.seconds.setdefault(g, {})

    def timed(self, group: str, phase: str, fn: Callable[[], T]) -> T:
        """Run ``fn``; its wall time adds to what earlier invocations spent on ``group``/``phase``."""
        log.info(f"{group}: {phase}")
        t0 = time.perf_counter()
        result = fn()
        self.add(group, phase, time.perf_counter() - t0)
        return result

    def add(self, group: str, phase: str, seconds: float) -> None:
        """``seconds`` more spent on ``group``/``phase`` (saved at once)."""
        self.seconds.setdefault(group, {})[phase] = self.seconds[group].get(phase, 0.0) + seconds
        atomic_write_bytes(self.path, json.dumps(self.seconds, indent=1).encode())

    def recorder(self, group: str) -> Callable[[str, float], None]:
        """A runner's ``RunOptions.on_phase`` that adds each phase's time to ``group``."""
        return lambda phase, seconds: self.add(group, phase, seconds)
