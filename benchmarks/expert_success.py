"""Expert success per task and randomization preset (CPU rollouts, no rendering).

    python benchmarks/expert_success.py [--seeds 0-99] [--presets clean,randomized] [--tasks a,b]
                                        [--preset-seeds clean=0-29 ...]

Covers every registered task (the eight AnchorDP3 task categories) under each preset. Prints, per
task and preset: successes, success rate, failure reasons, mean anchors per kept episode, mean
control steps per kept episode, and the expert's mean seconds per episode (CPU, no rendering;
timings are wall-clock and shift with machine load). RoboTwin's own experts reach 0.66-0.96 per
seed on the challenge tasks (REFERENCE.md); the bar here is >= 0.80.
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
    ap.add_argument("--preset-seeds", action="append", default=[], metavar="PRESET=SEEDS",
                    help="seeds for one preset instead of --seeds, e.g. clean=0-29 (repeatable)")
    args = ap.parse_args()
    seeds = {p: parse_seeds(args.seeds) for p in args.presets.split(",")}
    for item in args.preset_seeds:
        name, _, text = item.partition("=")
        if name not in seeds:
            ap.error(f"--preset-seeds: {name!r} is not one of --presets {sorted(seeds)}")
        seeds[name] = parse_seeds(text, "--preset-seeds")
    rows = []
    for task in args.tasks.split(","):
        for preset in seeds:
            s = summarize(run_rollouts(task, seeds[preset], world_config(preset), preset, show_progress=False))
            reasons = ", ".join(f"{k}:{v}" for k, v in sorted(s["reasons"].items())) or "-"
            rows.append([task, preset, f"{s['successes']}/{s['episodes']}", s["success_rate"], s["mean_anchors"],
                         s["mean_steps"], s["mean_seconds"], reasons])
            print(text_table(["task", "preset", "kept", "rate", "anchors/ep", "steps/ep", "s/episode", "failures"], rows[-1:])
                  .splitlines()[-1], flush=True)
    print()
    print(text_table(["task", "preset", "kept", "rate", "anchors/ep", "steps/ep", "s/episode", "failures"], rows))


if __name__ == "__main__":
    main()
