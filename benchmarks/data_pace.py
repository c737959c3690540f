"""Episodes per CPU-hour of the data path after rollout (render + features + write): the earlier
path and today's side by side, on the same episodes, in one process.

    python benchmarks/data_pace.py [--config configs/recipe.yaml] [--tasks a,b] [--seeds 0-1]

The config is a run config or an experiment config (its ``run`` section). The episodes' rollouts
and frame plans are made once (not timed). Then every path renders, featurises and writes the same
kept episodes, the paths taking turns episode by episode so that the machine's drift falls on all
of them alike:

- ``earlier``: SAPIEN's ``default`` shader pack, the frames file deflated (zlib level 6) even when
  its images are dropped after featurising (``keep_frames: false``), and each planned step reached
  by replaying the recorded actions through the physics, as before the change;
- ``shader``: only the ``minimal`` shader pack changed;
- ``stored``: only the transient frames file stored without deflate;
- ``set``: only the planned steps set from the rollout's recorded PhysX states (no physics);
- ``today``: all three (the defaults).

The replaying paths read copies of the rollout files without their ``physx`` array, as rollouts
made before it was recorded.

Each path's first episode pays its shader compilation: it is timed apart (``start-up``) and left
out of the pace. Times are CPU seconds of this process, every thread (lavapipe renders on its own
threads), BLAS and OpenMP pinned to one thread as in the stages' one-core actors. The frames file
of a run with ``keep_frames: false`` is pruned once featurised, in every path as in the pipeline.
Last line: ``RESULT episodes_per_cpu_hour_old=… episodes_per_cpu_hour_new=… speedup=…
render_ms_old=… render_ms_new=… features_ms_old=… features_ms_new=…`` (ms: CPU per frame).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install

from anchordp3.schemas.dataset import ShardMember  # noqa: E402
from anchordp3.schemas.episode import parse_seeds  # noqa: E402
from anchordp3.schemas.run import RunConfig  # noqa: E402
from anchordp3.stages.anchors import load_plan, run_anchors  # noqa: E402
from anchordp3.stages.features import run_features  # noqa: E402
from anchordp3.stages.files import plan_file, save_npz  # noqa: E402
from anchordp3.stages.render import prune_frames, run_render  # noqa: E402
from anchordp3.stages.rollout import load_episode, rollout  # noqa: E402
from anchordp3.stages.write import write_shard  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PATHS = {  # name: (shader pack, deflate the transient frames file, replay the physics)
    "earlier": ("default", True, True),
    "shader": ("minimal", True, True),
    "stored": ("default", False, True),
    "set": ("default", True, False),
    "today": ("minimal", False, False),
}


@dataclass
class Pace:
    """CPU seconds one path spent, by stage, over the timed episodes."""

    render: float = 0.0
    features: float = 0.0
    write: float = 0.0
    frames: int = 0
    episodes: int = 0
    startup: float = 0.0
    members: list = field(default_factory=list)

    @property
    def per_episode(self) -> float:
        return (self.render + self.features + self.write) / max(self.episodes, 1)


def load_config(path: Path) -> RunConfig:
    """A run config, or the ``run`` section of an experiment config."""
    data = yaml.safe_load(path.read_text())
    return RunConfig.model_validate(data.get("run", data) if isinstance(data, dict) else data)


def with_path(cfg: RunConfig, shader: str) -> RunConfig:
    """``cfg`` rendering with ``shader``."""
    return cfg.model_copy(update={"cameras": cfg.cameras.model_copy(update={"shader": shader})})


def cpu() -> float:
    """CPU seconds of this process, every thread."""
    return time.process_time()


def without_physx(rollouts: Path, rec, out: Path) -> None:
    """A copy of an episode's rollout file without its recorded PhysX states (replayed)."""
    arrays = load_episode(rollouts, rec)
    del arrays["physx"]
    save_npz(out / rec.arrays, arrays)


