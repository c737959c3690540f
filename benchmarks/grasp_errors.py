"""Why grasps fail in closed loop: each time the policy closes a gripper, where it is against
where the expert closed it on the same object of the same scene. Any task, either arm.

    python benchmarks/grasp_errors.py --models pretrained --tasks place_mouse --seeds 2000-2039
    python benchmarks/grasp_errors.py --run-dir RUN --tasks place_phone_stand,stack_blocks_three --seeds 1119-1128

Per (task, seed) the expert runs first (``sim.episode.run_expert``, no rendering): at each of its
closes (the ``TGC`` anchors) the tool centre point is taken in the frame of the critical object
nearest it. Then the policy runs in closed loop as ``anchordp3 eval`` does (one process, through
poses), watched at every decision (``stages.evaluate.evaluate_episode(watch=...)``):

- at the first decision, whether the tokens found each critical object: the distance in the
  table plane from the object's origin to its token's centroid (the token of its role with role
  tokens, the nearest cluster with k-means tokens), cm; over 5 cm the segmenter marked something
  else;
- at every decision where an arm's gripper is commanded from open to closed (a grasp): the
  critical object nearest the tool centre point, and the TCP against the expert's close on that
  object (by that arm where it closed on it, else by the other), in the object's frame: along its
  x and y axes and up (cm), and the wrist's yaw about the vertical against the object's, modulo
  180 degrees (the gripper is symmetric; a cube's 90-degree symmetry shows as +-90), measured at
  the next decision, when the close has been carried out; and how far the TCP is then from the
  close's anchor (``track cm``: the executor's error, not the policy's);
- whether the grasp held: the object rose 2 cm above where it was at the close while that
  gripper stayed closed;
- at every decision where an arm's gripper that held an object is commanded open (a release):
  where the object lies at the next decision against where the expert's episode of the scene left
  it (cm, in the table plane and up).

Each grasp that did not hold gets one cause, the first that holds: ``token`` (its object's token
was over 5 cm off at the first decision), ``far`` (over 3 cm from the expert's close in the table
plane), ``height`` (over 1.5 cm above or below it), ``yaw`` (the wrist over 20 degrees off), else
``other``. Episodes whose arms never closed count as ``no_close``.
Last line: ``RESULT success=K/N grasps=G held=H releases=R token=.. far=.. height=.. yaw=.. other=.. no_close=..``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from anchordp3.models.objects import object_tokens, token_centroids  # noqa: E402
from anchordp3.pipeline.evaluation import eval_run_config, models_folder  # noqa: E402
from anchordp3.schemas.evaluation import DECISION_SAMPLES, EvalOptions  # noqa: E402
from anchordp3.schemas.episode import parse_seeds  # noqa: E402
from anchordp3.sim.actors import pose_matrix  # noqa: E402
from anchordp3.sim.episode import build, run_expert  # noqa: E402
from anchordp3.sim.poses import wrap_angle  # noqa: E402
from anchordp3.schemas.state import ARMS  # noqa: E402
from anchordp3.stages.evaluate import EvalModels, evaluate_episode  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402

TOKEN_MISS_CM = 5.0
FAR_CM = 3.0
HEIGHT_CM = 1.5
YAW_DEG = 20.0
HELD_RISE = 0.02  # metres above the object's height at the close
CAUSES = ("token", "far", "height", "yaw", "other", "no_close")


def in_object_frame(tcp: np.ndarray, obj: np.ndarray) -> tuple[np.ndarray, float]:
    """``tcp``, ``obj``: (4, 4) world poses -> the TCP's position in the object's frame (3,) metres
    and the finger direction's yaw minus the object's x axis' yaw, radians."""
    local = obj[:3, :3].T @ (tcp[:3, 3] - obj[:3, 3])
    yaw = float(np.arctan2(tcp[1, 1], tcp[0, 1])) - float(np.arctan2(obj[1, 0], obj[0, 0]))
    return local, wrap_angle(yaw)


def nearest_object(world, names: list[str], point: np.ndarray) -> str:
    """The name among ``names`` (those that are bodies: a goal marker is not) whose origin is
    nearest ``point (3,)`` world metres."""
    return min((n for n in names if n in world.objects), key=lambda n: float(np.linalg.norm(np.asarray(world.objects[n].pose.p) - point)))


@dataclass
class ExpertScene:
    """What the expert did in one scene: its first close on each object by each arm, ``(arm,
    object) -> (TCP position in the object's frame (3,) metres, yaw against the object's)``, and
    where each object ended, ``object -> (3,)`` world metres."""

    closes: dict[tuple[str, str], tuple[np.ndarray, float]]
    ends: dict[str, np.ndarray]


