"""A rendered snapshot of a seed's scene from the four cameras, as one picture."""

from __future__ import annotations

from pathlib import Path

from anchordp3.schemas.sim import WorldConfig
from anchordp3.sim.episode import build
from anchordp3.viz.mosaic import mosaic


def snapshot(task: str, seed: int, world: WorldConfig, out: Path) -> Path:
    """Build and settle ``(task, seed)`` with rendering on, capture every view, save a PNG mosaic."""
    w, t = build(task, seed, world, render=True)
    w.settle_and_check()
    caps = w.capture(segmentation=False)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    mosaic([c.rgb for c in caps], [c.name for c in caps], title=f"{task} seed {seed}: {t.instruction()}").save(out)
    return out
