"""Closed-loop evaluation of a run's trained models: episodes in parallel in Ray actors.

Seeds are disjoint from every training seed (``max(training seeds) + 1000 + i``) and the
instructions come from held-out phrasing families. Output under ``<run>/eval/``:
``records.sqlite`` (the manifest: one record per episode, resumable), ``episodes/<task>/<seed>.json``,
``episodes.parquet`` (the table), ``success.png`` (success rate per task with 95 % Wilson
intervals), ``strips/<task>/<seed>.png`` (the head camera at each decision of a few episodes)
and ``report.md``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path

import ray

import anchordp3
from anchordp3.dataset.files import file_sha256
from anchordp3.logs import Capture, WorkerRecord, replay, to_file
from anchordp3.pipeline.actors import FAULTS_ENV, InjectedFault, one_line, parse_faults
from anchordp3.pipeline.codehash import code_hash
from anchordp3.pipeline.runner import ensure_ray
from anchordp3.pipeline.store import ManifestStore, StaleStageError, read_summary
from anchordp3.schemas.manifest import Fingerprint, ItemRecord
from anchordp3.schemas.records import EvalEpisodeInfo
from anchordp3.schemas.episode import parse_seeds
from anchordp3.schemas.evaluation import DEFAULT_EPISODES, EvalOptions
from anchordp3.schemas.run import RunConfig, config_hash, load_run_config
from anchordp3.stages.files import atomic_write_bytes

log = logging.getLogger(__name__)

EVAL_DIR = "eval"
STAGE = "evaluate"
LOG_FILE = "eval.log"  # the evaluation's messages, its workers' included, appended per invocation
SEED_OFFSET = 1000
MODEL_NAMES = ("segmenter", "classifier", "policy")
EPISODE_RETRIES = 2  # an episode whose worker dies (on a new worker) or that raises is tried again at most this many times
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


def eval_run_config(run_dir: Path | None, models_dir: Path, opts: EvalOptions) -> RunConfig:
    """The data config the models were trained on (the run's ``config.yaml``, or the
    ``run_config.yaml`` shipped beside a models folder), restricted to ``opts.tasks`` and set to
    ``opts.preset``."""
    for path in ([Path(run_dir) / "config.yaml"] if run_dir is not None else []) + [models_dir / RUN_CONFIG_FILE,
                                                                                       models_dir.parent / "config.yaml"]:
        if path.is_file():
            cfg = load_run_config(path)
            break
    else:
        raise FileNotFoundError(f"{models_dir}: no {RUN_CONFIG_FILE} beside the models and no run config; give --run-dir")
    update: dict = {}
    if opts.tasks:
        unknown = sorted(set(opts.tasks) - set(cfg.tasks))
        if unknown:
            raise ValueError(f"--tasks: {unknown} not among the tasks the models were trained on ({cfg.tasks})")
        update["tasks"] = list(opts.tasks)
    if opts.preset:
        update["preset"] = opts.preset
    return RunConfig.model_validate({**cfg.model_dump(mode="json"), **update}) if update else cfg




def selected_seeds(cfg: RunConfig, opts: EvalOptions) -> list[int]:
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


def actor_device(device: str, workers: int) -> tuple[str, float]:
    """The torch device of the evaluation actors and the GPUs each reserves: ``auto`` takes CUDA
    when the Ray cluster has GPUs (shared equally among ``workers``), else the CPU."""
    if device not in ("auto", "cpu", "cuda"):
        raise ValueError(f"--device: expected auto, cpu or cuda, got {device!r}")
    gpus = ray.cluster_resources().get("GPU", 0)
    if device == "cuda" and gpus <= 0:
        raise ValueError("--device: cuda asked for, but the Ray cluster has no GPU")
    if device == "cpu" or gpus <= 0:
        return "cpu", 0.0
    return "cuda", min(1.0, gpus / workers)


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


@ray.remote
class EvalWorker:
    """Loads the models once, then runs episodes one at a time."""

    def __init__(self, models_dir: str, out_dir: str, cfg_json: str, device: str, ddim_steps: int | None = None,
                 samples: int = 1, faults: str = ""):
        import torch

        from anchordp3.stages.evaluate import EvalModels

        torch.set_num_threads(1)
        self.out = Path(out_dir)
        self.cfg = RunConfig.model_validate_json(cfg_json)
        self.models = EvalModels(Path(models_dir), device, ddim_steps, samples)
        self.faults = parse_faults(faults)

    def run(self, task: str, seed: int, max_decisions: int | None, strip: str | None,
            through: str, attempt: int = 1) -> tuple[dict, tuple[WorkerRecord, ...]]:
        """One episode: its ``EvalRecord`` as a dict, and what was logged while it ran. Injected faults
        (``ANCHORDP3_INJECT_FAULTS``): ``evaluate:<task>/<seed>:n`` raises in the episode's first
        ``n`` attempts, ``...:n:crash`` ends this process at the episode's second decision."""
        from anchordp3.stages.evaluate import evaluate_episode

        n, crash = self.faults.get((STAGE, episode_item(task, seed)), (0, False))
        if attempt <= n and not crash:
            raise InjectedFault(f"injected fault in evaluate {episode_item(task, seed)} (attempt {attempt})")
        watch = (lambda ep, decision, points, pred: decision == 1 and os._exit(1)) if crash and attempt <= n else None
        path = self.out / strip if strip else None
        with Capture() as cap:
            rec = evaluate_episode(task, seed, self.models, self.cfg, max_decisions, path, through, watch).to_dict()
        return rec, tuple(cap.records)


