"""Does the critical channel show the task object where the policy must find it?

    python benchmarks/first_decision_objects.py RUN

At each episode's first decision (the robot at home, the first rest frame), per split of the
run's dataset, with the simulator's labels as reference:

- the segmenter's recall of the object (the smaller of the two critical clusters; the larger is
  the target, e.g. the scale), the share of scenes where it misses most of the object (recall
  < 0.5), and the points it marks wrongly;
- how well the first anchor's gripper position can be read off the critical points: a per-task
  linear fit from the two critical-object tokens (``models/objects.py``) to it, fitted on the
  training split and scored on validation, with the simulator's labels and with the segmenter's
  probabilities (cm).

The segmenter's probabilities are the run's cache (``models/policy/critical_prob-*.npy``, written
by ``train policy``), or with ``--segmenter PATH`` (a ``model.pt``) those of any segmenter, computed
here at the first decisions only, so two segmenters can be compared on the same held-out scenes.
Meant for the single-arm place tasks (two critical objects).
Last line: ``RESULT val_object_recall=X val_missed_share=Y fit_cm_labels=Z fit_cm_segmenter=W``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from anchordp3.dataset.reader import open_dataset  # noqa: E402
from anchordp3.models.objects import cluster_critical_points, object_tokens  # noqa: E402
from anchordp3.schemas.stages import FRAME_KINDS  # noqa: E402
from anchordp3.schemas.state import ARMS, StateLayout  # noqa: E402
from anchordp3.stages.train_segmenter import load_segmenter  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402

LAYOUT = StateLayout()


def first_decisions(data, split: str) -> list[int]:
    """Sample indices of each episode's first rest frame in ``split``."""
    first: dict[int, tuple[int, int]] = {}
    for i in data.indices(split, None):
        s = data.sample(int(i), ())
        if s["kind"] == FRAME_KINDS.index("rest"):
            ep = int(s["episode_index"])
            if ep not in first or s["timestep"] < first[ep][0]:
                first[ep] = (int(s["timestep"]), int(i))
    return sorted(i for _, i in first.values())


def collect(data, prob: Callable[[int, np.ndarray], np.ndarray], split: str) -> dict[str, np.ndarray]:
    """Per first decision: object recall, wrong points, tokens (labels / segmenter), target, task.
    prob: (sample index, points (N, 11)) -> the segmenter's critical probability (N,)."""
    rows = {k: [] for k in ("recall", "wrong", "tok_label", "tok_seg", "target", "task")}
    for i in first_decisions(data, split):
        s = data.sample(i, ("points", "labels", "state", "anchors"))
        p = prob(i, s["points"])
        label, seg = s["labels"] > 0, p > 0.5
        assign, _ = cluster_critical_points(torch.from_numpy(s["points"][None, :, :3]), torch.from_numpy(label[None]), 2)
        obj = label & (assign[0].numpy() == 1)
        rows["recall"].append((seg & obj).sum() / max(obj.sum(), 1))
        rows["wrong"].append((seg & ~label).sum())
        for key, channel in (("tok_label", label), ("tok_seg", p)):
            pts = np.concatenate([s["points"], np.asarray(channel, np.float32)[:, None]], axis=1)
            rows[key].append(object_tokens(torch.from_numpy(pts[None]), torch.from_numpy(s["state"][None]), LAYOUT, 2).flatten().numpy())
        moves = [np.linalg.norm(s["anchors"][0, LAYOUT.ee_xyz(a)] - s["state"][LAYOUT.ee_xyz(a)]) for a in ARMS]
        rows["target"].append(s["anchors"][0, LAYOUT.ee_xyz(ARMS[int(np.argmax(moves))])])
        rows["task"].append(int(s["task_id"]))
    return {k: np.asarray(v) for k, v in rows.items()}


def cached_probabilities(run: Path) -> Callable[[int, np.ndarray], np.ndarray]:
    """The run's cache of the segmenter's probabilities, written by ``train policy``."""
    caches = sorted((run / "models" / "policy").glob("critical_prob-*.npy"))
    if not caches:
        raise SystemExit(f"{run / 'models' / 'policy'}: no cached segmenter probabilities; train the policy first "
                         "(or give --segmenter)")
    prob = np.load(caches[0]).astype(np.float32)
    return lambda i, _points: prob[i]


def segmenter_probabilities(path: Path) -> Callable[[int, np.ndarray], np.ndarray]:
    """The probabilities of the segmenter in ``path`` (a ``model.pt``), computed per sample."""
    model = load_segmenter(path)

    @torch.no_grad()
    def prob(_i: int, points: np.ndarray) -> np.ndarray:
        return model.probabilities(torch.from_numpy(np.asarray(points, np.float32))[None])[0].numpy()
    return prob


def fit_cm(train: dict, val: dict, key: str, task: int) -> float:
    """Validation error (cm) of a least-squares fit tokens -> first gripper position for ``task``."""
    a, b = train["task"] == task, val["task"] == task
    A = np.c_[train[key][a], np.ones(a.sum())]
    w = np.linalg.lstsq(A, train["target"][a], rcond=1e-6)[0]
    return float(100 * np.linalg.norm(np.c_[val[key][b], np.ones(b.sum())] @ w - val["target"][b], axis=1).mean())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--segmenter", type=Path, default=None, help="a segmenter model.pt (default: the run's cached probabilities)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    data = open_dataset(args.run / "dataset")
    prob = segmenter_probabilities(args.segmenter) if args.segmenter else cached_probabilities(args.run)
    got = {split: collect(data, prob, split) for split in ("train", "validation")}
    rows = [[split, len(g["recall"]), f"{g['recall'].mean():.2f}", f"{(g['recall'] < 0.5).mean():.0%}", f"{g['wrong'].mean():.1f}"]
            for split, g in got.items()]
    print(text_table(["split", "first decisions", "object recall", "object mostly missed", "wrong points"], rows))
    val = got["validation"]
    per_task = [[name, int((val["task"] == t).sum()), f"{val['recall'][val['task'] == t].mean():.2f}",
                 int((val["recall"][val["task"] == t] < 0.6).sum()), f"{val['wrong'][val['task'] == t].mean():.1f}"]
                for t, name in enumerate(data.tasks)]
    print()
    print(text_table(["task (validation)", "first decisions", "object recall", "recall < 0.6", "wrong points"], per_task))
    fits = []
    for t, name in enumerate(data.tasks):
        fits.append([name, f"{fit_cm(got['train'], got['validation'], 'tok_label', t):.2f}",
                     f"{fit_cm(got['train'], got['validation'], 'tok_seg', t):.2f}"])
    print()
    print(text_table(["task", "fit from tokens, labels (cm)", "fit from tokens, segmenter (cm)"], fits))
    lab = np.mean([float(r[1]) for r in fits])
    seg = np.mean([float(r[2]) for r in fits])
    print(f"RESULT val_object_recall={val['recall'].mean():.3f} val_missed_share={(val['recall'] < 0.5).mean():.3f} "
          f"fit_cm_labels={lab:.2f} fit_cm_segmenter={seg:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
