"""One closed-loop decision on the CPU, one thread: where its time goes, today's kernels against
PyTorch's reference ones, side by side in one run.

    python benchmarks/decision_latency.py [--models pretrained] [--task place_mouse] [--seed 2000] [--reps 30] [--shader lambert]

Builds the evaluation scene of ``(task, seed)`` with the models' own data config, renders one
observation, computes its point features, and then times, as medians over ``--reps`` calls with
``torch.set_num_threads(1)``: the render, the features, the segmenter, the policy (encoders and
every DDIM step of the U-Net), and the two together (``policy_ms``, the part a decision budget of 50 ms bounds),
once with the models' fast CPU kernels (``models.kernels``) and once with ``reference_kernels()``
(PyTorch's own convolution and the torch FPS loop). Checks that both give the same anchors.
Prints a table, a profile of the top operators of one fast decision, and a last line
``RESULT policy_ms=X reference_ms=Y speedup=Z decision_ms=W``.
"""

from __future__ import annotations

import time

T_START = time.perf_counter()  # before the heavy imports: a worker's start-up includes them

import argparse  # noqa: E402
import contextlib  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from anchordp3.models.kernels import reference_kernels  # noqa: E402
from anchordp3.pipeline.evaluation import eval_run_config, models_folder  # noqa: E402
from anchordp3.schemas.evaluation import EvalOptions  # noqa: E402
from anchordp3.schemas.tasks import task_id  # noqa: E402
from anchordp3.sim.closed_loop import EvalEpisode  # noqa: E402
from anchordp3.stages.evaluate import EvalModels, frames_dict  # noqa: E402
from anchordp3.stages.features import frame_features  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402


def median_ms(fn, reps: int) -> float:
    """Median wall time of ``fn()`` over ``reps`` calls after one warm-up, milliseconds."""
    fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default="pretrained", help="models folder, or 'pretrained'")
    ap.add_argument("--task", default="place_mouse")
    ap.add_argument("--seed", type=int, default=2000)
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--shader", default=None, help="render with this shader pack (default: the models' data config's)")
    ap.add_argument("--ddim-steps", default="", help="also time these DDIM step counts, e.g. 5,3 (fast kernels)")
    ap.add_argument("--samples", default="", help="also time the medoid of these sample counts per decision, e.g. 4,8")
    args = ap.parse_args()
    torch.set_num_threads(1)
    models_dir = models_folder(None, args.models)
    cfg = eval_run_config(None, models_dir, EvalOptions(tasks=(args.task,)))
    if args.shader:
        cfg = cfg.model_copy(update={"cameras": cfg.cameras.model_copy(update={"shader": args.shader})})
    t0 = time.perf_counter()
    models = EvalModels(models_dir)
    t1 = time.perf_counter()
    ep = EvalEpisode(args.task, args.seed, cfg.world())
    obs = ep.observe()
    t2 = time.perf_counter()
    startup = {"imports": 1000 * (t0 - T_START), "models": 1000 * (t1 - t0), "first observation": 1000 * (t2 - t1)}
    points, _ = frame_features(frames_dict(obs), 0, cfg.features, 1)
    task = task_id(args.task)
    pts = torch.from_numpy(points)[None]

    def segment():
        with torch.inference_mode():  # as ``EvalModels.anchors`` decides
            return models.segmenter.probabilities(pts)

    decide = lambda: models.anchors(points, obs.state, task, 1)  # noqa: E731  segmenter + policy, DDIM included
    rows, fast, ref = [], {}, {}
    fast["render"] = median_ms(ep.observe, max(3, args.reps // 5))
    fast["features"] = median_ms(lambda: frame_features(frames_dict(obs), 0, cfg.features, 1), args.reps)
    for store, ctx in ((fast, contextlib.nullcontext), (ref, reference_kernels)):
        with ctx():
            store["segmenter"] = median_ms(segment, args.reps)
            store["segmenter + policy"] = median_ms(decide, args.reps)
            store["anchors"] = decide()
    same = float(np.abs(fast["anchors"] - ref["anchors"]).max())
    for k, ms in startup.items():
        rows.append([f"start-up: {k}", f"{ms:.0f}", "-", "-"])
    for k in ("render", "features"):
        rows.append([k, f"{fast[k]:.1f}", "-", "-"])
    for k in ("segmenter", "segmenter + policy"):
        rows.append([k, f"{fast[k]:.1f}", f"{ref[k]:.1f}", f"{ref[k] / fast[k]:.2f}x"])
    for steps in [int(x) for x in args.ddim_steps.split(",") if x.strip()]:
        models.ddim_steps = steps
        ms = median_ms(decide, args.reps)
        rows.append([f"segmenter + policy, {steps} DDIM steps", f"{ms:.1f}", "-", "-"])
    models.ddim_steps = None
    drawn = models.samples  # the evaluation's default, the one the rows above time
    for k in [int(x) for x in args.samples.split(",") if x.strip()]:
        models.samples = k
        ms = median_ms(decide, args.reps)
        rows.append([f"segmenter + policy, medoid of {k} samples", f"{ms:.1f}", "-", "-"])
    models.samples = drawn
    full = fast["render"] + fast["features"] + fast["segmenter + policy"]
    rows.append(["full decision (render + features + models)", f"{full:.1f}", "-", "-"])
    print(text_table(["one thread, median ms", "fast kernels", "reference kernels", "speed-up"], rows))
    print(f"\nlargest anchor difference fast vs reference: {same:.2e} (data units); DDIM steps "
          f"{models.policy.config.scheduler.num_inference_steps}; draws per decision {drawn}; models {models_dir}")
    from torch.profiler import ProfilerActivity, profile
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        decide()
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=10))
    print(f"RESULT policy_ms={fast['segmenter + policy']:.1f} reference_ms={ref['segmenter + policy']:.1f} "
          f"speedup={ref['segmenter + policy'] / fast['segmenter + policy']:.2f} decision_ms={full:.1f} "
          f"render_ms={fast['render']:.1f} startup_ms={sum(startup.values()):.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