def one_episode(cfg: RunConfig, deflate: bool, replay: bool, rec, base: Path, out: Path, pace: Pace, first: bool) -> None:
    """Render and featurise one kept episode along one path, adding its CPU time to ``pace``."""
    render_cfg = cfg.render.model_copy(update={"keep_frames": deflate or cfg.render.keep_frames})
    rollouts = base / ("rollout-replayed" if replay else "rollout")
    t0 = cpu()
    plan = base / "anchors" / plan_file(rec.task, rec.seed)
    rel = run_render(rec, rollouts, plan, out / "render", cfg.world(), render_cfg, cfg.anchors)
    t1 = cpu()
    run_features(rec.task, rec.seed, out / "render" / rel, out / "features", cfg.features)
    if not cfg.render.keep_frames:
        prune_frames(out / "render" / rel)
    t2 = cpu()
    if first:  # shader compilation and first-use costs
        pace.startup = t1 - t0
        return
    pace.render += t1 - t0
    pace.features += t2 - t1
    pace.frames += len(load_plan(plan))
    pace.episodes += 1
    pace.members.append((rec.task, rec.seed))


def write_all(cfg: RunConfig, out: Path, pace: Pace) -> None:
    """Write the path's timed episodes as one shard, timing it."""
    tasks = sorted({t for t, _ in pace.members})
    members = [ShardMember(task=t, seed=s, episode_index=i, task_id=tasks.index(t)) for i, (t, s) in enumerate(sorted(pace.members))]
    t0 = cpu()
    write_shard(0, members, out / "features", out / "write", cfg.write, tasks=tasks)
    pace.write = cpu() - t0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "recipe.yaml")
    parser.add_argument("--tasks", default=None, help="comma-separated tasks (default: the config's)")
    parser.add_argument("--seeds", default="0-2", help="seeds per task; the first kept episode of each path is its warm-up")
    parser.add_argument("--paths", default=",".join(PATHS), help=f"paths to time, among {', '.join(PATHS)}")
    args = parser.parse_args()
    cfg = load_config(args.config)
    tasks = args.tasks.split(",") if args.tasks else list(cfg.tasks)
    paths = args.paths.split(",")
    if "earlier" not in paths or "today" not in paths:
        raise SystemExit("--paths: needs at least earlier and today")
    with tempfile.TemporaryDirectory() as d, threadpool_limits(1):
        base = Path(d)
        kept = []
        for task in tasks:
            for seed in parse_seeds(args.seeds):
                rec = rollout(task, seed, cfg.world(), cfg.preset, base / "rollout")
                if rec.success:
                    run_anchors(rec, base / "rollout", base / "anchors", cfg.anchors)
                    without_physx(base / "rollout", rec, base / "rollout-replayed")
                    kept.append(rec)
        if len(kept) < 2:
            raise SystemExit("fewer than two kept episodes: give more seeds")
        print(f"{len(kept)} kept episodes ({', '.join(tasks)}); the first is each path's warm-up", file=sys.stderr)
        paces = {p: Pace() for p in paths}
        for i, rec in enumerate(kept):
            for p in paths:
                shader, deflate, replay = PATHS[p]
                one_episode(with_path(cfg, shader), deflate, replay, rec, base, base / p, paces[p], first=i == 0)
            print(f"  episode {i + 1}/{len(kept)} {rec.task}/{rec.seed:06d}", file=sys.stderr)
        for p in paths:
            write_all(cfg, base / p, paces[p])
    rows = []
    for p in paths:
        r = paces[p]
        ms = lambda s: f"{1000 * s / max(r.frames, 1):.1f}"  # noqa: E731
        rows.append([p, PATHS[p][0], "yes" if PATHS[p][1] or cfg.render.keep_frames else "no", "replay" if PATHS[p][2] else "set", r.episodes, r.frames, ms(r.render), ms(r.features), ms(r.write),
                     f"{r.per_episode:.2f}", f"{3600 / r.per_episode:.0f}", f"{r.startup:.1f}"])
    print(text_table(["path", "shader", "deflate", "steps", "episodes", "frames", "render ms/frame", "features ms/frame", "write ms/frame",
                      "CPU s/episode", "episodes/CPU-h", "start-up s"], rows))
    old, new = paces["earlier"], paces["today"]
    per_frame = lambda s, r: 1000 * s / max(r.frames, 1)  # noqa: E731
    print(f"RESULT episodes_per_cpu_hour_old={3600 / old.per_episode:.0f} episodes_per_cpu_hour_new={3600 / new.per_episode:.0f} "
          f"speedup={old.per_episode / new.per_episode:.2f} render_ms_old={per_frame(old.render, old):.1f} "
          f"render_ms_new={per_frame(new.render, new):.1f} features_ms_old={per_frame(old.features, old):.1f} "
          f"features_ms_new={per_frame(new.features, new):.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
