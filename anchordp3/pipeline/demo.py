"""``anchordp3 demo``: what the system can do so far, on a tiny default, in a couple of minutes.

Today: CPU rollouts of every task on a few randomized seeds (episodes saved), and a rendered
snapshot of each task's first seed. Later stages join as they land.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from anchordp3.pipeline.rollouts import run_rollouts, summarize
from anchordp3.schemas.sim import world_config
from anchordp3.sim.tasks import TASKS
from anchordp3.stages.snapshot import snapshot
from anchordp3.viz.table import text_table


def run_demo(out_dir: Path, seeds: list[int], preset: str = "randomized", say: Callable[[str], None] = print) -> dict:
    """Roll out every task on ``seeds`` and snapshot each; returns the per-task summaries."""
    out_dir = Path(out_dir)
    world = world_config(preset)
    summaries, rows = {}, []
    for task in TASKS:
        records = run_rollouts(task, seeds, world, preset, out_dir / "rollout")
        s = summarize(records)
        summaries[task] = s
        png = snapshot(task, seeds[0], world, out_dir / "snapshots" / f"{task}.png")
        rows.append([task, f"{s['successes']}/{s['episodes']}", s["mean_anchors"], s["mean_steps"], s["mean_seconds"], str(png)])
    say(text_table(["task", "kept", "anchors/ep", "steps/ep", "s/episode", "snapshot"], rows))
    say(f"\nKept episodes (states, replayable actions, anchors) are in {out_dir / 'rollout' / 'episodes'}; "
        f"snapshots of the four camera views in {out_dir / 'snapshots'}.")
    return summaries
