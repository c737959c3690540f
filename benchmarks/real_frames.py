"""Real rendered frames for the benchmarks: roll out the expert, plan, render (full resolution)."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install

from anchordp3.schemas.sim import world_config  # noqa: E402
from anchordp3.schemas.stages import AnchorsConfig, RenderConfig  # noqa: E402
from anchordp3.stages.anchors import run_anchors  # noqa: E402
from anchordp3.stages.render import load_frames, run_render  # noqa: E402
from anchordp3.stages.rollout import rollout  # noqa: E402


def rendered_frames(task: str = "stack_blocks_three", seed: int = 0, preset: str = "randomized") -> dict[str, np.ndarray]:
    """The planned frames of one kept episode at the default camera settings (4 views, 320×240)."""
    world = world_config(preset)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        rec = rollout(task, seed, world, preset, root / "rollout")
        if not rec.success:
            raise SystemExit(f"{task} seed {seed}: the expert failed ({rec.reason}); pick another seed")
        cfg = AnchorsConfig(dagger={"fraction": 0.0})
        plan = root / "anchors" / run_anchors(rec, root / "rollout", root / "anchors", cfg)
        return load_frames(root / "render" / run_render(rec, root / "rollout", plan, root / "render", world, RenderConfig(), cfg))
