"""``anchordp3 experiment anchors-vs-dense``: the AnchorDP3 report's central claim, measured.

Two arms with the same tasks and the same render budget (rendered frames):

- **anchors**: the run as configured: sparse frames between anchors, DAgger frames, labels = the
  next H anchors;
- **dense**: DP3 on RoboTwin's way: a frame every ``dense.frame_stride`` control steps, labels =
  the next H commanded actions, on the prefix of the same seeds whose dense frames come nearest
  to the frames the anchors arm rendered.

Both arms train the same three models with the same settings and are evaluated in closed loop on
the same seeds and held-out instructions. Output under the experiment folder: ``anchors/`` and
``dense/`` (complete run directories, each resumable and inspectable), ``phases.json`` (wall
seconds per phase), ``results.json``,
``comparison.png`` (success per task, both arms, 95 % intervals) and ``report.md`` (trajectories per
render budget, success per task, wall time of each phase).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path

from anchordp3.pipeline.phases import PhaseClock
from anchordp3.pipeline.evaluation import SEED_OFFSET, episode_key, episode_records, summarize, wilson_interval
from anchordp3.pipeline.products import stage_folder
from anchordp3.pipeline.runner import RunOptions, run_pipeline
from anchordp3.pipeline.store import read_manifest
from anchordp3.pipeline.work import stage_dir
from anchordp3.schemas.episode import SeedSet
from anchordp3.schemas.experiment import ExperimentConfig
from anchordp3.schemas.records import AnchorsInfo, RolloutInfo
from anchordp3.schemas.run import RunConfig
from anchordp3.stages.files import atomic_write_bytes

log = logging.getLogger(__name__)

ARMS = ("anchors", "dense")
PHASES_FILE = "phases.json"  # wall seconds per arm and phase, summed over invocations
REPORTED_RATIO = 14.5  # trajectories per render budget, anchors over dense, in the AnchorDP3 report


def rendered_frames(run_dir: Path) -> dict[tuple[str, int], int]:
    """Frames rendered per ``(task, seed)`` episode of a run (planned frames of rendered episodes)."""
    plans = read_manifest(stage_dir(run_dir, "anchors")).items
    rendered = read_manifest(stage_dir(run_dir, "render")).items
    return {episode_key(k): plans[k].payload(AnchorsInfo).frames for k, r in rendered.items()
            if r.status == "done" and k in plans and plans[k].status == "done"}


def kept_steps(run_dir: Path) -> dict[tuple[str, int], int]:
    """Control steps of each kept (expert-successful) episode of a run."""
    items = read_manifest(stage_dir(run_dir, "rollout")).items
    kept = {k: info for k, r in items.items() if r.status == "done" and (info := r.payload(RolloutInfo)).kept}
    return {episode_key(k): info.record.steps for k, info in kept.items()}


def dense_frame_count(steps: int, stride: int) -> int:
    """Frames of the dense plan of a ``steps``-step episode: one every ``stride`` steps from 0."""
    return -(-steps // stride)


def dense_seed_count(tasks: Sequence[str], seeds: Sequence[int], steps: dict[tuple[str, int], int], budget: int,
                     stride: int) -> int:
    """The ``n`` whose dense plans of ``seeds[:n]`` over all ``tasks`` render the number of frames
    nearest to ``budget`` (the fewer seeds on a tie; at least 1: the dense arm always has data).

    A dense episode costs as many frames as several sparse ones, so the nearest count may lie a
    little above the budget rather than far below it; the report gives both arms' frames."""
    totals, total = [], 0
    for s in seeds:
        total += sum(dense_frame_count(steps[(t, s)], stride) for t in tasks if (t, s) in steps)
        totals.append(total)
    return 1 + min(range(len(totals)), key=lambda i: (abs(totals[i] - budget), i)) if totals else 1


def dense_arm(cfg: RunConfig, n_seeds: int) -> RunConfig:
    """The dense arm's run config: ``cfg`` with the dense plan on its first ``n_seeds`` seeds."""
    seeds = str(SeedSet((s, s) for s in cfg.seed_list[:n_seeds]))  # compact: "0-35", not "0,1,...,35"
    anchors = cfg.anchors.model_copy(update={"plan": "dense"})
    return cfg.model_copy(update={"name": f"{cfg.name}-dense", "seeds": seeds, "anchors": anchors})