def expert_scene(task: str, seed: int, cfg) -> ExpertScene:
    """The expert's closes (its rollout's ``TGC`` anchors replayed) and its objects' final places."""
    res = run_expert(task, seed, cfg.world())
    if not res.success:
        return ExpertScene({}, {})
    world, t = build(task, seed, cfg.world(), render=False)
    names = t.critical_objects()
    world.unpack(res.physx[-1].tobytes())
    ends = {n: np.asarray(world.objects[n].pose.p, dtype=np.float64) for n in names if n in world.objects}
    out: dict[tuple[str, str], tuple[np.ndarray, float]] = {}
    for tag in res.anchors:
        if tag.name != "TGC":
            continue
        world.unpack(res.physx[tag.t].tobytes())
        for arm in ARMS if tag.arm == "both" else (tag.arm,):
            tcp = world.robot.ee_pose(arm)
            name = nearest_object(world, names, tcp[:3, 3])
            out.setdefault((arm, name), in_object_frame(tcp, pose_matrix(world.objects[name].pose)))
    return ExpertScene(out, ends)


def token_centres(models: EvalModels, points: np.ndarray, state: np.ndarray, task_id: int) -> np.ndarray:
    """The policy's object tokens' centroids at one observation, ``(k, 3)`` metres (NaN for an
    object without points), as the policy makes its tokens (``models.objects.object_tokens``): role
    j + 1's points with role tokens, else the k-means clusters."""
    obs = models.observation(points, state, task_id)
    cfg = models.policy.config.objects
    roles = obs["roles"] if cfg is not None and cfg.source == "roles" else None
    tokens = object_tokens(obs["points"], obs["state"], models.policy.layout, cfg.tokens if cfg is not None else 2,
                           z_weight=cfg.z_weight if cfg is not None else 1.0, roles=roles)
    centres, present = token_centroids(tokens)
    return np.where(present[0, :, None].numpy(), centres[0].numpy(), np.nan)


@dataclass
class Grasp:
    """One commanded close: arm, object, decision, the errors against the expert's close (cm, deg;
    None without one), the object's height at the close (m) and whether it held."""

    arm: str
    obj: str
    decision: int
    error_cm: np.ndarray | None
    yaw_deg: float | None
    z0: float
    command: np.ndarray  # the close's anchor: its TCP position, (3,) world metres
    track_cm: float | None = None
    held: bool = False


@dataclass
class Release:
    """One commanded open of a gripper that held an object: arm, object, decision, and where the
    object lay at the next decision against where the expert's episode left it (cm: in the table
    plane, and up; None until measured)."""

    arm: str
    obj: str
    decision: int
    plane_cm: float | None = None
    up_cm: float | None = None


@dataclass
class GraspWatch:
    """Collects one episode's token errors at the first decision and its grasps."""

    models: EvalModels
    expert: dict
    token_cm: dict[str, float] = field(default_factory=dict)
    grasps: list[Grasp] = field(default_factory=list)
    releases: list[Release] = field(default_factory=list)

    def __call__(self, ep, decision: int, points: np.ndarray, pred: np.ndarray) -> None:
        names = ep.task.critical_objects()
        if decision == 0:
            centres = token_centres(self.models, points, ep.robot.state(), self.models.classify(ep.instruction()))
            by_role = self.models.policy.config.objects is not None and self.models.policy.config.objects.source == "roles"
            for i, n in enumerate(names):
                if n not in ep.world.objects:
                    continue
                xy = np.asarray(ep.world.objects[n].pose.p)[:2]
                d = np.linalg.norm(centres[:, :2] - xy, axis=1)
                self.token_cm[n] = 100 * float(d[i] if by_role and i < len(d) else np.nanmin(d))
        target = ep.robot.joint_target()
        for r in self.releases:
            if r.decision == decision - 1 and r.obj in self.expert.ends:
                d = np.asarray(ep.world.objects[r.obj].pose.p) - self.expert.ends[r.obj]
                r.plane_cm, r.up_cm = 100 * float(np.hypot(d[0], d[1])), 100 * float(d[2])
        for g in self.grasps:
            if g.decision == decision - 1:  # the close has been carried out: where it closed
                self.measure(ep, g)
            if not g.held and target[ep.layout.gripper(g.arm)] < 0.5:  # held: rose with the gripper closed
                g.held = float(ep.world.objects[g.obj].pose.p[2]) > g.z0 + HELD_RISE
        for arm in ARMS:
            gi = ep.layout.gripper(arm)
            if target[gi] < 0.5 < pred[0][gi]:
                held = [g for g in self.grasps if g.arm == arm and g.held]
                if held and held[-1].decision > max((r.decision for r in self.releases if r.arm == arm), default=-1):
                    self.releases.append(Release(arm, held[-1].obj, decision))
            if target[gi] > 0.5 and pred[0][gi] < 0.5:
                tcp = ep.robot.ee_pose(arm)
                name = nearest_object(ep.world, names, tcp[:3, 3])
                self.grasps.append(Grasp(arm, name, decision, None, None, float(ep.world.objects[name].pose.p[2]),
                                         np.asarray(pred[0][ep.layout.ee_xyz(arm)], dtype=np.float64)))
                self.measure(ep, self.grasps[-1])  # until the next decision shows where it closed

    def measure(self, ep, g: Grasp) -> None:
        """The grasp's TCP against the expert's close on its object (module docstring)."""
        tcp = ep.robot.ee_pose(g.arm)
        g.track_cm = 100 * float(np.linalg.norm(tcp[:3, 3] - g.command))
        local, yaw = in_object_frame(tcp, pose_matrix(ep.world.objects[g.obj].pose))
        closes = self.expert.closes
        ref = closes.get((g.arm, g.obj)) or next((v for (a, n), v in closes.items() if n == g.obj), None)
        if ref is not None:
            g.error_cm = 100 * (local - ref[0])
            g.yaw_deg = float(np.degrees((wrap_angle(yaw - ref[1]) + np.pi / 2) % np.pi - np.pi / 2))


