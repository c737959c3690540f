"""Expert success per task and randomization preset (CPU rollouts, no rendering).

    python benchmarks/expert_success.py [--seeds 0-99] [--presets clean,randomized] [--tasks a,b]

Prints, per task and preset: successes, success rate, failure reasons, mean anchors per kept
episode, mean control steps, and the expert's mean seconds per episode. RoboTwin's own experts
reach 0.66-0.96 per seed on the challenge tasks (REFERENCE.md); the bar here is >= 0.80.
"""

from __future__ import annotations

import argparse

from anchordp3.pipeline.rollouts import run_rollouts, summarize
from anchordp3.schemas.episode import parse_seeds
from anchordp3.schemas.sim import world_config
from anchordp3.sim.tasks import TASKS
from anchordp3.viz.table import text_table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0-99")
    ap.add_argument("--presets", default="clean,randomized")
    ap.add_argument("--tasks", default=",".join(TASKS))
    args = ap.parse_args()
    seeds = parse_seeds(args.seeds)
    rows = []
    for task in args.tasks.split(","):
        for preset in args.presets.split(","):
            s = summarize(run_rollouts(task, seeds, world_config(preset), preset, show_progress=False))
            reasons = ", ".join(f"{k}:{v}" for k, v in sorted(s["reasons"].items())) or "-"
            rows.append([task, preset, f"{s['successes']}/{s['episodes']}", s["success_rate"], s["mean_anchors"],
                         s["mean_steps"], s["mean_seconds"], reasons])
            print(text_table(["task", "preset", "kept", "rate", "anchors/ep", "steps/ep", "s/episode", "failures"], rows[-1:])
                  .splitlines()[-1], flush=True)
    print()
    print(text_table(["task", "preset", "kept", "rate", "anchors/ep", "steps/ep", "s/episode", "failures"], rows))


if __name__ == "__main__":
    main()
