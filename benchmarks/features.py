"""Time the fast point-feature path against the whole-cloud reference on the same cloud.

    python benchmarks/features.py [--points 150000] [--n 4096] [--k 16] [--npz PATH] [--repeats 5]

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


def load_cloud(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray, str]:
    """The cloud to benchmark: ``points`` / ``colors`` from --npz, else the synthetic tabletop."""
    if args.npz is None:
        points, colors = synthetic_tabletop(args.points, seed=args.seed)
        return points, colors, f"synthetic tabletop, {len(points)} points"
    with np.load(args.npz) as data:
        points = np.asarray(data["points"], dtype=np.float32)
        colors = np.asarray(data["colors"])
    colors = colors.astype(np.float32) / 255.0 if np.issubdtype(colors.dtype, np.integer) else colors.astype(np.float32)
    return points, colors, f"{args.npz}, {len(points)} points"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=150_000, help="synthetic cloud size")
    parser.add_argument("--n", type=int, default=4096, help="FPS samples")
    parser.add_argument("--k", type=int, default=16, help="neighbourhood size K")
    parser.add_argument("--npz", type=Path, default=None, help="file with 'points' (M, 3) and 'colors' (M, 3)")
    parser.add_argument("--viewpoint", type=float, nargs=3, default=(-0.032, -0.45, 1.35), help="normals face this point (metres)")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of each implementation")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    points, colors, source = load_cloud(args)
    viewpoint = np.asarray(args.viewpoint)
    print(f"cloud: {source}; n={args.n}, K={args.k}, repeats={args.repeats}")

    point_features(points, colors, args.n, args.k, viewpoint, args.seed)  # warm-up (imports, caches)
    wall = np.zeros((args.repeats, 3))  # columns: fast path, reference features, reference FPS
    cpu = np.zeros((args.repeats, 3))  # process CPU time, all threads
    for r in range(args.repeats):
        stamps = [(time.perf_counter(), time.process_time())]
        idx, feats = point_features(points, colors, args.n, args.k, viewpoint, args.seed)
        stamps.append((time.perf_counter(), time.process_time()))
        ref_all = reference_features(points, colors, args.k, viewpoint)
        stamps.append((time.perf_counter(), time.process_time()))
        ref_idx = reference_fps(points, min(args.n, len(points)), int(idx[0]))
        stamps.append((time.perf_counter(), time.process_time()))
        wall[r], cpu[r] = np.diff(np.array(stamps), axis=0).T
    fast, ref = wall[:, 0], wall[:, 1] + wall[:, 2]

    def row(label: str, w: np.ndarray, c: np.ndarray) -> None:
        print(f"{label:34s} wall best {1e3 * w.min():7.1f} ms  median {1e3 * np.median(w):7.1f} ms   cpu median {1e3 * np.median(c):7.1f} ms")

    row("fast path (FPS + local features)", fast, cpu[:, 0])
    row("reference (all-point features)", wall[:, 1], cpu[:, 1])
    row("reference (open3d FPS)", wall[:, 2], cpu[:, 2])
    row("reference total", ref, cpu[:, 1] + cpu[:, 2])
    print(f"speed-up (wall): {ref.min() / fast.min():.1f}x best   {np.median(ref) / np.median(fast):.1f}x median")

    ref = ref_all[idx]
    same_samples = np.array_equal(np.unique(idx), ref_idx)
    xyzrgb_err = np.abs(feats[:, :6] - ref[:, :6]).max()
    normal_err = np.abs(feats[:, 6:9] - ref[:, 6:9]).max()
    curvature_err = np.abs(feats[:, 9:] - ref[:, 9:]).max()
    # Informational: fpsample (float32) and open3d (float64) can split a near-tie differently.
    print(f"FPS picks identical to open3d's:  {same_samples}")
    print(f"max |xyz, rgb error|:             {xyzrgb_err:.2e}")
    print(f"max |normal error|:               {normal_err:.2e}  (tolerance {NORMAL_TOL:g})")
    print(f"max |curvature error|:            {curvature_err:.2e}  (tolerance {CURVATURE_TOL:g})")
    ok = xyzrgb_err < 1e-6 and normal_err <= NORMAL_TOL and curvature_err <= CURVATURE_TOL
    print("agreement: OK" if ok else "agreement: FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
