"""Looking into a run directory: per-stage status, a stage's manifest, one item's record.

Read-only: nothing here writes to the run directory, so it is safe while a run is going on
(a record appears once its journal line is durable). Text comes as ``text_table`` tables; every
answer also has a JSON form for scripts.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterable
from pathlib import Path

import yaml
from pydantic import BaseModel, ConfigDict, Field

from anchordp3.pipeline.graph import CONFIG_FILE, fingerprints, translate_layout
from anchordp3.pipeline.store import has_manifest, read_manifest, read_record, read_records, read_stopped, read_summary
from anchordp3.pipeline.evaluation import STAGE as EVAL_STAGE
from anchordp3.pipeline.products import GRAPH, stage_folder
from anchordp3.pipeline.work import DATA_GRAPH, DATA_STAGES, STAGE_DIRS, stage_dir
from anchordp3.dataset.files import file_sha256
from anchordp3.schemas.dataset import INFO_FILE
from anchordp3.schemas.manifest import ItemRecord, StageManifest
from anchordp3.schemas.records import RolloutInfo
from anchordp3.schemas.run import RunConfig, load_run_config
from anchordp3.schemas.training import MODELS
from anchordp3.viz.table import text_table

SLOWEST = 5


class StageStatus(BaseModel):
    """One data stage of a run, at a glance."""

    model_config = ConfigDict(extra="forbid")

    stage: str = Field(description="Stage name.")
    folder: str = Field(description="The stage's folder in the run directory.")
    ran: bool = Field(description="The stage has a manifest (it has run at least partly).")
    done: int = Field(default=0, description="Items with a durable output.")
    failed: int = Field(default=0, description="Items that failed after retries.")
    planned: int = Field(default=0, description="Items the stage will see (known so far).")
    complete: bool = Field(default=False, description="Every planned item has a record.")
    seconds: float = Field(default=0.0, description="Sum of the items' compute seconds.")
    fingerprint: str | None = Field(default=None, description="Digest of the stored fingerprint.")
    stale: bool | None = Field(default=None, description="Stored fingerprint differs from what the run's config.yaml and this code give (None: unknown).")
    changed: list[str] = Field(default_factory=list, description="What differs when stale: code, config, upstream <stage> (Fingerprint.changes).")


def check_run_dir(run_dir: Path) -> Path:
    """``run_dir`` as a Path; FileNotFoundError / ValueError naming it when it is not a run directory."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: no such run directory")
    if not any(has_manifest(stage_dir(run_dir, s)) for s in DATA_STAGES) and not (run_dir / CONFIG_FILE).is_file():
        raise ValueError(f"{run_dir}: not a run directory (no {CONFIG_FILE} and no stage manifests)")
    return run_dir


def stage_name(name: str) -> str:
    """A stage of the graph by its name or its folder's name (``dataset`` → ``write``,
    ``models/policy`` → ``train-policy``); ValueError naming it."""
    if name in GRAPH.names:
        return name
    by_folder = {st.folder: st.name for st in GRAPH.stages}
    if name.rstrip("/") in by_folder:
        return by_folder[name.rstrip("/")]
    raise ValueError(f"unknown stage {name!r}; choose from {', '.join(GRAPH.names)}")


def load_manifest(run_dir: Path, stage: str) -> StageManifest:
    """The stage's manifest with every record; ValueError when the stage has not run."""
    load_manifest_summary(run_dir, stage)
    return read_manifest(stage_folder(run_dir, stage))


def load_manifest_summary(run_dir: Path, stage: str) -> StageManifest:
    """The stage's fingerprint and totals (no records); ValueError when the stage has not run."""
    d = stage_folder(run_dir, stage)
    m = read_summary(d) if d.is_dir() else None
    if m is None:
        raise ValueError(f"stage {stage}: has not run in {run_dir} (no manifest in {d})")
    return m


def run_config(run_dir: Path) -> RunConfig | None:
    """The run's saved resolved config, or None when there is none yet."""
    path = Path(run_dir) / CONFIG_FILE
    return load_run_config(path) if path.is_file() else None