def check_models(models_dir: Path) -> None:
    """Every model file of ``models_dir`` is a readable checkpoint of its kind: bad input gets a
    one-line error naming the file here, in the driver, not a traceback from an actor."""
    from anchordp3.stages.training_loop import load_checkpoint

    for name in MODEL_NAMES:
        path = Path(models_dir) / name / "model.pt"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no trained {name}; run `anchordp3 train all --run-dir RUN` first")
        kind = load_checkpoint(path).get("kind")
        if kind != name:
            raise ValueError(f"{path}: not a {name} checkpoint (kind {kind!r})")


def _fingerprint(models_dir: Path, cfg: RunConfig, opts: EvalOptions) -> Fingerprint:
    upstream = {}
    check_models(models_dir)
    for name in MODEL_NAMES:
        upstream[name] = file_sha256(Path(models_dir) / name / "model.pt")[:16]
    part = {"world": cfg.world().model_dump(mode="json"), "features": cfg.features.model_dump(mode="json"),
            "max_decisions": opts.max_decisions, "through": opts.through, "plan": cfg.anchors.plan, "dense": cfg.anchors.dense.model_dump(mode="json")}
    if opts.ddim_steps is not None:  # only when set: evaluations with the policy's own steps keep their fingerprint
        part["ddim_steps"] = opts.ddim_steps
    if opts.samples != 1:
        part["samples"] = opts.samples
    return Fingerprint(code_version=anchordp3.__version__, code_hash=code_hash([PROTOCOL_MODULE]),  # read, not imported: the driver stays free of the simulator
                       config_hash=config_hash(part), upstream=upstream)


def run_evaluation(run_dir: Path | None, opts: EvalOptions = EvalOptions(), cfg: RunConfig | None = None) -> list[dict]:
    """Evaluate (or finish evaluating) the models (``opts.models``, else the run's) on every task
    (``opts.tasks``, else the config's) and seed (``selected_seeds``); returns the per-episode
    records (dicts of ``EvalRecord`` with ``seen``: the seed was a training seed) in task, seed
    order. Output in ``opts.out`` (else ``<run>/eval``)."""
    models_dir = models_folder(run_dir, opts.models)
    cfg = cfg or eval_run_config(run_dir, models_dir, opts)
    out = evaluation_folder(run_dir, opts)
    fp = _fingerprint(models_dir, cfg, opts)
    seeds = selected_seeds(cfg, opts)  # before the folder exists: bad seeds create nothing
    with to_file(out / LOG_FILE):
        return _evaluate(models_dir, out, fp, cfg, opts, seeds)


def evaluation_folder(run_dir: Path | None, opts: EvalOptions) -> Path:
    """Where an evaluation goes: ``opts.out``, else ``<run>/eval``, else ``runs/eval-<models folder name>``."""
    if opts.out is not None:
        return Path(opts.out)
    if run_dir is not None:
        return Path(run_dir) / EVAL_DIR
    return Path("runs") / f"eval-{models_folder(None, opts.models).resolve().name}"