def run_experiment(out: Path, cfg: ExperimentConfig,
                   address: str | None = None) -> dict:
    """Run (or resume) both arms into ``out``, each one run of the whole graph (data, training,
    evaluation on the same unseen seeds); returns the results written to ``results.json``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    clock = PhaseClock(out / PHASES_FILE, ARMS)
    evaluation = cfg.eval.target(first_seed=cfg.run.seed_list.last + SEED_OFFSET)

    def arm(run: RunConfig) -> RunConfig:
        return run.model_copy(update={"training": cfg.training, "evaluation": evaluation})

    def run_arm(name: str) -> None:
        run_pipeline(runs[name], out / name, RunOptions(address=address, redo=("evaluate",), on_phase=clock.recorder(name)))

    runs = {"anchors": arm(cfg.run)}
    run_arm("anchors")
    budget = sum(rendered_frames(out / "anchors").values())
    n = dense_seed_count(cfg.run.tasks, cfg.run.seed_list, kept_steps(out / "anchors"), budget, cfg.run.anchors.dense.frame_stride)
    runs["dense"] = arm(dense_arm(cfg.run, n))
    log.info(f"experiment: the anchors arm rendered {budget} frames; the dense arm's plan on {n} seed(s) per task comes nearest")
    run_arm("dense")

    records = {}
    for name in ARMS:
        folder = stage_folder(out / name, "evaluate")
        records[name] = episode_records(folder, runs[name], read_manifest(folder).items)
    results = _results(out, runs, records, clock.seconds)
    atomic_write_bytes(out / "results.json", json.dumps(results, indent=1).encode())
    _chart(out / "comparison.png", results)
    atomic_write_bytes(out / "report.md", experiment_report(results).encode())
    return results


def _results(out: Path, runs: dict[str, RunConfig], records: dict[str, list[dict]], seconds: dict) -> dict:
    arms = {}
    for arm in ARMS:
        frames = rendered_frames(out / arm)
        k = sum(bool(r["success"]) for r in records[arm])
        arms[arm] = {
            "seeds": runs[arm].seeds, "trajectories": len(frames), "frames": sum(frames.values()),
            "trajectories_per_1000_frames": 1000 * len(frames) / max(1, sum(frames.values())),
            "success": k, "episodes": len(records[arm]), "rate": k / max(1, len(records[arm])),
            "per_task": summarize(records[arm]), "seconds": seconds[arm],
        }
    a, d = arms["anchors"], arms["dense"]
    ratio = a["trajectories_per_1000_frames"] / d["trajectories_per_1000_frames"] if d["trajectories_per_1000_frames"] else None
    return {"tasks": runs["anchors"].tasks, "trajectories_per_budget_ratio": ratio, "reported_ratio": REPORTED_RATIO,
            "dense_frame_stride": runs["anchors"].anchors.dense.frame_stride, "arms": arms}


def _chart(path: Path, results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = results["tasks"]
    fig, ax = plt.subplots(figsize=(max(5, 1.3 * len(tasks) + 2), 3.8))
    width = 0.38
    for j, (arm, colour) in enumerate(zip(ARMS, ("#4c72b0", "#dd8452"))):
        rows = {r["task"]: r for r in results["arms"][arm]["per_task"]}
        x = [i + (j - 0.5) * width for i in range(len(tasks))]
        rate = [rows[t]["rate"] if t in rows else 0.0 for t in tasks]
        err = [[rows[t]["rate"] - rows[t]["ci_low"] if t in rows else 0 for t in tasks],
               [rows[t]["ci_high"] - rows[t]["rate"] if t in rows else 0 for t in tasks]]
        n = results["arms"][arm]["trajectories"]
        ax.bar(x, rate, width, yerr=err, capsize=3, color=colour, label=f"{arm} ({n} trajectories)")
    ax.set_xticks(range(len(tasks)), tasks, rotation=20, ha="right")
    ax.set_ylim(0, 1)
    ax.set_ylabel("success rate (95 % CI)")
    ax.set_title(f"same render budget: {results['arms']['anchors']['frames']} vs {results['arms']['dense']['frames']} frames")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)


def experiment_report(results: dict) -> str:
    """The markdown report of ``results``."""
    arms = results["arms"]
    ratio = results["trajectories_per_budget_ratio"]
    lines = ["# Sparse anchors versus dense frames at the same render budget", "",
             f"Trajectories per render budget, anchors over dense: **{ratio:.1f}×** (the AnchorDP3 report: {results['reported_ratio']}×; "
             f"dense frames every {results['dense_frame_stride']} control steps).", "",
             "| arm | seeds per task | trajectories | rendered frames | trajectories / 1000 frames | success | data s | train s | eval s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for arm in ARMS:
        a = arms[arm]
        lo, hi = wilson_interval(a["success"], a["episodes"])
        s = a["seconds"]
        lines.append(f"| {arm} | {a['seeds']} | {a['trajectories']} | {a['frames']} | {a['trajectories_per_1000_frames']:.2f} | "
                     f"{a['success']}/{a['episodes']} = {a['rate']:.1%} [{lo:.2f}, {hi:.2f}] | "
                     f"{s.get('data', 0):.0f} | {s.get('train', 0):.0f} | {s.get('eval', 0):.0f} |")
    lines += ["", "Success per task (95 % Wilson interval):", "", "| task | anchors | dense |", "|---|---|---|"]
    per = {arm: {r["task"]: r for r in arms[arm]["per_task"]} for arm in ARMS}
    for t in results["tasks"]:
        cells = []
        for arm in ARMS:
            r = per[arm].get(t)
            cells.append(f"{r['successes']}/{r['episodes']} [{r['ci_low']:.2f}, {r['ci_high']:.2f}]" if r else "-")
        lines.append(f"| {t} | {cells[0]} | {cells[1]} |")
    lines += ["", "Wall times are summed over the invocations that built each phase (a resumed phase adds only what it redid).",
              "", "![success per task, both arms](comparison.png)", ""]
    return "\n".join(lines)
