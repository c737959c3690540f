"""Where a frame's features time goes, against the renderer's, and the floor the exact nearest
neighbours set.

    python benchmarks/features_floor.py RUN_DIR [--items 8]

RUN_DIR is a run whose render stage is complete, e.g. ``anchordp3 run configs/demo.yaml --run-dir
RUN_DIR --stages rollout,anchors,render``. Render: the stage's CPU seconds per rendered frame, from
its manifest (every thread of the renderer's worker). Features: the first ``--items`` episodes run
through the stage's own ``run_features`` on this one thread, timed, then again under cProfile, with the run's
features config; the table gives each step's time per frame. The exact path must answer two
batches of nearest-neighbour queries per frame (the samples', then their neighbours'); those
recorded queries are replayed, tree build included, with pykdtree and with scipy's cKDTree: the
faster one's time per frame is the kNN floor. The floor of the whole stage adds what the method
and the stage contract also do in compiled code, however the numpy glue around them is written:
FPS (fpsample), reading the frames file and writing the features file (zlib). Everything runs on
one thread (BLAS and OpenMP pinned), as in the stage's one-core actor. Last line: ``RESULT
features_over_render=X floor_over_render=Y knn_floor_over_render=Z render_cpu_ms_per_frame=R
features_cpu_ms_per_frame=F floor_ms_per_frame=G knn_ms_per_frame=Q``.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install

import anchordp3.geometry.features as geometry_features  # noqa: E402
from anchordp3.pipeline.store import read_manifest  # noqa: E402
from anchordp3.pipeline.work import stage_dir  # noqa: E402
from anchordp3.schemas.run import load_run_config  # noqa: E402
from anchordp3.schemas.stages import FeaturesConfig  # noqa: E402
from anchordp3.stages.features import run_features  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402

# (label, function name as cProfile names it): the stage's steps, outermost first.
STEPS = (
    ("load frames file", "load_frames"),
    ("back-project views", "backproject"),
    ("fuse views", "fuse_views"),
    ("table top height", "table_top_height"),
    ("FPS", "farthest_point_sample"),
    ("kNN tree build", "__init__"),
    ("kNN queries (tree)", "query"),
    ("kNN ties and order", "knn"),
    ("normals (PCA)", "normals_pca"),
    ("curvature", "curvature_features"),
    ("save features file", "save_npz"),
)


StageTree = geometry_features.NeighbourTree
QUERIES: list[tuple[np.ndarray, np.ndarray, int]] = []  # (points, queries, k) of each batch the stage asked


class RecordingTree(StageTree):
    """The stage's tree, noting every query batch in ``QUERIES`` for the replay."""

    def query(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        QUERIES.append((self.points, np.array(queries), k))
        return super().query(queries, k)


def render_cost(run: Path) -> tuple[float, list[tuple[str, Path, int]]]:
    """The render stage's CPU seconds over all its done items, and their ``(item, frames file,
    frames)``."""
    folder = stage_dir(run, "render")
    manifest = read_manifest(folder)
    if manifest is None or not manifest.items:
        raise SystemExit(f"{folder}: no render manifest; run the render stage first")
    cpu, files = 0.0, []
    for rec in sorted(manifest.items.values(), key=lambda r: r.item):
        if rec.status != "done" or rec.cpu_seconds is None:
            continue
        path = folder / rec.output
        with np.load(path, allow_pickle=False) as z:
            files.append((rec.item, path, len(z["t"])))
        cpu += rec.cpu_seconds
    return cpu, files


def step_times(stats: pstats.Stats) -> dict[str, float]:
    """Cumulative seconds of each step in ``STEPS`` (the tree's ``__init__`` and ``query`` only
    from the features module)."""
    out = dict.fromkeys((name for _, name in STEPS), 0.0)
    for (file, _, func), (_, _, _, cum, _) in stats.stats.items():  # type: ignore[attr-defined]
        if func in ("__init__", "query") and not file.endswith("geometry/features.py"):
            continue
        if func in out:
            out[func] += cum
    return out


def replay(calls: list[tuple[np.ndarray, np.ndarray, int]], scipy: bool) -> float:
    """CPU seconds of the recorded query batches, one tree per cloud (built once, as the stage does)."""
    c0, tree, last = time.process_time(), None, None
    for points, queries, k in calls:
        if points is not last:
            tree, last = StageTree(points, scipy=scipy), points
        tree.query(queries, k)
    return time.process_time() - c0


def run_episodes(files: list[tuple[str, Path, int]], cfg: FeaturesConfig, profile: cProfile.Profile | None) -> float:
    """Run the features stage on each ``(item, frames file, frames)`` into a scratch folder, under
    ``profile`` when given; returns the CPU seconds (this process)."""
    with tempfile.TemporaryDirectory() as out:
        c0 = time.process_time()
        for item, path, _ in files:
            task, seed = item.split("/")
            if profile is not None:
                profile.enable()
            run_features(task, int(seed), path, Path(out), cfg)
            if profile is not None:
                profile.disable()
        return time.process_time() - c0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path, help="a run directory whose render stage is complete")
    parser.add_argument("--items", type=int, default=8, help="episodes to profile (the first ones by item id)")
    args = parser.parse_args()
    cfg = load_run_config(args.run_dir / "config.yaml")
    render_cpu, files = render_cost(args.run_dir)
    render_frames = sum(n for _, _, n in files)
    render_ms = 1000 * render_cpu / render_frames

    with threadpool_limits(limits=1):
        return measure(args, cfg.features, files, render_ms, render_frames)


