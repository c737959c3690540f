"""Do the object tokens keep their objects? Per task, over a run's expert frames, with as many
tokens as the task has critical objects (the most tokens can do).

    python benchmarks/token_identity.py RUN [--tokens K] [--z-weight 5]

The policy's object tokens (``models.objects.object_tokens``) are k-means clusters of the critical
points ordered by size. For every featurised frame of RUN (the simulator's labels as the critical
channel, so the segmenter plays no part), each token is matched to the critical object whose pose
(set from the rollout's recorded PhysX state of that step) lies nearest its centroid. Per task:

- ``split``: frames where some object has no token of its own (two tokens share an object, so
  another object is merged into a token with a third, or missing);
- ``churn``: consecutive expert frames of an episode where some token changed object;
- ``first token``: how often token 0 is the same object at the first frame, across episodes (the
  share of the most frequent one: 1.0 means token 0 always names the same object).

The run must mark only the task's objects critical (``render.include_robot: false``, as the
recipe). Last line: ``RESULT split=… churn=…`` over all frames.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from anchordp3.models.objects import object_tokens, token_centroids  # noqa: E402
from anchordp3.pipeline.graph import CONFIG_FILE  # noqa: E402
from anchordp3.pipeline.store import read_manifest  # noqa: E402
from anchordp3.pipeline.work import stage_dir  # noqa: E402
from anchordp3.schemas.records import RolloutInfo  # noqa: E402
from anchordp3.schemas.run import load_run_config  # noqa: E402
from anchordp3.schemas.state import StateLayout  # noqa: E402
from anchordp3.sim.episode import build  # noqa: E402
from anchordp3.stages.features import load_features  # noqa: E402
from anchordp3.stages.files import features_file  # noqa: E402
from anchordp3.stages.rollout import load_episode  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402


def object_positions(world, task, physx_row: np.ndarray) -> tuple[list[str], np.ndarray]:
    """The task's critical objects and the centres of their visual bounding boxes ``(O, 3)``
    metres at one recorded state (an entity's pose origin need not lie inside what is seen of it)."""
    import sapien

    world.unpack(physx_row.tobytes())
    names = task.critical_objects()
    entities = {**world.objects, **world.markers}
    centres = []
    for n in names:
        body = entities[n].find_component_by_type(sapien.render.RenderBodyComponent)
        lo, hi = np.asarray(body.compute_global_aabb_tight(), dtype=np.float64)
        centres.append((lo + hi) / 2)
    return names, np.array(centres)


def episode_matches(cfg, rec, run: Path, k: int | None, z_weight: float) -> tuple[list[tuple[int, ...]], list[str]]:
    """Per featurised frame (expert frames only, in step order), the object index each token is
    matched to (-1: an absent token); and the objects' names."""
    feats = load_features(stage_dir(run, "features") / features_file(rec.task, rec.seed))
    arrays = load_episode(stage_dir(run, "rollout"), rec)
    world, task = build(rec.task, rec.seed, cfg.world(), render=True)  # markers (a target spot) exist only with visuals
    names = task.critical_objects()
    k = k or len(names)
    layout = StateLayout.of_length(feats["state"].shape[1])
    points = torch.from_numpy(np.concatenate([feats["points"][..., :3], (feats["labels"][..., None] > 0).astype(np.float32)], -1))
    tokens = object_tokens(points, torch.from_numpy(feats["state"]), layout, k, z_weight=z_weight)
    centroids, present = token_centroids(tokens)
    out = []
    expert = feats["kind"] == 0
    for i, t in enumerate(feats["t"]):
        _, where = object_positions(world, task, arrays["physx"][int(t)])
        d = np.linalg.norm(centroids[i, :, None, :2].numpy() - where[None, :, :2], axis=-1)  # (k, O), table plane
        out.append(tuple(int(np.argmin(d[j])) if present[i, j] else -1 for j in range(k)))
    order = np.argsort(feats["t"], kind="stable")
    return [out[i] for i in order if expert[i]], names


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--tokens", type=int, default=None, help="tokens per frame (default: the task's critical objects)")
    ap.add_argument("--z-weight", type=float, default=5.0, help="the clustering's height weight (the recipe's 5)")
    args = ap.parse_args()
    cfg = load_run_config(args.run / CONFIG_FILE)
    if cfg.render.include_robot:
        raise SystemExit(f"{args.run}: its masks mark the robot critical too (render.include_robot): the tokens would "
                         "cover the arms; use a run made with include_robot: false, as the recipe's")
    records = [r.payload(RolloutInfo).record for r in read_manifest(stage_dir(args.run, "rollout")).items.values()
               if r.status == "done" and r.payload(RolloutInfo).kept]
    rows, all_split, all_churn = [], [0, 0], [0, 0]
    for task in cfg.tasks:
        split = churn = frames = pairs = 0
        firsts = Counter()
        objects = []
        for rec in (r for r in records if r.task == task):
            matches, objects = episode_matches(cfg, rec, args.run, args.tokens, args.z_weight)
            for m in matches:
                split += len({o for o in m if o >= 0}) < len(objects)
            churn += sum(a != b for a, b in zip(matches, matches[1:]))
            frames, pairs = frames + len(matches), pairs + max(len(matches) - 1, 0)
            if matches:
                firsts[objects[matches[0][0]] if matches[0][0] >= 0 else "-"] += 1
        episodes = sum(firsts.values())
        top = firsts.most_common(1)[0] if firsts else ("-", 0)
        rows.append([task, len(objects), args.tokens or len(objects), episodes, frames, f"{split / max(frames, 1):.2f}",
                     f"{churn / max(pairs, 1):.2f}", f"{top[1] / max(episodes, 1):.2f} ({top[0]})"])
        all_split = [all_split[0] + split, all_split[1] + frames]
        all_churn = [all_churn[0] + churn, all_churn[1] + pairs]
    print(text_table(["task", "objects", "tokens", "episodes", "frames", "split", "churn", "first token, most often"], rows))
    print(f"RESULT split={all_split[0] / max(all_split[1], 1):.3f} churn={all_churn[0] / max(all_churn[1], 1):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
