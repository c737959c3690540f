"""Episodes per CPU-hour of the data path after rollout (render + features + write): the earlier
code and today's side by side, on the same episodes, in one run.

    python benchmarks/data_pace.py [--config configs/recipe.yaml] [--tasks a,b] [--seeds 0-2] [--earlier 0737b7b]

The config is a run config or an experiment config (its ``run`` section). Every path runs in a
process of its own (its own renderer, its own code), makes the episodes' rollouts and frame plans
once (not timed), and then the paths take turns episode by episode, each rendering, featurising
and writing the same kept episodes, so that the machine's drift falls on all of them alike:

- ``earlier``: the package as it was at the ``--earlier`` revision (a temporary git worktree),
  with that code's defaults: its render, features and write code, its shader pack and threads;
- ``base``: today's code with the earlier settings: SAPIEN's ``default`` shader pack, the frames
  file deflated (zlib level 6) even when its images are dropped after featurising
  (``keep_frames: false``), each planned step reached by replaying the recorded actions;
- ``minimal``, ``lambert``: ``base`` with only the shader pack changed (SAPIEN's one-pass and
  composite ``minimal``, the project's one-pass ``lambert``);
- ``stored``: ``base`` with only the transient frames file stored without deflate;
- ``set``: ``base`` with only the planned steps set from the rollout's recorded PhysX states;
- ``today``: today's code and defaults (``lambert``, no deflate, set steps).

``earlier`` against ``base`` is what today's code alone gives (features, write and render code,
lavapipe on the calling thread), the four levers each against ``base`` what each setting gives.
The replaying paths read copies of the rollout files without their ``physx`` array, as rollouts
made before it was recorded.

Each path's first episode pays its shader compilation: it is timed apart (``start-up``) and left
out of the pace. Times are CPU seconds of each path's process, every thread (lavapipe may render
on its own threads), BLAS and OpenMP pinned to one thread as in the stages' one-core actors. The
frames file of a run with ``keep_frames: false`` is pruned once featurised, in every path as in
the pipeline. Last line: ``RESULT episodes_per_cpu_hour_old=… episodes_per_cpu_hour_new=…
speedup=… render_ms_old=… render_ms_new=… features_ms_old=… features_ms_new=…`` (ms: CPU per frame).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EARLIER = "0737b7b"  # the code before the data path was made faster
PATHS = {  # name: (code, shader pack, deflate the transient frames file, replay the physics); None: that code's default
    "earlier": ("earlier", None, None, None),
    "base": ("today", "default", True, True),
    "minimal": ("today", "minimal", True, True),
    "lambert": ("today", "lambert", True, True),
    "stored": ("today", "default", False, True),
    "set": ("today", "default", True, False),
    "today": ("today", None, None, None),
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

    @property
    def per_episode(self) -> float:
        return (self.render + self.features + self.write) / max(self.episodes, 1)

    def ms(self, seconds: float) -> float:
        """CPU milliseconds per frame."""
        return 1000 * seconds / max(self.frames, 1)


# ---------------------------------------------------------------- worker: one path, one process


def worker(args: argparse.Namespace) -> int:
    """Serve one path: make the rollouts and plans, then answer ``episode I`` and ``write``
    requests (JSON lines on stdin) with the CPU seconds they took (JSON lines on stdout)."""
    import yaml
    from threadpoolctl import threadpool_limits

    from anchordp3.schemas.dataset import ShardMember
    from anchordp3.schemas.episode import parse_seeds
    from anchordp3.schemas.run import RunConfig
    from anchordp3.stages.anchors import load_plan, run_anchors
    from anchordp3.stages.features import run_features
    from anchordp3.stages.files import plan_file, save_npz
    from anchordp3.stages.render import prune_frames, run_render
    from anchordp3.stages.rollout import load_episode, rollout
    from anchordp3.stages.write import write_shard

    data = yaml.safe_load(Path(args.config).read_text())
    cfg = RunConfig.model_validate(data.get("run", data) if isinstance(data, dict) else data)
    if args.shader:
        cfg = cfg.model_copy(update={"cameras": cfg.cameras.model_copy(update={"shader": args.shader})})
    deflate = cfg.render.keep_frames if args.deflate is None else args.deflate == "yes" or cfg.render.keep_frames
    render_cfg = cfg.render.model_copy(update={"keep_frames": deflate})
    base = Path(args.dir)
    tasks = args.tasks.split(",") if args.tasks else list(cfg.tasks)

    def reply(obj) -> None:
        print(json.dumps(obj), flush=True)

    with threadpool_limits(1):
        kept = []
        for task in tasks:
            for seed in parse_seeds(args.seeds):
                rec = rollout(task, seed, cfg.world(), cfg.preset, base / "rollout")
                if not rec.success:
                    continue
                run_anchors(rec, base / "rollout", base / "anchors", cfg.anchors)
                if args.replay == "yes":  # a copy of the rollout without its PhysX states: replayed
                    arrays = load_episode(base / "rollout", rec)
                    arrays.pop("physx", None)
                    save_npz(base / "rollout-replayed" / rec.arrays, arrays)
                kept.append(rec)
        rollouts = base / ("rollout-replayed" if args.replay == "yes" else "rollout")
        reply({"kept": [[r.task, r.seed] for r in kept]})
        done = []
        for line in sys.stdin:
            msg = json.loads(line)
            if "episode" in msg:
                rec = kept[msg["episode"]]
                plan = base / "anchors" / plan_file(rec.task, rec.seed)
                t0 = time.process_time()
                rel = run_render(rec, rollouts, plan, base / "render", cfg.world(), render_cfg, cfg.anchors)
                t1 = time.process_time()
                run_features(rec.task, rec.seed, base / "render" / rel, base / "features", cfg.features)
                if not cfg.render.keep_frames:
                    prune_frames(base / "render" / rel)
                t2 = time.process_time()
                if msg.get("timed"):
                    done.append((rec.task, rec.seed))
                reply({"render": t1 - t0, "features": t2 - t1, "frames": len(load_plan(plan))})
            elif "write" in msg:
                names = sorted({t for t, _ in done})
                members = [ShardMember(task=t, seed=s, episode_index=i, task_id=names.index(t)) for i, (t, s) in enumerate(sorted(done))]
                t0 = time.process_time()
                write_shard(0, members, base / "features", base / "write", cfg.write, tasks=names)
                reply({"write": time.process_time() - t0})
                return 0
    return 0


# ---------------------------------------------------------------- driver


class RunningPath:
    """A running path: its worker process and what it has spent."""

    def __init__(self, name: str, code_root: Path, args: argparse.Namespace, workdir: Path):
        _, shader, deflate, replay = PATHS[name]
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--config", str(args.config), "--seeds", args.seeds,
               "--dir", str(workdir / name)]
        if replay is not None:  # else that code's own way: set where its rollouts record the states, replayed where not
            cmd += ["--replay", "yes" if replay else "no"]
        if args.tasks:
            cmd += ["--tasks", args.tasks]
        if shader:
            cmd += ["--shader", shader]
        if deflate is not None:
            cmd += ["--deflate", "yes" if deflate else "no"]
        env = {**os.environ, "PYTHONPATH": str(code_root)}  # the path's own package before the installed one
        self.name, self.pace = name, Pace()
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=str(code_root))
        self.kept = self.ask(None)["kept"]

    def ask(self, msg: dict | None) -> dict:
        if msg is not None:
            self.proc.stdin.write(json.dumps(msg) + "\n")
            self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise SystemExit(f"path {self.name}: its worker stopped (exit {self.proc.wait()})")
        return json.loads(line)

    def episode(self, i: int, timed: bool) -> None:
        r = self.ask({"episode": i, "timed": timed})
        if not timed:
            self.pace.startup = r["render"] + r["features"]
            return
        self.pace.render += r["render"]
        self.pace.features += r["features"]
        self.pace.frames += r["frames"]
        self.pace.episodes += 1

    def finish(self) -> None:
        self.pace.write = self.ask({"write": True})["write"]
        self.proc.wait()


def earlier_worktree(rev: str, into: Path) -> Path:
    """A git worktree of the checkout at ``rev`` (removed by the caller's ``git worktree remove``)."""
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(into), rev], check=True, capture_output=True)
    return into


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "recipe.yaml")
    parser.add_argument("--tasks", default=None, help="comma-separated tasks (default: the config's)")
    parser.add_argument("--seeds", default="0-2", help="seeds per task; the first kept episode of each path is its warm-up")
    parser.add_argument("--paths", default=",".join(PATHS), help=f"paths to time, among {', '.join(PATHS)}")
    parser.add_argument("--earlier", default=EARLIER, help="git revision of the earlier code")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--dir", help=argparse.SUPPRESS)
    parser.add_argument("--shader", help=argparse.SUPPRESS)
    parser.add_argument("--deflate", choices=["yes", "no"], help=argparse.SUPPRESS)
    parser.add_argument("--replay", choices=["yes", "no"], help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        return worker(args)
    args.config = args.config.resolve()
    paths = args.paths.split(",")
    if "earlier" not in paths or "today" not in paths or not set(paths) <= set(PATHS):
        raise SystemExit(f"--paths: needs earlier and today, among {', '.join(PATHS)}")
    sys.path.insert(0, str(ROOT))
    from anchordp3.viz.table import text_table

    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        old = earlier_worktree(args.earlier, work / "earlier-code")
        try:
            running = {p: RunningPath(p, old if PATHS[p][0] == "earlier" else ROOT, args, work) for p in paths}
            kept = running["today"].kept
            for p, r in running.items():
                if r.kept != kept:
                    raise SystemExit(f"path {p} kept other episodes than today's: {r.kept} against {kept}")
            if len(kept) < 2:
                raise SystemExit("fewer than two kept episodes: give more seeds")
            print(f"{len(kept)} kept episodes; the first is each path's warm-up", file=sys.stderr)
            for i, (task, seed) in enumerate(kept):
                for r in running.values():
                    r.episode(i, timed=i > 0)
                print(f"  episode {i + 1}/{len(kept)} {task}/{seed:06d}", file=sys.stderr)
            for r in running.values():
                r.finish()
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], capture_output=True)
    rows = []
    for p, r in running.items():
        code, shader, deflate, replay = PATHS[p]
        pc = r.pace
        rows.append([p, f"{code} ({args.earlier})" if code == "earlier" else code, shader or "its default",
                     "its default" if deflate is None else "yes" if deflate else "no",
                     "its default" if replay is None else "replay" if replay else "set", pc.episodes, pc.frames,
                     f"{pc.ms(pc.render):.1f}", f"{pc.ms(pc.features):.1f}", f"{pc.ms(pc.write):.1f}",
                     f"{pc.per_episode:.2f}", f"{3600 / pc.per_episode:.0f}", f"{pc.startup:.1f}"])
    print(text_table(["path", "code", "shader", "deflate", "steps", "episodes", "frames", "render ms/frame", "features ms/frame",
                      "write ms/frame", "CPU s/episode", "episodes/CPU-h", "start-up s"], rows))
    o, n = running["earlier"].pace, running["today"].pace
    print(f"RESULT episodes_per_cpu_hour_old={3600 / o.per_episode:.0f} episodes_per_cpu_hour_new={3600 / n.per_episode:.0f} "
          f"speedup={o.per_episode / n.per_episode:.2f} render_ms_old={o.ms(o.render):.1f} render_ms_new={n.ms(n.render):.1f} "
          f"features_ms_old={o.ms(o.features):.1f} features_ms_new={n.ms(n.features):.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