def _evaluate(models_dir: Path, out: Path, fp: Fingerprint, cfg: RunConfig, opts: EvalOptions, seeds: list[int]) -> list[dict]:
    try:
        store = ManifestStore(out, STAGE, fp)
    except StaleStageError:
        stored = read_summary(out)
        changed = ", ".join(stored.fingerprint.changes(fp)) if stored is not None else "fingerprint"
        if not opts.force:
            raise StaleStageError(f"--out: {out} holds an evaluation of other models, settings or code ({changed} changed); "
                                  "give another folder, or --force to start over") from None
        log.info(f"evaluate: {changed} changed since the last evaluation in {out}; starting over (--force)")
        store = ManifestStore(out, STAGE, fp, reset=True)
    todo = [(t, s) for t in cfg.tasks for s in seeds]
    pending = [ep for ep in todo if not store.done(episode_item(*ep))]
    log.info(f"evaluate: {len(todo)} episodes ({len(todo) - len(pending)} already done), {opts.workers} workers")
    if pending:
        ensure_ray(opts.address)
        n = max(1, min(opts.workers, len(pending)))
        device, gpus = actor_device(opts.device, n)
        faults = os.environ.get(FAULTS_ENV, "")

        def new_worker():
            return EvalWorker.options(num_cpus=opts.cpus_per_worker, num_gpus=gpus).remote(
                str(models_dir), str(out), cfg.model_dump_json(), device, opts.ddim_steps, opts.samples, faults)

        workers = [new_worker() for _ in range(n)]
        strip_seeds = set(seeds[:opts.strips])
        attempts: dict[tuple[str, int], int] = {}

        def submit(w, ep):
            strip = f"strips/{ep[0]}/{ep[1]:06d}.png" if ep[1] in strip_seeds else None
            attempts[ep] = attempts.get(ep, 0) + 1
            running[w.run.remote(ep[0], ep[1], opts.max_decisions, strip, opts.through, attempts[ep])] = (w, ep)

        queue = list(pending)
        running: dict = {}
        t0 = time.perf_counter()
        for w in workers:
            if queue:
                submit(w, queue.pop(0))
        finished = 0
        try:
            while running:
                [ref], _ = ray.wait(list(running), num_returns=1)
                w, ep = running.pop(ref)
                try:
                    rec, logs = ray.get(ref)
                except ray.exceptions.RayActorError as e:  # the worker died mid-episode (killed, out of memory, node lost)
                    workers.remove(w)
                    if attempts[ep] > EPISODE_RETRIES:
                        raise RuntimeError(f"evaluate {episode_item(*ep)}: its worker died in each of {attempts[ep]} attempts "
                                           f"({one_line(e)})") from None
                    log.warning(f"evaluate: {ep[0]} seed {ep[1]}: its worker died ({one_line(e)}); the episode starts "
                                f"again on a new worker (attempt {attempts[ep] + 1})")
                    w = new_worker()
                    workers.append(w)
                    submit(w, ep)
                    continue
                except ray.exceptions.RayTaskError as e:  # the episode raised: retried, then recorded as failed
                    if attempts[ep] <= EPISODE_RETRIES:
                        log.warning(f"evaluate: {ep[0]} seed {ep[1]}: {one_line(e)}; retrying (attempt {attempts[ep] + 1})")
                        submit(w, ep)
                        continue
                    cause = e.cause if isinstance(e.cause, BaseException) else e
                    store.record(ItemRecord(item=episode_item(*ep), status="failed", attempts=attempts[ep],
                                            reason=type(cause).__name__, detail=one_line(cause)))
                    log.error(f"evaluate: {ep[0]} seed {ep[1]}: failed in each of {attempts[ep]} attempts: {one_line(cause)}")
                    if queue:
                        submit(w, queue.pop(0))
                    continue
                replay(logs, f"evaluate {episode_item(*ep)}")
                rel = f"episodes/{ep[0]}/{ep[1]:06d}.json"
                atomic_write_bytes(out / rel, json.dumps(rec, indent=1).encode())
                store.record(ItemRecord(item=episode_item(*ep), status="done", output=rel, checksum=file_sha256(out / rel),
                                        seconds=rec["seconds"], info=EvalEpisodeInfo(
                                            success=rec["success"], steps=rec["steps"], decisions=rec["decisions"],
                                            failure=rec["failure"], unmet=rec.get("unmet", "")).model_dump(mode="json")))
                finished += 1
                log.info(f"evaluate: {ep[0]} seed {ep[1]}: {'success' if rec['success'] else rec['failure']} "
                    f"({rec['steps']} steps, {rec['decisions']} decisions) [{finished}/{len(pending)}, "
                    f"{time.perf_counter() - t0:.0f} s]")
                if queue:
                    submit(w, queue.pop(0))
        finally:
            for w in workers:
                ray.kill(w)
    store.finish(len(todo), complete=all(store.done(episode_item(*ep)) for ep in todo))
    train_seeds = cfg.seed_list
    records = [{**json.loads((out / store.items[episode_item(*ep)].output).read_text()), "seen": ep[1] in train_seeds}
               for ep in todo if store.done(episode_item(*ep))]
    errors = [store.items[episode_item(*ep)] for ep in todo if not store.done(episode_item(*ep))]
    if errors:  # the report covers the episodes that ran; these are named, and the next run tries them again
        log.error(f"evaluate: {len(errors)} of {len(todo)} episodes failed with an error (not in the report; run again "
                  f"to retry them): " + "; ".join(f"{r.item}: {r.reason}: {r.detail}" for r in errors[:5]))
    store.close()
    write_reports(out, records, cfg, opts)
    return records


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
             f"{len(records)} episodes on seeds disjoint from training (training seeds {cfg.seeds}; evaluation seeds "
             f"from {min(r['seed'] for r in records) if records else '-'}), instructions from held-out phrasing families"
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
