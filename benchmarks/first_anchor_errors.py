"""Where a trained policy's first-anchor error comes from: split by the size of the move, on the
validation and the training split, and whether it is sampling noise or a bias.

    python benchmarks/first_anchor_errors.py RUN [--models DIR] [--samples 192] [--draws 8]

Takes up to ``--samples`` decision states (``rest`` frames, evenly spread) of each split of the
run's dataset, predicts each one's anchors ``--draws`` times (different diffusion noise), and
prints the gripper error of the first anchor (cm, the worse arm) for a single draw and for the
mean of the draws, by the size of the true move (< 2 cm: close or open in place; 2-10 cm: down
to the grasp, lifts; > 10 cm: from home to the object, to the target), with the spread of the
draws around their mean. A mean-of-draws error close to the single-draw error says the error is a
bias, not sampling noise. With anchored offsets a second table splits the one-draw error by
whether the first gates pick the labelled anchor's object (``first_gate_hits``). The critical channel comes from the run's cached segmenter
probabilities (``models/policy/critical_prob-*.npy``, written by ``train policy``).
Last line: ``RESULT val_cm=X val_long_cm=Y train_cm=Z train_long_cm=W``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from anchordp3.dataset.reader import open_dataset  # noqa: E402
from anchordp3.dataset.torch_data import SplitDataset, collate_samples  # noqa: E402
from anchordp3.models.encoders import append_critical_probability  # noqa: E402
from anchordp3.schemas.stages import FRAME_KINDS  # noqa: E402
from anchordp3.schemas.state import ARMS, StateLayout  # noqa: E402
from anchordp3.schemas.training import model_task_ids  # noqa: E402
from anchordp3.stages.train_policy import POLICY_KEYS, load_policy  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402

BINS = ((0.0, 2.0, "< 2 cm"), (2.0, 10.0, "2-10 cm"), (10.0, 1e9, "> 10 cm"))


def gripper_cm(a: np.ndarray, b: np.ndarray, layout: StateLayout) -> np.ndarray:
    """The worse arm's end-effector distance between ``a`` and ``b`` (..., D), centimetres."""
    return 100 * np.max([np.linalg.norm(a[..., layout.ee_xyz(arm)] - b[..., layout.ee_xyz(arm)], axis=-1) for arm in ARMS], axis=0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--models", type=Path, default=None, help="models folder (default: RUN/models)")
    ap.add_argument("--samples", type=int, default=192)
    ap.add_argument("--draws", type=int, default=8)
    args = ap.parse_args()
    torch.set_num_threads(1)
    models = args.models or args.run / "models"
    data = open_dataset(args.run / "dataset")
    caches = sorted((args.run / "models" / "policy").glob("critical_prob-*.npy"))
    if not caches:
        raise SystemExit(f"{args.run / 'models' / 'policy'}: no cached segmenter probabilities; train the policy first")
    prob = torch.from_numpy(np.load(caches[0]))
    policy = load_policy(models / "policy" / "model.pt")
    layout = StateLayout.of_length(policy.config.action_dim)
    lut = torch.tensor(model_task_ids(data.tasks))
    rows, gate_rows, result = [], [], {}
    for split in ("validation", "train"):
        ds = SplitDataset(data, split, keys=POLICY_KEYS)
        kinds = np.array([data.sample(int(i), ())["kind"] for i in ds.samples])
        pos = np.flatnonzero(kinds == FRAME_KINDS.index("rest"))
        pick = sorted({int(pos[int(round(x))]) for x in np.linspace(0, len(pos) - 1, min(args.samples, len(pos)))})
        batch = collate_samples(ds.__getitems__(pick))
        obs = {"points": append_critical_probability(batch["points"], prob[batch["index"]].float()),
               "state": batch["state"], "task_id": lut[batch["task_id"]]}
        draws = np.stack([policy.predict(obs, generator=torch.Generator().manual_seed(d))[:, 0].numpy() for d in range(args.draws)])
        true, state = batch["anchors"][:, 0].numpy(), batch["state"].numpy()
        move, single, mean = gripper_cm(true, state, layout), gripper_cm(draws[0], true, layout), gripper_cm(draws.mean(0), true, layout)
        spread = gripper_cm(draws, draws.mean(0)[None], layout).mean(0)
        for lo, hi, name in BINS:
            sel = (move >= lo) & (move < hi)
            if sel.any():
                rows.append([split, name, int(sel.sum()), f"{single[sel].mean():.2f}", f"{mean[sel].mean():.2f}", f"{spread[sel].mean():.2f}"])
        rows.append([split, "all", len(move), f"{single.mean():.2f}", f"{mean.mean():.2f}", f"{spread.mean():.2f}"])
        hits = policy.first_gate_hits({**obs, "anchors": batch["anchors"]})
        if hits is not None:
            for name, sel in (("right", hits.numpy()), ("wrong", ~hits.numpy())):
                if sel.any():
                    gate_rows.append([split, name, int(sel.sum()), f"{single[sel].mean():.2f}", f"{np.median(single[sel]):.2f}"])
        key = "val" if split == "validation" else "train"
        result[f"{key}_cm"] = single.mean()
        result[f"{key}_long_cm"] = single[move >= 10].mean() if (move >= 10).any() else float("nan")
    print(text_table(["split", "true move", "states", "error, one draw (cm)", f"error, mean of {args.draws}", "draw spread"], rows))
    if gate_rows:
        print(text_table(["split", "first gates", "states", "error, one draw (cm)", "median"], gate_rows))
    print("RESULT " + " ".join(f"{k}={v:.2f}" for k, v in result.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
