"""Closed-loop evaluation of a run's trained models: the evaluate stage (an item per task and
seed, run by the runner in a pool of actors, each loading the models once), its fingerprint,
seeds and reports.

Seeds are disjoint from every training seed (``max(training seeds) + 1000 + i``) and the
instructions come from held-out phrasing families. Output under ``<run>/eval/``:
``records.sqlite`` (the stage manifest: one record per episode, resumable, retried like any
stage's items), ``episodes/<task>/<seed>.json``,
``episodes.parquet`` (the table), ``success.png`` (success rate per task with 95 % Wilson
intervals), ``strips/<task>/<seed>.png`` (the head camera at each decision of a few episodes),
``report.md``, and with ``train_episodes`` the same for training seeds in ``eval/train/``
(stage ``evaluate-train``).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path

import anchordp3
from anchordp3.dataset.files import file_sha256
from anchordp3.pipeline.codehash import code_hash
from anchordp3.pipeline.graph import BatchContext, BatchItem, StageOutput
from anchordp3.pipeline.store import StaleStageError, has_manifest, read_summary
from anchordp3.schemas.manifest import Fingerprint, ItemRecord
from anchordp3.schemas.records import EvalEpisodeInfo
from anchordp3.schemas.episode import SeedSet, parse_seeds
from anchordp3.schemas.evaluation import DEFAULT_EPISODES, EvalOptions, EvaluationConfig
from anchordp3.schemas.run import RunConfig, config_hash, load_run_config
from anchordp3.schemas.training import MODELS
from anchordp3.stages.files import atomic_write_bytes

log = logging.getLogger(__name__)

EVAL_DIR = "eval"
STAGE = "evaluate"
TRAIN_STAGE = "evaluate-train"  # the same models on training seeds
TRAIN_DIR = "train"  # its folder, inside the evaluation's
SEED_OFFSET = 1000
PROTOCOL_MODULE = "anchordp3.stages.evaluate"  # the decision loop and how a prediction is carried out


PRETRAINED = "pretrained"
PRETRAINED_DIR = Path(__file__).resolve().parents[1] / "pretrained"  # the shipped models, inside the package
RUN_CONFIG_FILE = "run_config.yaml"  # beside shipped models: the data config they were trained on


def models_folder(run_dir: Path | None, models: str | None) -> Path:
    """The folder of the three trained models: ``models`` (a path, or ``pretrained`` for the
    shipped ones), else ``<run>/models``."""
    if models == PRETRAINED:
        return PRETRAINED_DIR
    if models is not None:
        return Path(models)
    if run_dir is None:
        raise ValueError("--models: give a models folder (or 'pretrained') or a --run-dir")
    return Path(run_dir) / "models"


def eval_run_config(run_dir: Path | None, models_dir: Path, target: EvaluationConfig) -> RunConfig:
    """The data config the models were trained on (the run's ``config.yaml``, or the
    ``run_config.yaml`` shipped beside a models folder) with ``target`` as its ``evaluation``
    section; tasks the models were not trained on are refused."""
    for path in ([Path(run_dir) / "config.yaml"] if run_dir is not None else []) + [models_dir / RUN_CONFIG_FILE,
                                                                                       models_dir.parent / "config.yaml"]:
        if path.is_file():
            cfg = load_run_config(path)
            break
    else:
        raise FileNotFoundError(f"{models_dir}: no {RUN_CONFIG_FILE} beside the models and no run config; give --run-dir")
    unknown = sorted(set(target.tasks or ()) - set(cfg.tasks))
    if unknown:
        raise ValueError(f"--tasks: {unknown} not among the tasks the models were trained on ({cfg.tasks})")
    section = EvaluationConfig(**{k: getattr(target, k) for k in EvaluationConfig.model_fields})  # EvalOptions' own fields left out
    return cfg.model_copy(update={"evaluation": section})


def evaluated(cfg: RunConfig) -> RunConfig:
    """The run config of the evaluation's scenes: the tasks and preset its ``evaluation`` section
    names (default: the run's)."""
    ev = cfg.evaluation
    data = cfg.model_dump(mode="json")
    return RunConfig.model_validate({**data, "tasks": list(ev.tasks or data["tasks"]), "preset": ev.preset or data["preset"]})


def selected_seeds(cfg: RunConfig, opts: EvaluationConfig) -> list[int]:
    """The evaluation seeds: ``opts.seeds`` (``train``: the training seeds, the first
    ``opts.episodes`` of them when given), else ``opts.episodes`` seeds disjoint from training.
    An explicit seed list and a different episode count contradict each other: refused."""
    if opts.seeds == "train":
        return list(cfg.seed_list)[:opts.episodes]  # None: all of them
    if opts.seeds:
        seeds = parse_seeds(opts.seeds, "--seeds")
        if opts.episodes is not None and opts.episodes != len(seeds):
            raise ValueError(f"--episodes: {opts.episodes} per task, but --seeds {opts.seeds!r} lists {len(seeds)}; give one or the other")
        return seeds
    return eval_seeds(cfg, opts.episodes if opts.episodes is not None else DEFAULT_EPISODES, opts.first_seed)


def eval_seeds(cfg: RunConfig, episodes: int, first_seed: int | None = None) -> list[int]:
    """Evaluation seeds, disjoint from the run's training seeds."""
    last = cfg.seed_list.last
    base = last + SEED_OFFSET if first_seed is None else first_seed
    if base <= last:
        raise ValueError(f"first_seed: {base} would overlap the training seeds {cfg.seeds}; choose one above {last}")
    return [base + i for i in range(episodes)]


def train_target(cfg: RunConfig) -> RunConfig:
    """The config of the second evaluation (``evaluate-train``): the first ``train_episodes``
    training seeds, no frame strips."""
    ev = cfg.evaluation
    return cfg.model_copy(update={"evaluation": ev.model_copy(update={
        "seeds": "train", "episodes": ev.train_episodes, "strips": 0, "train_episodes": 0})})


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """The 95 % Wilson score interval of a success rate (``(0, 1)`` when ``n == 0``). It holds the
    rate itself: at 0 or n successes the bound at the rate is exactly 0 or 1, not a rounding off."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    low = 0.0 if successes == 0 else min(p, max(0.0, centre - half))
    high = 1.0 if successes == n else max(p, min(1.0, centre + half))
    return low, high


def episode_item(task: str, seed: int) -> str:
    return f"{task}/{seed:06d}"


def episode_key(item: str) -> tuple[str, int]:
    """``place_mouse/002000`` → ``("place_mouse", 2000)``."""
    task, seed = item.rsplit("/", 1)
    return task, int(seed)


# ------------------------------------------------------------------------ the evaluate stage
def episode_items(cfg: RunConfig) -> list[str]:
    """The evaluate stage's items: one per task and seed of ``cfg.evaluation``, in that order."""
    ev = evaluated(cfg)
    seeds = selected_seeds(ev, ev.evaluation)
    return [episode_item(t, s) for t in ev.tasks for s in seeds]


def check_models(models_dir: Path) -> None:
    """Every model file of ``models_dir`` is a readable checkpoint of its kind: bad input gets a
    one-line error naming the file here, in the driver, not a traceback from an actor."""
    from anchordp3.stages.training_loop import load_checkpoint

    for name in MODELS:
        path = Path(models_dir) / name / "model.pt"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no trained {name}; run `anchordp3 train all --run-dir RUN` first")
        kind = load_checkpoint(path).get("kind")
        if kind != name:
            raise ValueError(f"{path}: not a {name} checkpoint (kind {kind!r})")


def evaluation_fingerprint(ctx: BatchContext, cfg: RunConfig) -> Fingerprint:
    """What an evaluation's episodes depend on: the models' checksums, the scenes' world and
    features, and how decisions are made and carried out (not the seeds: more seeds resume)."""
    ev = evaluated(cfg)
    opts = ev.evaluation
    models_dir = models_folder(ctx.run_dir, opts.models)
    check_models(models_dir)
    upstream = {name: file_sha256(Path(models_dir) / name / "model.pt")[:16] for name in MODELS}
    part = {"world": ev.world().model_dump(mode="json"), "features": ev.features.model_dump(mode="json"),
            "max_decisions": opts.max_decisions, "through": opts.through, "plan": ev.anchors.plan, "dense": ev.anchors.dense.model_dump(mode="json")}
    if opts.ddim_steps is not None:  # only when set: evaluations with the policy's own steps keep their fingerprint
        part["ddim_steps"] = opts.ddim_steps
    if opts.samples != 1:
        part["samples"] = opts.samples
    if opts.skip_reached:
        part["skip_reached"] = opts.skip_reached
    return Fingerprint(code_version=anchordp3.__version__, code_hash=code_hash([PROTOCOL_MODULE]),  # read, not imported: the driver stays free of the simulator
                       config_hash=config_hash(part), upstream=upstream)


def check_evaluation(ctx: BatchContext, cfg: RunConfig) -> None:
    """Refused before anything runs: bad seeds, unreadable models, and a folder holding an
    evaluation of other models, settings or code (unless ``force``). Models this call trains
    first are checked when the stage starts."""
    episode_items(cfg)
    if cfg.evaluation.models is None and any(s.startswith("train-") for s in ctx.stages):
        return
    fp = evaluation_fingerprint(ctx, cfg)
    stored = read_summary(ctx.folder) if ctx.folder.is_dir() and has_manifest(ctx.folder) else None
    changes = stored.fingerprint.changes(fp) if stored is not None else []
    if ctx.refuses(changes):
        raise StaleStageError(f"--out: {ctx.folder} holds an evaluation of other models, settings or code "
                              f"({', '.join(changes)} changed); give another folder, or --force to start over")


_MODELS: dict = {}  # (models folder, device, DDIM steps, samples) -> EvalModels: loaded once per worker


def _models(models_dir: Path, device: str, ddim_steps: int | None, samples: int):
    from anchordp3.stages.evaluate import EvalModels

    key = (str(models_dir), device, ddim_steps, samples)
    if key not in _MODELS:
        import torch

        torch.set_num_threads(1)
        _MODELS.clear()
        _MODELS[key] = EvalModels(Path(models_dir), device, ddim_steps, samples)
    return _MODELS[key]


def actor_device(device: str) -> str:
    """The torch device of an evaluation worker: ``auto`` takes CUDA when the worker was given a
    GPU (Ray shows it only the GPUs it reserved), else the CPU."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def run_episode(run_dir: Path, cfg: RunConfig, item: BatchItem) -> StageOutput:
    """One evaluation episode (the evaluate stage's item): its ``EvalRecord`` as
    ``episodes/<task>/<seed>.json`` in the stage folder, a frame strip for the first ``strips``
    seeds of each task."""
    from anchordp3.stages.evaluate import evaluate_episode

    ev = evaluated(cfg)
    opts = ev.evaluation
    task, seed = episode_key(item.id)
    models = _models(models_folder(run_dir, opts.models), actor_device(opts.device), opts.ddim_steps, opts.samples)
    strip = f"strips/{task}/{seed:06d}.png" if seed in selected_seeds(ev, opts)[:opts.strips] else None
    rec = evaluate_episode(task, seed, models, ev, opts.max_decisions, item.folder / strip if strip else None, opts.through,
                           skip_reached=opts.skip_reached).to_dict()
    rel = f"episodes/{task}/{seed:06d}.json"
    atomic_write_bytes(item.folder / rel, json.dumps(rec, indent=1).encode())
    log.info(f"{'success' if rec['success'] else rec['failure']} ({rec['steps']} steps, {rec['decisions']} decisions)")
    return StageOutput(rel, file_sha256(item.folder / rel), EvalEpisodeInfo(
        success=rec["success"], steps=rec["steps"], decisions=rec["decisions"], failure=rec["failure"], unmet=rec.get("unmet", "")))


def episode_records(folder: Path, cfg: RunConfig, records: dict[str, ItemRecord]) -> list[dict]:
    """The done episodes' ``EvalRecord`` dicts, in item order, each with ``seen`` (the seed was a
    training seed)."""
    train_seeds = cfg.seed_list
    out = []
    for item in episode_items(cfg):
        rec = records.get(item)
        if rec is not None and rec.status == "done":
            out.append({**json.loads((Path(folder) / rec.output).read_text()), "seen": episode_key(item)[1] in train_seeds})
    return out


def report_evaluation(ctx: BatchContext, cfg: RunConfig, records: dict[str, ItemRecord]) -> None:
    """The evaluation's table, chart and report from the episodes that ran; the ones that failed
    with an error are named (the next run tries them again)."""
    items = episode_items(cfg)
    errors = [r for i in items if (r := records.get(i)) is not None and r.status == "failed"]
    if errors:
        log.error(f"evaluate: {len(errors)} of {len(items)} episodes failed with an error (not in the report; run again "
                  f"to retry them): " + "; ".join(f"{r.item}: {r.reason}: {r.detail}" for r in errors[:5]))
    write_reports(ctx.folder, episode_records(ctx.folder, cfg, records), evaluated(cfg), cfg.evaluation)


def summarize(records: Sequence[dict]) -> list[dict]:
    """Per task: episodes, successes, rate, Wilson 95 % interval, mean steps and decisions, failures."""
    rows = []
    for task in dict.fromkeys(r["task"] for r in records):
        rs = [r for r in records if r["task"] == task]
        k = sum(bool(r["success"]) for r in rs)
        lo, hi = wilson_interval(k, len(rs))
        failures: dict[str, int] = {}
        unmet: dict[str, int] = {}  # condition: failed episodes that ended without it
        for r in rs:
            if not r["success"]:
                failures[r["failure"]] = failures.get(r["failure"], 0) + 1
                for name in filter(None, r.get("unmet", "").split(",")):
                    unmet[name] = unmet.get(name, 0) + 1
        rows.append({"task": task, "episodes": len(rs), "successes": k, "rate": k / len(rs), "ci_low": lo, "ci_high": hi,
                     "mean_steps": sum(r["steps"] for r in rs) / len(rs),
                     "mean_decisions": sum(r["decisions"] for r in rs) / len(rs),
                     "classifier_correct": sum(r["predicted_task"] == r["task"] for r in rs), "failures": failures,
                     "unmet": unmet})
    return rows


def seeds_phrase(records: Sequence[dict], cfg: RunConfig) -> str:
    """Where the episodes ran, for the report: ``on seeds disjoint from training (...)``, ``on
    training seeds (...)`` or, for a mix, how many were training seeds."""
    if not records:
        return "(none)"
    span = str(SeedSet((r["seed"], r["seed"]) for r in records))  # the canonical spec, e.g. 0-9 or 1199-1248,1300
    seen = sum(bool(r["seen"]) for r in records)
    if seen == 0:
        return f"on seeds disjoint from training (training seeds {cfg.seeds}; evaluation seeds {span})"
    if seen == len(records):
        return f"on training seeds, the scenes the models were trained on ({span} of {cfg.seeds})"
    return f"on seeds {span}, {seen} of them among the training seeds {cfg.seeds}"


def write_reports(out: Path, records: Sequence[dict], cfg: RunConfig, opts: EvalOptions) -> dict[str, Path]:
    """``episodes.parquet``, ``success.png`` and ``report.md`` from the records."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = Path(out)
    cols = ["task", "seed", "instruction", "predicted_task", "success", "steps", "step_limit", "decisions", "failure", "seconds", "unmet"]
    table = pa.table({c: [r.get(c, "") if c == "unmet" else r[c] for r in records] for c in cols},
                     schema=pa.schema([("task", pa.string()), ("seed", pa.int64()), ("instruction", pa.string()),
                                       ("predicted_task", pa.string()), ("success", pa.bool_()), ("steps", pa.int64()),
                                       ("step_limit", pa.int64()), ("decisions", pa.int64()), ("failure", pa.string()),
                                       ("seconds", pa.float64()), ("unmet", pa.string())]))
    tmp = out / "episodes.parquet.tmp"
    pq.write_table(table, tmp)
    tmp.replace(out / "episodes.parquet")

    rows = summarize(records)
    fig, ax = plt.subplots(figsize=(max(4, 1.2 * len(rows) + 2), 3.5))
    x = list(range(len(rows)))
    rates = [r["rate"] for r in rows]
    err = [[r["rate"] - r["ci_low"] for r in rows], [r["ci_high"] - r["rate"] for r in rows]]
    ax.bar(x, rates, yerr=err, capsize=4, color="#4c72b0")
    for xi, r in zip(x, rows):  # the count above every bar, so that a task at 0 shows too
        ax.text(xi, min(r["ci_high"], 1.0) + 0.02, f"{r['successes']}/{r['episodes']}", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(x, [r["task"] for r in rows], rotation=20, ha="right")
    ax.set_ylim(0, 1.12)
    ax.set_ylabel("success rate (95 % Wilson CI)")
    ax.set_title(f"{cfg.name}: closed-loop success")
    fig.tight_layout()
    tmp_png = out / "success.tmp.png"
    fig.savefig(tmp_png, dpi=100)
    plt.close(fig)
    tmp_png.replace(out / "success.png")

    lines = [f"# Closed-loop evaluation: {cfg.name}", "",
             f"{len(records)} episodes {seeds_phrase(records, cfg)}, instructions from held-out phrasing families"
             + (f", at most {opts.max_decisions} decisions per episode" if opts.max_decisions else "") + ".", "",
             "| task | episodes | success | rate | 95 % CI | mean steps | mean decisions | classifier correct | failures | conditions unmet at the end |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        fails = ", ".join(f"{k}: {v}" for k, v in sorted(r["failures"].items())) or "-"
        unmet = ", ".join(f"{k}: {v}" for k, v in sorted(r["unmet"].items(), key=lambda kv: -kv[1])) or "-"
        lines.append(f"| {r['task']} | {r['episodes']} | {r['successes']} | {r['rate']:.1%} | "
                     f"[{r['ci_low']:.2f}, {r['ci_high']:.2f}] | {r['mean_steps']:.0f} | {r['mean_decisions']:.1f} | "
                     f"{r['classifier_correct']}/{r['episodes']} | {fails} | {unmet} |")
    k = sum(bool(r["success"]) for r in records)
    lo, hi = wilson_interval(k, len(records))
    lines += ["", f"Overall: {k}/{len(records)} = {k / max(1, len(records)):.1%} (95 % CI [{lo:.2f}, {hi:.2f}]).", "",
              "![success per task](success.png)", ""]
    strips = sorted(out.glob("strips/*/*.png"))
    if strips:
        lines += ["Frame strips (head camera at each decision):", ""]
        lines += [f"![{p.parent.name} {p.stem}]({p.relative_to(out).as_posix()})" for p in strips] + [""]
    atomic_write_bytes(out / "report.md", "\n".join(lines).encode())
    return {"table": out / "episodes.parquet", "chart": out / "success.png", "report": out / "report.md"}


def evaluation_summary(records: Sequence[dict]) -> str:
    """A plain-text success table for the terminal."""
    from anchordp3.viz.table import text_table

    rows = summarize(records)
    return text_table(["task", "episodes", "success", "rate", "95% CI"],
                      [[r["task"], r["episodes"], r["successes"], f"{r['rate']:.1%}", f"[{r['ci_low']:.2f}, {r['ci_high']:.2f}]"]
                       for r in rows])