def cause(g: Grasp, token_cm: dict[str, float]) -> str | None:
    """A grasp's failure cause (module docstring), None when it held."""
    if g.held:
        return None
    if token_cm.get(g.obj, 0.0) > TOKEN_MISS_CM:
        return "token"
    if g.error_cm is None:
        return "other"
    if np.hypot(g.error_cm[0], g.error_cm[1]) > FAR_CM:
        return "far"
    if abs(g.error_cm[2]) > HEIGHT_CM:
        return "height"
    if abs(g.yaw_deg) > YAW_DEG:
        return "yaw"
    return "other"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=None, help="a models folder or 'pretrained' (default: RUN/models)")
    ap.add_argument("--run-dir", type=Path, default=None)
    ap.add_argument("--tasks", default="place_mouse")
    ap.add_argument("--seeds", default="2000-2019")
    ap.add_argument("--samples", type=int, default=DECISION_SAMPLES, help="anchor sequences per decision, their medoid carried out (default: the evaluation's)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    opts = EvalOptions(models=args.models, tasks=tuple(args.tasks.split(",")))
    models_dir = models_folder(args.run_dir, args.models)
    cfg = eval_run_config(args.run_dir, models_dir, opts)
    models = EvalModels(models_dir, samples=args.samples)
    rows, let_go, counts, n_ok, n, n_grasps, n_held = [], [], {c: 0 for c in CAUSES}, 0, 0, 0, 0
    for task in opts.tasks:
        for seed in parse_seeds(args.seeds, "--seeds"):
            w = GraspWatch(models, expert_scene(task, seed, cfg))
            rec = evaluate_episode(task, seed, models, cfg, watch=w)
            n, n_ok = n + 1, n_ok + rec.success
            if not w.grasps and not rec.success:
                counts["no_close"] += 1
            outcome = "ok" if rec.success else rec.failure
            for g in w.grasps:
                why = cause(g, w.token_cm)
                n_grasps, n_held = n_grasps + 1, n_held + g.held
                if why:
                    counts[why] += 1
                e = g.error_cm
                row = [task, seed, outcome, g.arm, g.obj, g.decision, "held" if g.held else why,
                       f"{w.token_cm.get(g.obj, float('nan')):.1f}",
                       *(f"{v:+.1f}" for v in (e if e is not None else [np.nan] * 3)),
                       f"{g.yaw_deg:+.0f}" if g.yaw_deg is not None else "-", f"{g.track_cm:.1f}"]
                rows.append(row)
                print(" ".join(map(str, row)), flush=True)
            if not w.grasps:
                print(task, seed, outcome, "no close", flush=True)
            let_go += [[task, seed, outcome, r.arm, r.obj, r.decision,
                        *(f"{v:+.1f}" if v is not None else "-" for v in (r.plane_cm, r.up_cm))] for r in w.releases]
    print(text_table(["task", "seed", "outcome", "arm", "object", "decision", "grasp", "token cm", "x cm", "y cm",
                      "up cm", "yaw deg", "track cm"], rows))
    print(text_table(["task", "seed", "outcome", "arm", "object", "decision", "off the expert's place cm", "up cm"],
                     let_go))
    for held in ("held", None):
        sel = [r for r in rows if (r[6] == "held") == (held is not None) and r[8] != "+nan"]
        if sel:
            plane = np.median([np.hypot(float(r[8]), float(r[9])) for r in sel])
            up = np.median([abs(float(r[10])) for r in sel])
            yaw = np.median([abs(float(r[11])) for r in sel if r[11] != "-"] or [np.nan])
            print(f"grasps {'held' if held else 'not held'}: {len(sel)}, median |plane| {plane:.1f} cm, "
                  f"|up| {up:.1f} cm, |yaw| {yaw:.0f} deg")
    placed = [abs(float(r[6])) for r in let_go if r[6] != "-"]
    if placed:
        print(f"releases: {len(let_go)}, median distance in the table plane from the expert's place "
              f"{np.median(placed):.1f} cm, within 2 cm: {sum(v < 2 for v in placed)}")
    print(f"RESULT success={n_ok}/{n} grasps={n_grasps} held={n_held} releases={len(let_go)} " + " ".join(f"{c}={counts[c]}" for c in CAUSES))
    return 0


if __name__ == "__main__":
    sys.exit(main())
