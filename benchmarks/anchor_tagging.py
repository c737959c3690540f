"""Kinematic anchor tagging measured against the expert's symbolic tags.

    python benchmarks/anchor_tagging.py [--seeds 0-9] [--tol 3]

For each task's kept expert episodes, tags anchors from motion alone, once from the commanded
actions and once from the measured states only, and prints precision and recall of those tags
against the expert's operation boundaries (a match is within ±tol control steps, one to one).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from anchordp3.schemas.episode import parse_seeds  # noqa: E402
from anchordp3.schemas.sim import world_config  # noqa: E402
from anchordp3.sim.episode import run_expert  # noqa: E402
from anchordp3.sim.tasks import TASKS  # noqa: E402
from anchordp3.stages.anchors import kinematic_anchors, match_anchors  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="0-9")
    parser.add_argument("--tol", type=int, default=3, help="match tolerance, control steps")
    parser.add_argument("--preset", default="randomized")
    parser.add_argument("--tasks", default=",".join(TASKS), help="comma-separated task names")
    args = parser.parse_args()
    world = world_config(args.preset)
    rows = []
    for task in args.tasks.split(","):
        totals = {"commands": [0, 0, 0], "states": [0, 0, 0]}
        kept, seconds = 0, 0.0
        for seed in parse_seeds(args.seeds):
            ep = run_expert(task, seed, world)
            if not ep.success:
                continue
            kept += 1
            true = [a.t for a in ep.anchors]
            for source, actions in (("commands", ep.actions), ("states", None)):
                t0 = time.perf_counter()
                pred = kinematic_anchors(ep.states, actions)
                seconds += time.perf_counter() - t0
                for i, v in enumerate(match_anchors(pred, np.asarray(true), args.tol)):
                    totals[source][i] += v
        for source, (m, p, t) in totals.items():
            rows.append([task, source, kept, t, p, f"{m / p:.3f}" if p else "-", f"{m / t:.3f}" if t else "-"])
    print(text_table(["task", "tagged from", "episodes", "symbolic anchors", "kinematic anchors", "precision", "recall"], rows))
    print(f"(match within ±{args.tol} control steps; preset {args.preset}; seeds {args.seeds})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
