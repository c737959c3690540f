"""Time the fast point-feature path against the whole-cloud reference on the same cloud.

    python benchmarks/features.py [--frames 4] [--n 4096] [--k 16] [--repeats 3]
    python benchmarks/features.py --synthetic [--points 150000]

By default the clouds are real: a kept stack_blocks_three episode is rolled out and rendered at
the default camera settings (4 views, 320×240), and each of the first ``--frames`` frames is
fused and cropped exactly as the features stage does.

Fast path: ``anchordp3.geometry.features.point_features`` (fpsample FPS, then normals/curvature
only where the samples need them). Reference: ``anchordp3.geometry.reference`` (KNN, eigh and
eigvalsh for every point, then open3d's legacy FPS started at the fast path's first pick). Runs
alternate so that load changes on the machine hit both alike; the best and median times are
printed with the speed-up, then the agreement checks (exit status 1 if they fail).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install

from anchordp3.geometry.features import point_features
from anchordp3.geometry.reference import (
    reference_features,
    reference_fps,
    synthetic_tabletop,
)

NORMAL_TOL = 1e-4
CURVATURE_TOL = 1e-3


def load_clouds(args: argparse.Namespace) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, str]]:
    """(points, colors, viewpoint, description) of each cloud to benchmark."""
    if args.synthetic:
        points, colors = synthetic_tabletop(args.points, seed=args.seed)
        return [(points, colors, np.asarray(args.viewpoint), f"synthetic tabletop, {len(points)} points")]
    from real_frames import rendered_frames

    from anchordp3.schemas.stages import FeaturesConfig
    from anchordp3.stages.features import frame_cloud

    frames = rendered_frames(args.task, args.seed)
    out = []
    for i in range(min(args.frames, len(frames["t"]))):
        c = frame_cloud(frames, i, FeaturesConfig())
        out.append((c.points, c.colors, frames["cam2world"][i, 0][:3, 3], f"{args.task} seed {args.seed} frame {i} (step {frames['t'][i]}), {len(c.points)} points"))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=4096, help="FPS samples")
    parser.add_argument("--k", type=int, default=16, help="neighbourhood size K")
    parser.add_argument("--synthetic", action="store_true", help="use the synthetic tabletop instead of rendered frames")
    parser.add_argument("--points", type=int, default=150_000, help="synthetic cloud size")
    parser.add_argument("--viewpoint", type=float, nargs=3, default=(-0.032, -0.45, 1.35), help="synthetic: normals face this point (metres)")
    parser.add_argument("--task", default="stack_blocks_three", help="task of the rendered episode")
    parser.add_argument("--frames", type=int, default=4, help="rendered frames to benchmark")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each implementation per cloud")
    parser.add_argument("--seed", type=int, default=0, help="episode seed (and FPS seed)")
    args = parser.parse_args()

    clouds = load_clouds(args)
    print(f"n={args.n}, K={args.k}, repeats={args.repeats} per cloud")
    p0, c0, v0, _ = clouds[0]
    point_features(p0, c0, args.n, args.k, v0, args.seed)  # warm-up (imports, caches)
    wall, cpu, errors = [], [], []  # wall/cpu columns: fast path, reference features, reference FPS
    for points, colors, viewpoint, source in clouds:
        print(f"cloud: {source}")
        for _ in range(args.repeats):
            stamps = [(time.perf_counter(), time.process_time())]
            idx, feats = point_features(points, colors, args.n, args.k, viewpoint, args.seed)
            stamps.append((time.perf_counter(), time.process_time()))
            ref_all = reference_features(points, colors, args.k, viewpoint)
            stamps.append((time.perf_counter(), time.process_time()))
            ref_idx = reference_fps(points, min(args.n, len(points)), int(idx[0]))
            stamps.append((time.perf_counter(), time.process_time()))
            w, c = np.diff(np.array(stamps), axis=0).T
            wall.append(w)
            cpu.append(c)
        ref = ref_all[idx]
        errors.append((np.array_equal(np.unique(idx), ref_idx), np.abs(feats[:, :6] - ref[:, :6]).max(),
                       np.minimum(np.abs(feats[:, 6:9] - ref[:, 6:9]), np.abs(feats[:, 6:9] + ref[:, 6:9])).max(),
                       np.abs(feats[:, 9:] - ref[:, 9:]).max()))
    wall, cpu = np.array(wall), np.array(cpu)
    fast, ref = wall[:, 0], wall[:, 1] + wall[:, 2]

    def row(label: str, w: np.ndarray, c: np.ndarray) -> None:
        print(f"{label:34s} wall best {1e3 * w.min():7.1f} ms  median {1e3 * np.median(w):7.1f} ms   cpu median {1e3 * np.median(c):7.1f} ms")

    row("fast path (FPS + local features)", fast, cpu[:, 0])
    row("reference (all-point features)", wall[:, 1], cpu[:, 1])
    row("reference (open3d FPS)", wall[:, 2], cpu[:, 2])
    row("reference total", ref, cpu[:, 1] + cpu[:, 2])
    print(f"speed-up (wall): {ref.min() / fast.min():.1f}x best   {np.median(ref) / np.median(fast):.1f}x median")

    same, xyzrgb_err, normal_err, curvature_err = (max(e[i] for e in errors) for i in range(4))
    # Informational: fpsample (float32) and open3d (float64) can split a near-tie differently.
    print(f"FPS picks identical to open3d's:  {all(e[0] for e in errors)}")
    print(f"max |xyz, rgb error|:             {xyzrgb_err:.2e}")
    print(f"max |normal error| (up to sign):  {normal_err:.2e}  (tolerance {NORMAL_TOL:g})")
    print(f"max |curvature error|:            {curvature_err:.2e}  (tolerance {CURVATURE_TOL:g})")
    ok = xyzrgb_err < 1e-6 and normal_err <= NORMAL_TOL and curvature_err <= CURVATURE_TOL
    print("agreement: OK" if ok else "agreement: FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
