"""Pipelined wall time of the data stages against the sum of the stages' own compute times.

    python benchmarks/pipeline.py [--config anchordp3/configs/demo.yaml] [--seeds 0-1] [--workers N]

Runs the data stages of the config into a fresh temporary run directory with Ray actor pools
(items stream between stages), then reads every stage's manifest: the sum of the items' compute
seconds is what running the stages one after another in one process would take; the ratio to
the pipelined wall time is what streaming over actor pools buys on this machine. Also prints the
samples written per second of wall time, and the render and features stages' cost per
rendered frame with their ratio (the features stage should keep pace with the renderer). The
ratio is taken on CPU time (each item's worker process, all threads, as its record holds it):
stage wall times on a busy 2-core machine say more about which actor the scheduler favoured
than about what a frame costs. Last line: ``RESULT features_over_render=X
render_cpu_ms_per_frame=R features_cpu_ms_per_frame=F render_ms_per_frame=.. features_ms_per_frame=.. speedup=S``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from anchordp3.dataset.reader import open_dataset  # noqa: E402
from anchordp3 import logs  # noqa: E402
from anchordp3.pipeline.runner import RunOptions, run_pipeline  # noqa: E402
from anchordp3.pipeline.store import read_manifest  # noqa: E402
from anchordp3.pipeline.work import DATA_STAGES, stage_dir  # noqa: E402
from anchordp3.schemas.run import load_run_config  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path(__file__).resolve().parents[1] / "anchordp3" / "configs" / "demo.yaml")
    parser.add_argument("--seeds", default=None, help="override the config's seeds")
    parser.add_argument("--workers", type=int, default=None, help="actors per stage pool (default: the config's)")
    args = parser.parse_args()
    logs.console()  # progress lines on stderr
    cfg = load_run_config(args.config)
    if args.seeds:
        cfg = cfg.model_copy(update={"seeds": args.seeds})
    with tempfile.TemporaryDirectory() as d:
        run = Path(d) / "run"
        t0 = time.perf_counter()
        run_pipeline(cfg, run, RunOptions(workers=args.workers, progress_interval=30))
        wall = time.perf_counter() - t0
        rows, total, seconds, cpu = [], 0.0, {}, {}
        for s in DATA_STAGES:
            m = read_manifest(stage_dir(run, s))
            c = m.counts
            total += c.seconds
            seconds[s] = c.seconds
            cpu[s] = sum(r.cpu_seconds or 0.0 for r in m.items.values() if r.status == "done")
            rows.append([s, c.done, c.failed, f"{c.seconds:.1f}", f"{cpu[s]:.1f}"])
        ds = open_dataset(stage_dir(run, "write"))
        samples = len(ds)
        ds.close()
    print(text_table(["stage", "items done", "failed", "compute s (wall)", "CPU s"], rows))
    print(f"\nconfig {args.config.name}: {len(cfg.tasks)} tasks x {len(cfg.seed_list)} seeds")
    print(f"sum of stage compute times (sequential reference): {total:8.1f} s")
    print(f"pipelined wall time (Ray pools, incl. Ray start):  {wall:8.1f} s")
    print(f"speed-up: {total / wall:.2f}x   samples written: {samples} ({samples / wall:.2f} samples/s of wall time)")
    per_frame = {s: 1000 * seconds[s] / max(samples, 1) for s in ("render", "features")}
    cpu_frame = {s: 1000 * cpu[s] / max(samples, 1) for s in ("render", "features")}
    ratio = cpu_frame["features"] / cpu_frame["render"]
    print(f"per rendered frame, CPU: render {cpu_frame['render']:.1f} ms, features {cpu_frame['features']:.1f} ms "
          f"(features / render = {ratio:.2f}); wall: render {per_frame['render']:.1f} ms, features {per_frame['features']:.1f} ms")
    print(f"RESULT features_over_render={ratio:.3f} render_cpu_ms_per_frame={cpu_frame['render']:.1f} "
          f"features_cpu_ms_per_frame={cpu_frame['features']:.1f} render_ms_per_frame={per_frame['render']:.1f} "
          f"features_ms_per_frame={per_frame['features']:.1f} speedup={total / wall:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
