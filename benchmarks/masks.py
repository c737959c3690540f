"""Time the two critical-object mask methods side by side on the same rendered frames.

    python benchmarks/masks.py [--task stack_blocks_three] [--seed 0] [--frames 12]

Replays a kept expert episode at the default camera settings (4 views, 320×240) and at evenly
spaced steps renders every view with each method, alternating which goes first:

* segmentation: one render with SAPIEN's per-entity segmentation buffer;
* depth_diff (the report's method): one render, then a re-render with the critical objects
  invisible, masks where the depth changed.

Prints per-frame times, the speed-up and the pixel agreement of the two masks.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from anchordp3.schemas.sim import world_config  # noqa: E402
from anchordp3.schemas.stages import RenderConfig  # noqa: E402
from anchordp3.sim.episode import build, run_expert  # noqa: E402
from anchordp3.sim.frames import observe  # noqa: E402
from anchordp3.sim.masks import critical_roles  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="stack_blocks_three")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=12, help="frames timed (evenly spaced over the episode)")
    parser.add_argument("--preset", default="randomized")
    args = parser.parse_args()

    world_cfg = world_config(args.preset)
    ep = run_expert(args.task, args.seed, world_cfg)
    if not ep.success:
        raise SystemExit(f"{args.task} seed {args.seed}: the expert failed ({ep.reason}); pick another seed")
    world, task = build(args.task, args.seed, world_cfg, render=True)
    world.settle_and_check()
    roles = critical_roles(world, task.critical_objects(), include_robot=True)
    methods = {m: RenderConfig(mask_method=m) for m in ("segmentation", "depth_diff")}
    observe(world, roles, methods["segmentation"])  # warm-up: shader compilation
    steps = set(np.linspace(0, len(ep.actions), args.frames).astype(int).tolist())
    times = {m: [] for m in methods}
    agree, critical = [], []
    for t in range(len(ep.actions) + 1):
        if t in steps:
            order = list(methods) if t % 2 == 0 else list(methods)[::-1]
            masks = {}
            for m in order:
                t0 = time.perf_counter()
                _, masks[m] = observe(world, roles, methods[m])
                times[m].append(time.perf_counter() - t0)
            agree.append(float((masks["segmentation"] == masks["depth_diff"]).mean()))
            critical.append(float((masks["segmentation"] > 0).mean()))
        if t < len(ep.actions):
            world.control_step(ep.actions[t])

    c = world_cfg.cameras
    print(f"{args.task} seed {args.seed}: {len(agree)} frames, {len(c.views)} views at {c.width}x{c.height}")
    for m, ts in times.items():
        ts = np.asarray(ts) * 1e3
        print(f"{m:13s} per frame: best {ts.min():7.1f} ms   median {np.median(ts):7.1f} ms")
    seg, dd = (np.median(times[m]) for m in ("segmentation", "depth_diff"))
    print(f"speed-up of segmentation over depth_diff (median): {dd / seg:.2f}x")
    print(f"pixel agreement: min {min(agree):.5f}  mean {np.mean(agree):.5f}; critical pixels {np.mean(critical):.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
