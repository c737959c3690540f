"""Why grasps fail in closed loop: where the gripper is, in the object's frame, when the policy
closes it.

    python benchmarks/grasp_errors.py --models pretrained --tasks place_mouse --seeds 2000-2039
    python benchmarks/grasp_errors.py --run-dir RUN --tasks place_mouse,place_stapler --seeds 2000-2019

Runs closed-loop episodes of the single-arm place tasks as ``anchordp3 eval`` does (one process,
through poses) and watches every decision (``stages.evaluate.evaluate_episode(watch=...)``):

- at the first decision, whether the critical-object tokens found the object: the distance in the
  table plane from the object to the nearest of the two clusters' centroids (cm); over 5 cm means
  the segmenter marked something else (a distractor) and the object was merged into another
  cluster;
- at the first decision where the task arm's gripper is commanded from open to closed, the tool
  centre point against the expert's grasp pose of the object as it lies then
  (``task.grasp_pose()``): along the object's length and across it, and the height (cm), and the
  wrist's yaw error (degrees, modulo 180 for an elongated object, 0 for a round one).

Each failed episode gets one cause, the first that holds: ``token`` (the tokens missed the
object), ``no_close`` (never closed), ``far`` (closed over 3 cm from the grasp point in the table
plane), ``yaw`` (the wrist over 20 degrees off), else ``other`` (dropped, placed wrong, ...).
Last line: ``RESULT success=K/N token=.. far=.. yaw=.. other=.. no_close=..`` (failures by cause).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from anchordp3.models.encoders import append_critical_probability  # noqa: E402
from anchordp3.models.objects import cluster_critical_points  # noqa: E402
from anchordp3.pipeline.evaluation import eval_run_config, models_folder  # noqa: E402
from anchordp3.schemas.evaluation import EvalOptions  # noqa: E402
from anchordp3.schemas.episode import parse_seeds  # noqa: E402
from anchordp3.sim.actors import pose_matrix  # noqa: E402
from anchordp3.sim.poses import wrap_angle  # noqa: E402
from anchordp3.stages.evaluate import EvalModels, evaluate_episode  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402

TOKEN_MISS_CM = 5.0
FAR_CM = 3.0
YAW_DEG = 20.0
CAUSES = ("token", "far", "yaw", "other", "no_close")


class GraspWatch:
    """Collects one episode's first-decision token error and its first close's errors."""

    def __init__(self, models: EvalModels):
        self.models = models
        self.token_cm: float | None = None
        self.close: dict | None = None

    def __call__(self, ep, decision: int, points: np.ndarray, pred: np.ndarray) -> None:
        task, arm = ep.task, ep.task.arm
        obj = pose_matrix(ep.world.objects[task.noun].pose)
        if decision == 0:
            pts = torch.from_numpy(points.astype(np.float32))[None]
            prob = self.models.segmenter.probabilities(pts)
            full = append_critical_probability(pts, prob)
            _, centres = cluster_critical_points(full[..., :3], full[..., -1] > 0.5, 2,
                                                 self.models.policy.config.objects.z_weight)
            self.token_cm = 100 * float(np.min(np.linalg.norm(centres[0, :, :2].numpy() - obj[:2, 3], axis=1)))
        g = ep.layout.gripper(arm)
        if self.close is None and ep.robot.joint_target()[g] > 0.5 and pred[0][g] < 0.5:
            grasp, finger = task.grasp_pose()
            tcp = ep.robot.ee_pose(arm)
            along, across, up = obj[:3, :3].T @ (tcp[:3, 3] - grasp[:3, 3])
            yaw = 0.0
            if not task.model.symmetric_yaw:
                err = wrap_angle(float(np.arctan2(tcp[1, 1], tcp[0, 1])) - finger)
                yaw = float(np.degrees((err + np.pi / 2) % np.pi - np.pi / 2))
            self.close = {"decision": decision, "along_cm": 100 * along, "across_cm": 100 * across, "up_cm": 100 * up,
                          "yaw_deg": yaw}


def cause(success: bool, w: GraspWatch) -> str | None:
    """The failure's cause (module docstring), None on success."""
    if success:
        return None
    if w.token_cm is not None and w.token_cm > TOKEN_MISS_CM:
        return "token"
    if w.close is None:
        return "no_close"
    if np.hypot(w.close["along_cm"], w.close["across_cm"]) > FAR_CM:
        return "far"
    if abs(w.close["yaw_deg"]) > YAW_DEG:
        return "yaw"
    return "other"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=None, help="a models folder or 'pretrained' (default: RUN/models)")
    ap.add_argument("--run-dir", type=Path, default=None)
    ap.add_argument("--tasks", default="place_mouse")
    ap.add_argument("--seeds", default="2000-2019")
    ap.add_argument("--samples", type=int, default=1, help="anchor sequences per decision, their medoid carried out")
    args = ap.parse_args()
    torch.set_num_threads(1)
    opts = EvalOptions(models=args.models, tasks=tuple(args.tasks.split(",")))
    models_dir = models_folder(args.run_dir, args.models)
    cfg = eval_run_config(args.run_dir, models_dir, opts)
    models = EvalModels(models_dir, samples=args.samples)
    rows, counts, n_ok, n = [], {c: 0 for c in CAUSES}, 0, 0
    for task in opts.tasks:
        for seed in parse_seeds(args.seeds, "--seeds"):
            w = GraspWatch(models)
            rec = evaluate_episode(task, seed, models, cfg, watch=w)
            why = cause(rec.success, w)
            n, n_ok = n + 1, n_ok + rec.success
            if why:
                counts[why] += 1
            c = w.close or {}
            row = [task, seed, "ok" if rec.success else rec.failure, why or "-",
                   f"{w.token_cm:.1f}" if w.token_cm is not None else "-",
                   *(f"{c[k]:+.1f}" if k in c else "-" for k in ("along_cm", "across_cm", "up_cm", "yaw_deg"))]
            rows.append(row)
            print(" ".join(map(str, row)), flush=True)
    print(text_table(["task", "seed", "outcome", "cause", "token cm", "along cm", "across cm", "up cm", "yaw deg"], rows))
    for ok in (True, False):
        sel = [r for r in rows if (r[2] == "ok") == ok and r[8] != "-"]
        if sel:
            yaw = np.median([abs(float(r[8])) for r in sel])
            plane = np.median([np.hypot(float(r[5]), float(r[6])) for r in sel])
            print(f"{'successes' if ok else 'failures'} that closed: {len(sel)}, median |yaw| {yaw:.1f} deg, "
                  f"median distance in the table plane {plane:.1f} cm")
    print(f"RESULT success={n_ok}/{n} " + " ".join(f"{c}={counts[c]}" for c in CAUSES))
    return 0


if __name__ == "__main__":
    sys.exit(main())