def run_status(run_dir: Path) -> list[StageStatus]:
    """One ``StageStatus`` per data stage, in pipeline order."""
    run_dir = check_run_dir(run_dir)
    cfg = run_config(run_dir)
    summaries = {s: read_summary(d) if (d := stage_dir(run_dir, s)).is_dir() else None for s in DATA_STAGES}
    stored = {s: m.fingerprint for s, m in summaries.items() if m is not None}
    if cfg is not None:  # outputs made under an earlier config layout read as the current one
        stored = translate_layout(cfg, DATA_GRAPH, stored)
    want = None if cfg is None else fingerprints(cfg, DATA_GRAPH)
    out = []
    gone = None  # the first stage without records: every stage after it that has some lost its input
    for s, m in summaries.items():
        if m is None:
            out.append(StageStatus(stage=s, folder=STAGE_DIRS[s], ran=False))
            gone = gone or s
            continue
        digest = stored[s].digest()
        c = m.counts
        changed = [] if want is None else stored[s].changes(want[s])
        if gone is not None:
            changed.append(f"upstream {gone} has no records (its manifest is gone)")
        out.append(StageStatus(stage=s, folder=STAGE_DIRS[s], ran=True, done=c.done, failed=c.failed, planned=c.planned,
                               complete=m.complete, seconds=c.seconds, fingerprint=digest,
                               stale=None if want is None and gone is None else
                               bool(changed),  # a task's change too: its items will be made again
                               changed=changed))
    return out


def product_status(run_dir: Path) -> list[StageStatus]:
    """What was made from a run's data: one ``StageStatus`` per trained model (``models/<name>``)
    and per evaluation folder in the run directory (``eval``, ``eval-*``). A model is stale when
    the dataset (or, for the policy, the segmenter) it was trained on has changed since; an
    evaluation of the run's own models when one of them has. Code and settings staleness is
    ``train``'s and ``eval``'s to tell: they depend on the settings they are given."""
    run_dir = check_run_dir(run_dir)
    dataset = stage_dir(run_dir, "write") / INFO_FILE
    now = {"dataset": file_sha256(dataset) if dataset.is_file() else None}  # what training records as its upstream
    for name in MODELS:  # the files as they are now, whatever replaced them
        model = run_dir / "models" / name / "model.pt"
        now[name] = file_sha256(model) if model.is_file() else None
    out = []
    for label, d in product_folders(run_dir, all_models=True):
        m = read_summary(d) if d.is_dir() else None
        folder = d.relative_to(run_dir).as_posix()
        if m is None:
            out.append(StageStatus(stage=label, folder=folder, ran=False))
            continue
        # upstream digests are whole checksums (training) or their first 16 digits (evaluation);
        # another folder's evaluation may be of any models, so only ``eval`` is compared
        checked = label.startswith("train ") or d.relative_to(run_dir).parts[0] == "eval"
        changed = [f"upstream {k}" for k, v in m.fingerprint.upstream.items()
                   if checked and now.get(k) and v != "ground_truth" and not now[k].startswith(v)]
        c = m.counts
        out.append(StageStatus(stage=label, folder=folder, ran=True, done=c.done, failed=c.failed, planned=c.planned,
                               complete=m.complete, seconds=c.seconds, fingerprint=m.fingerprint.digest(),
                               stale=True if changed else None, changed=changed))
    return out


def product_folders(run_dir: Path, all_models: bool = False) -> list[tuple[str, Path]]:
    """``(label, folder)`` of each trained model (``train <name>``, ``models/<name>``; with
    ``all_models`` also those not trained) and each evaluation folder of a run directory with a
    manifest (``evaluate (<folder>)``: the evaluate stages' ``eval``, ``eval/train``, and other
    evaluations written into the run, ``eval-*``)."""
    run_dir = Path(run_dir)
    models = [(f"train {n}", run_dir / "models" / n) for n in MODELS]
    folders = [run_dir / st.folder for st in GRAPH.batch_stages if st.phase.startswith("eval")]
    folders += [d for d in sorted(run_dir.glob("eval-*")) if d not in folders]
    evals = [(f"{EVAL_STAGE} ({d.relative_to(run_dir).as_posix()})", d) for d in folders if d.is_dir() and has_manifest(d)]
    return [(label, d) for label, d in models if all_models or has_manifest(d)] + evals


def status_table(statuses: list[StageStatus]) -> str:
    """The per-stage table: counts, complete, compute seconds, fingerprint, stale."""
    rows = []
    for st in statuses:
        if not st.ran:
            rows.append([st.stage, "-", "-", "-", "not run", "-", "-", "-"])
            continue
        stale = "-" if st.stale is None else (f"STALE({','.join(dict.fromkeys(c.split()[0] for c in st.changed))})" if st.stale else "current")
        rows.append([st.stage, st.done, st.failed, st.planned, "complete" if st.complete else "incomplete",
                     f"{st.seconds:.1f}", st.fingerprint, stale])
    return text_table(["stage", "done", "failed", "planned", "state", "compute s", "fingerprint", "vs config, code, upstream"], rows)


