"""Why placements fail in closed loop: what the policy predicts once the object is carried over
its goal.

    python benchmarks/release_errors.py --models pretrained --tasks place_bell --seeds 0-29
    python benchmarks/release_errors.py --run-dir RUN --tasks place_mouse,place_bell --seeds 2000-2019

The companion of ``grasp_errors.py`` for the end of the single-arm place tasks. Runs closed-loop
episodes as ``anchordp3 eval`` does (one process, through poses) and watches every decision at
which the task arm's gripper is closed and the object is up (over ``LIFTED`` above where it
settled) within ``NEAR_CM`` of the goal in the table plane. At each such decision it logs the
object against the goal (``task.functional_point()``): its xy distance and the height of its
origin above the goal (cm, the expert releases it ``task.drop`` above), and the first predicted
anchor: the end effector's move (xy and z, cm), the gripper command (1 open) and the gate the
policy chose for it (``stay``: relative to the state; ``pair``: an object's offset from the held
one; ``object``: an object's offset from the end effector, the held object's own included;
``-``: no gating). ``--verbose`` prints every watched decision with the tokens' centroids, the
tool centre, the object and the goal (metres).

Each failed episode that carried the object near its goal gets one cause: ``never_released``
(it stayed closed there until the episode ended), ``released_off`` (opened with the object
outside the task's xy tolerance), ``released_high`` (opened over ``HIGH_CM`` above the goal),
else ``other``. Failures that never brought the object near the goal are ``not_near``.
Last line: ``RESULT success=K/N never_released=.. released_off=.. released_high=.. other=.. not_near=..``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from anchordp3.models.objects import token_centroids  # noqa: E402
from anchordp3.pipeline.evaluation import eval_run_config, models_folder  # noqa: E402
from anchordp3.schemas.evaluation import EvalOptions  # noqa: E402
from anchordp3.schemas.episode import parse_seeds  # noqa: E402
from anchordp3.schemas.state import ARMS  # noqa: E402
from anchordp3.schemas.tasks import task_id  # noqa: E402
from anchordp3.stages.evaluate import LIFTED, EvalModels, evaluate_episode  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402

NEAR_CM = 6.0
HIGH_CM = 4.0
CAUSES = ("never_released", "released_off", "released_high", "other", "not_near")


class ReleaseWatch:
    """Collects, per decision over the goal with the object held, the object's place and the
    first predicted anchor (module docstring)."""

    def __init__(self, models: EvalModels, task: str):
        self.models = models
        self.task_id = task_id(task)
        self.rows: list[dict] = []
        self.rest_z: float | None = None
        self.tolerance_cm = 0.0  # the task's xy success tolerance, read at the first decision

    def gate(self, points: np.ndarray, state: np.ndarray, arm: str) -> tuple[str, np.ndarray | None]:
        """The gate the policy picks for the first anchor of ``arm`` (stay, object, pair or -) and
        the object tokens' centroids ``(K, 3)`` metres (None without gating)."""
        policy = self.models.policy
        if policy.anchor_gates is None:
            return "-", None
        obs = self.models.observation(points, state, self.task_id)
        with torch.no_grad():
            cond, tokens = policy._condition(obs)
            cls = int(policy.gate_logits(cond)[0, 0, ARMS.index(arm)].argmax())
        centroids = token_centroids(tokens.float())[0][0].numpy()
        if cls == 0:
            return "stay", centroids
        if not policy.config.objects.held_offsets:
            return f"object {cls - 1}", centroids
        obj, held = divmod(cls - 1, policy.config.objects.tokens)
        return (f"object {obj}" if obj == held else f"pair {obj}-{held}"), centroids

    def __call__(self, ep, decision: int, points: np.ndarray, pred: np.ndarray) -> None:
        task, arm = ep.task, ep.task.arm
        p = np.asarray(ep.world.objects[task.noun].pose.p, dtype=np.float64)
        if self.rest_z is None:
            self.rest_z, self.tolerance_cm = float(p[2]), 100 * task.xy_tolerance
        state = ep.robot.state()
        g = ep.layout.gripper(arm)
        goal = task.functional_point()
        xy = 100 * float(np.linalg.norm(p[:2] - goal[:2]))
        if state[g] > 0.5 or p[2] - self.rest_z < LIFTED or xy > NEAR_CM:
            return
        ee = ep.layout.ee_xyz(arm)
        move = 100 * (pred[0][ee] - state[ee])
        gate, centroids = self.gate(points, state, arm)
        self.rows.append({"decision": decision, "xy_cm": xy, "up_cm": 100 * float(p[2] - goal[2]),
                          "move_xy_cm": float(np.hypot(move[0], move[1])), "move_z_cm": float(move[2]),
                          "gripper": float(pred[0][g]), "gate": gate.split()[0], "detail": " | ".join([
                              f"gate {gate}", "tokens " + ("-" if centroids is None else " ".join(_xyz(c) for c in centroids)),
                              f"tcp {_xyz(state[ee])}", f"object {_xyz(p)}", f"goal {_xyz(goal)}"])})