def measure(args: argparse.Namespace, cfg: FeaturesConfig, files: list[tuple[str, Path, int]], render_ms: float, render_frames: int) -> int:
    """The features side of ``main``, printed (see the module docstring)."""
    chosen = files[: args.items]
    frames = sum(n for _, _, n in chosen)
    features_ms = 1000 * run_episodes(chosen, cfg, None) / frames
    profile = cProfile.Profile()
    geometry_features.NeighbourTree = RecordingTree  # the stage's functions look it up at call time
    try:
        run_episodes(chosen, cfg, profile)
    finally:
        geometry_features.NeighbourTree = StageTree
    steps = step_times(pstats.Stats(profile))
    knn_ms = {lib: 1000 * replay(QUERIES, lib == "scipy") / frames for lib in ("pykdtree", "scipy")}
    knn_floor = min(knn_ms.values())
    floor_ms = knn_floor + 1000 * sum(steps[name] for name in ("farthest_point_sample", "load_frames", "save_npz")) / frames

    rows = [[label, f"{1000 * steps[name] / frames:.2f}"] for label, name in STEPS]
    rows.append(["(kNN steps include the tree's)", ""])
    print(text_table(["features step (cProfile, cumulative)", "ms / frame"], rows))
    queries = sum(len(q) for _, q, _ in QUERIES) / frames
    print(f"\n{frames} frames of {len(chosen)} episodes; n_points {cfg.n_points}, K {cfg.k}; "
          f"{queries:.0f} exact kNN queries per frame")
    print(f"per frame, CPU: render {render_ms:.1f} ms (all {render_frames} frames), features {features_ms:.1f} ms (unprofiled)")
    print(f"kNN queries alone, tree build included: pykdtree {knn_ms['pykdtree']:.1f} ms, scipy {knn_ms['scipy']:.1f} ms "
          f"-> {knn_floor / render_ms:.2f} of the render time")
    print(f"floor (kNN + FPS + frames file read + features file write): {floor_ms:.1f} ms = {floor_ms / render_ms:.2f} of the render time")
    print(f"RESULT features_over_render={features_ms / render_ms:.3f} floor_over_render={floor_ms / render_ms:.3f} "
          f"knn_floor_over_render={knn_floor / render_ms:.3f} render_cpu_ms_per_frame={render_ms:.1f} "
          f"features_cpu_ms_per_frame={features_ms:.1f} floor_ms_per_frame={floor_ms:.1f} knn_ms_per_frame={knn_floor:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