def run_overview(run_dir: Path) -> str:
    """Heading (run name, tasks, episodes) and the per-stage table."""
    run_dir = check_run_dir(run_dir)
    table = status_table(run_status(run_dir) + product_status(run_dir))
    cfg = run_config(run_dir)
    if cfg is None:
        return f"run {run_dir} (no {CONFIG_FILE})\n\n{table}"
    head = (f"run {run_dir}: {cfg.name}, {len(cfg.tasks)} task(s) × {len(cfg.seed_list)} seed(s) = "
            f"{len(cfg.tasks) * len(cfg.seed_list)} episodes")
    return f"{head}\n\n{table}"


# ---------------------------------------------------------------------------------- one stage
def failure_groups(records: Iterable[ItemRecord]) -> list[tuple[str, int, str, str]]:
    """Failed items grouped by reason: ``(reason, count, example item, its detail)``, most first."""
    return _groups([(r.reason or "?", r.item, _short(r.detail)) for r in records if r.status == "failed"])


def discard_groups(records: Iterable[ItemRecord]) -> list[tuple[str, int, str, str]]:
    """Rollout records done but not kept (the expert failed), grouped by the episode's failure reason."""
    rows = []
    for r in records:
        if r.status == "done" and not (info := r.payload(RolloutInfo)).kept:
            rows.append((info.record.reason or "?", r.item, _short(info.record.detail)))
    return _groups(rows)


def _short(text: str, n: int = 100) -> str:
    return text if len(text) <= n else text[: n - 1] + "…"


def _groups(rows: list[tuple[str, str, str]]) -> list[tuple[str, int, str, str]]:
    counts = Counter(reason for reason, _, _ in rows)
    first: dict[str, tuple[str, str]] = {}
    for reason, item, detail in rows:
        first.setdefault(reason, (item, detail))
    return [(reason, n, *first[reason]) for reason, n in counts.most_common()]


def stage_report(run_dir: Path, stage: str, limit: int = 50) -> str:
    """A stage's manifest as text: summary, fingerprint, slowest items, failure reasons, items.

    limit: items listed at most (0: all)."""
    run_dir = check_run_dir(run_dir)
    stage = stage_name(stage)
    d = stage_folder(run_dir, stage)
    m = load_manifest_summary(run_dir, stage)
    folder = GRAPH[stage].folder
    st = next(s for s in (run_status(run_dir) if stage in DATA_STAGES else product_status(run_dir)) if s.folder == folder)
    c = m.counts
    fp = m.fingerprint
    stale = (("unknown (no config.yaml)" if stage in DATA_STAGES else "current as far as its inputs tell") if st.stale is None
             else (f"STALE: {', '.join(st.changed)} changed" if st.stale else "current"))
    lines = [f"stage {stage} ({d}): {'complete' if m.complete else 'incomplete'}",
             "",
             text_table(["planned", "done", "failed", "compute s", "mean s/item"],
                        [[c.planned, c.done, c.failed, f"{c.seconds:.1f}",
                          f"{c.seconds / (c.done + c.failed):.2f}" if c.done + c.failed else "-"]]),
             "",
             text_table(["fingerprint", "code version", "code hash", "config hash", "upstream", "vs config and code"],
                        [[fp.digest(), fp.code_version, fp.code_hash[:16] or "-", fp.config_hash[:16],
                          ", ".join(f"{k}:{v}" for k, v in fp.upstream.items()) or "-", stale]])]
    slow = read_records(d, slowest=True, limit=SLOWEST)
    if slow:
        lines += ["", "slowest items:", text_table(["item", "seconds", "attempts"], [[r.item, f"{r.seconds:.2f}", r.attempts] for r in slow])]
    fails = failure_groups(read_records(d, status="failed"))
    if fails:
        lines += ["", "failure reasons:", text_table(["reason", "count", "example", "detail"], [list(g) for g in fails])]
    discards = discard_groups(read_stopped(d, RolloutInfo)) if stage == "rollout" else []
    if discards:
        lines += ["", "not kept (the expert failed):", text_table(["reason", "count", "example", "detail"], [list(g) for g in discards])]
    shown = read_records(d, limit=limit)
    lines += ["", "items:", text_table(["item", "status", "attempts", "seconds", "output"],
                                       [[r.item, r.status, r.attempts, f"{r.seconds:.2f}", r.output or "-"] for r in shown])]
    if len(shown) < c.done + c.failed:
        lines.append(f"… {c.done + c.failed - len(shown)} more (--limit 0 lists all, --json gives everything)")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------- one item