def _xyz(v: np.ndarray) -> str:
    return ",".join(f"{x:+.3f}" for x in v)


def cause(success: bool, w: ReleaseWatch) -> str | None:
    """The failure's cause (module docstring), None on success."""
    if success:
        return None
    if not w.rows:
        return "not_near"
    opened = [r for r in w.rows if r["gripper"] > 0.5]
    if not opened:
        return "never_released"
    first = opened[0]
    if first["xy_cm"] > w.tolerance_cm:
        return "released_off"
    if first["up_cm"] > HIGH_CM:
        return "released_high"
    return "other"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=None, help="a models folder or 'pretrained' (default: RUN/models)")
    ap.add_argument("--run-dir", type=Path, default=None)
    ap.add_argument("--tasks", default="place_bell")
    ap.add_argument("--seeds", default="0-29")
    ap.add_argument("--verbose", action="store_true", help="print every watched decision")
    args = ap.parse_args()
    torch.set_num_threads(1)
    opts = EvalOptions(models=args.models, tasks=tuple(args.tasks.split(",")))
    models_dir = models_folder(args.run_dir, args.models)
    cfg = eval_run_config(args.run_dir, models_dir, opts)
    models = EvalModels(models_dir)
    rows, counts, n_ok, n = [], {c: 0 for c in CAUSES}, 0, 0
    for task in opts.tasks:
        for seed in parse_seeds(args.seeds, "--seeds"):
            w = ReleaseWatch(models, task)
            rec = evaluate_episode(task, seed, models, cfg, watch=w)
            why = cause(rec.success, w)
            n, n_ok = n + 1, n_ok + rec.success
            if why:
                counts[why] += 1
            gates = {g: sum(r["gate"] == g for r in w.rows) for g in ("stay", "pair", "object")}
            last = w.rows[-1] if w.rows else {}
            row = [task, seed, "ok" if rec.success else rec.failure, why or "-", len(w.rows),
                   *(f"{last[k]:.1f}" if k in last else "-" for k in ("xy_cm", "up_cm", "move_xy_cm", "move_z_cm")),
                   f"{last['gripper']:.2f}" if last else "-", "/".join(str(gates[g]) for g in gates)]
            rows.append(row)
            if args.verbose:
                for r in w.rows:
                    print(f"  {task} {seed} d{r['decision']}: xy {r['xy_cm']:.1f} up {r['up_cm']:.1f} | move xy "
                          f"{r['move_xy_cm']:.1f} z {r['move_z_cm']:+.1f} grip {r['gripper']:.2f} {r['detail']}")
            print(" ".join(map(str, row)), flush=True)
    print(text_table(["task", "seed", "outcome", "cause", "held near", "xy cm", "up cm", "move xy cm", "move z cm",
                      "gripper", "stay/pair/object"], rows))
    print("(the last watched decision: the object against the goal, the first anchor's move, its gripper; "
          "gates over the watched decisions)")
    print(f"RESULT success={n_ok}/{n} " + " ".join(f"{c}={counts[c]}" for c in CAUSES))
    return 0


if __name__ == "__main__":
    sys.exit(main())
