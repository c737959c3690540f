"""A rendered snapshot of a seed's scene from the four cameras, as one picture."""

from __future__ import annotations

import io
import logging
import time
from pathlib import Path

from anchordp3.schemas.sim import WorldConfig
from anchordp3.sim.episode import build
from anchordp3.stages.files import atomic_write_bytes
from anchordp3.viz.mosaic import mosaic

log = logging.getLogger(__name__)


def snapshot(task: str, seed: int, world: WorldConfig, out: Path) -> Path:
    """Build and settle ``(task, seed)`` with rendering on, capture every view, save a PNG mosaic
    (written whole or not at all); each step is logged as it starts."""
    t0 = time.perf_counter()
    log.info(f"snapshot {task} seed {seed}: building the scene (the renderer starts)")
    w, t = build(task, seed, world, render=True)
    log.info(f"snapshot: settling the objects ({time.perf_counter() - t0:.1f} s)")
    w.settle_and_check()
    log.info(f"snapshot: rendering {len(world.cameras.views)} views ({time.perf_counter() - t0:.1f} s; "
             "the first render in a process compiles the shaders)")
    caps = w.capture(segmentation=False)
    buf = io.BytesIO()
    mosaic([c.rgb for c in caps], [c.name for c in caps], title=f"{task} seed {seed}: {t.instruction()}").save(buf, format="PNG")
    atomic_write_bytes(Path(out), buf.getvalue())
    log.info(f"snapshot: done in {time.perf_counter() - t0:.1f} s")
    return Path(out)
