"""Running the rollout stage over many seeds in this process, with progress and a summary."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from anchordp3.pipeline.progress import Progress
from anchordp3.schemas.episode import EpisodeRecord
from anchordp3.schemas.sim import WorldConfig
from anchordp3.stages.rollout import rollout


def run_rollouts(task: str, seeds: list[int], world: WorldConfig, preset: str, out_dir: Path | None = None,
                 show_progress: bool = True) -> list[EpisodeRecord]:
    """Roll the expert out on every seed; kept episodes' arrays go to ``out_dir`` when given."""
    prog = Progress(f"rollout {task}", len(seeds)) if show_progress else None
    records = []
    for seed in seeds:
        rec = rollout(task, seed, world, preset, out_dir)
        records.append(rec)
        if prog:
            prog.update(rec.success)
    return records


def summarize(records: list[EpisodeRecord]) -> dict:
    """Success rate, failure reasons with counts, mean anchors and seconds of a set of episodes."""
    n = len(records)
    ok = [r for r in records if r.success]
    return {
        "episodes": n,
        "successes": len(ok),
        "success_rate": len(ok) / n if n else 0.0,
        "reasons": dict(Counter(r.reason for r in records if not r.success)),
        "mean_anchors": sum(len(r.anchors) for r in ok) / len(ok) if ok else 0.0,
        "mean_steps": sum(r.steps for r in ok) / len(ok) if ok else 0.0,
        "mean_seconds": sum(r.seconds for r in records) / n if n else 0.0,
    }