def item_records(run_dir: Path, item: str, stage: str | None = None) -> dict[str, ItemRecord]:
    """Stage → the record of ``item``, in one stage or (stage None) in every stage that has it.

    ValueError naming the item when no stage has it."""
    run_dir = check_run_dir(run_dir)
    if stage is not None:
        stage = stage_name(stage)
        load_manifest_summary(run_dir, stage)
        rec = read_record(stage_folder(run_dir, stage), item)
        if rec is None:
            raise ValueError(f"stage {stage}: no item {item!r} in its manifest")
        return {stage: rec}
    out = {}
    for s in GRAPH.names:
        d = stage_folder(run_dir, s)
        rec = read_record(d, item) if has_manifest(d) else None
        if rec is not None:
            out[s] = rec
    if not out:
        raise ValueError(f"no item {item!r} in any stage of {run_dir}")
    return out


def record_text(stage: str, rec: ItemRecord) -> str:
    """Every field of a record, one per line (``info`` as indented JSON)."""
    d = rec.model_dump(mode="json")
    info = d.pop("info")
    width = max(len(k) for k in d)
    lines = [f"[{stage}] {rec.item}"] + [f"  {k.ljust(width)}  {'-' if v is None or v == '' else v}" for k, v in d.items()]
    if info:
        lines.append(f"  {'info'.ljust(width)}  " + json.dumps(info, indent=2).replace("\n", "\n  " + " " * (width + 2)))
    return "\n".join(lines)


# ---------------------------------------------------------------------------------- JSON forms
def inspect_json(run_dir: Path, stage: str | None = None, item: str | None = None) -> str:
    """The JSON answer of ``inspect``: stage statuses, a manifest, or item record(s)."""
    if item is not None:
        recs = item_records(run_dir, item, stage)
        if stage is not None:
            return next(iter(recs.values())).model_dump_json(indent=2)
        return json.dumps({s: r.model_dump(mode="json") for s, r in recs.items()}, indent=2)
    if stage is not None:
        return load_manifest(check_run_dir(run_dir), stage_name(stage)).model_dump_json(indent=2)
    return json.dumps([s.model_dump(mode="json") for s in run_status(run_dir)], indent=2)


def inspect_text(run_dir: Path, stage: str | None = None, item: str | None = None, limit: int = 50) -> str:
    """The text answer of ``inspect``."""
    if item is not None:
        return "\n\n".join(record_text(s, r) for s, r in item_records(run_dir, item, stage).items())
    if stage is not None:
        return stage_report(run_dir, stage, limit)
    return run_overview(run_dir)


# ---------------------------------------------------------------------------------- configs
def resolved_config_yaml(path: Path) -> str:
    """A run config with every default filled in, as YAML (what a run saves as config.yaml)."""
    return yaml.safe_dump(load_run_config(path).model_dump(mode="json"), sort_keys=False)


def check_task_names(cfg: RunConfig) -> None:
    """ValueError naming ``tasks.<i>`` when a task is not one the simulator knows (the schema
    cannot check this: ``schemas/`` does not import ``sim/``)."""
    from anchordp3.sim.tasks import TASKS

    for i, t in enumerate(cfg.tasks):
        if t not in TASKS:
            raise ValueError(f"tasks.{i}: unknown task {t!r}; choose from {', '.join(sorted(TASKS))}")


def config_summary(path: Path) -> str:
    """``OK: …`` line for a valid config (raises like ``load_run_config`` otherwise, or naming
    ``tasks.<i>`` for an unknown task)."""
    cfg = load_run_config(path)
    check_task_names(cfg)
    n, k = len(cfg.tasks), len(cfg.seed_list)
    return f"OK: {path} ({cfg.name}: {n} task(s) × {k} seed(s) = {n * k} episodes)"


SCHEMAS = {"run": RunConfig, "manifest": StageManifest}


def json_schema(what: str) -> str:
    """JSON schema of the run config (``run``) or of a stage manifest (``manifest``)."""
    if what not in SCHEMAS:
        raise ValueError(f"--what: unknown schema {what!r}; choose from {', '.join(SCHEMAS)}")
    return json.dumps(SCHEMAS[what].model_json_schema(), indent=2)
