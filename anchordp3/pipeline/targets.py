"""The everyday targets of the graph: train a run's models, evaluate models. Each is one call of
the runner (``runner.run_pipeline``) on the stages it names, with the run config's section set
(``training``, ``evaluation``); the recipe, the experiments and the demo run the whole graph the
same way.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from anchordp3.pipeline.evaluation import (
    EVAL_DIR,
    STAGE,
    TRAIN_DIR,
    TRAIN_STAGE,
    episode_items,
    episode_records,
    eval_run_config,
    models_folder,
)
from anchordp3.pipeline.graph import CONFIG_FILE
from anchordp3.pipeline.products import GRAPH
from anchordp3.pipeline.runner import RunOptions, run_pipeline
from anchordp3.pipeline.store import read_manifest
from anchordp3.schemas.evaluation import EvalOptions
from anchordp3.schemas.manifest import ItemRecord
from anchordp3.schemas.records import ModelInfo
from anchordp3.schemas.run import RunConfig, load_run_config
from anchordp3.schemas.training import MODELS, TrainingConfig


# ------------------------------------------------------------------------------------ training
@dataclass
class Trained:
    """One model's outcome in a ``train_models`` call: ``status`` is ``trained``, ``up-to-date`` or
    ``stopped`` (``stop_at`` reached; resumable, at ``step`` of ``total_steps``)."""

    name: str
    status: str
    record: ItemRecord | None
    step: int | None = None
    total_steps: int | None = None


def train_models(run_dir: Path, names: Sequence[str], cfg: TrainingConfig, force: bool = False,
                 stop_at: dict[str, int] | None = None, keep_outputs: bool = False) -> list[Trained]:
    """Train models ``names`` (in ``MODELS`` order) of the run at ``run_dir``: its train stages,
    with ``cfg`` as the run config's ``training`` section (see ``pipeline.training``).

    force: retrain a model whose fingerprint changed (its folder is emptied first); a model that is
    up to date stays as it is.
    stop_at: ``{name: step}``: stop that model there with a resumable checkpoint (tests, demos).
    keep_outputs: keep a model that only other code trained (same settings and data)."""
    from anchordp3.pipeline.training import model_status, stage_name

    run_dir = Path(run_dir)
    unknown = [n for n in names if n not in MODELS]
    if unknown:
        raise ValueError(f"model: unknown {unknown}; choose from {list(MODELS)} or all")
    if not (run_dir / CONFIG_FILE).is_file():
        raise FileNotFoundError(f"{run_dir}: not a run directory (no {CONFIG_FILE}); run `anchordp3 run CONFIG --run-dir {run_dir}` first")
    run_cfg = load_run_config(run_dir / CONFIG_FILE).model_copy(update={"training": cfg})
    names = [n for n in MODELS if n in names]
    before = {n: model_status(run_dir, n).record for n in names}
    run_pipeline(run_cfg, run_dir, RunOptions(stages=tuple(stage_name(n) for n in names), force=force,
                                                  keep_outputs=keep_outputs, stop_at=dict(stop_at or {})))
    out = []
    for n in names:
        st = model_status(run_dir, n)
        if st.state == "done":
            out.append(Trained(n, "up-to-date" if st.record == before[n] else "trained", st.record))
        else:
            out.append(Trained(n, "stopped", None, *_checkpoint_step(run_dir, n)))
    return out


def _checkpoint_step(run_dir: Path, name: str) -> tuple[int | None, int | None]:
    """The step and total steps of model ``name``'s resumable checkpoint (None when it has none)."""
    from anchordp3.pipeline.training import model_dir
    from anchordp3.stages.training_loop import LAST_CHECKPOINT, load_checkpoint

    path = model_dir(run_dir, name) / "checkpoints" / LAST_CHECKPOINT
    if not path.is_file():
        return None, None
    ck = load_checkpoint(path)
    return ck.get("step"), ck.get("total_steps")


def training_summary(results: Sequence[Trained]) -> str:
    """A table of the models of one ``train_models`` call: status, steps, seconds, metrics, checkpoint."""
    from anchordp3.stages.training_loop import format_metrics
    from anchordp3.viz.table import text_table

    rows = []
    for t in results:
        if t.status == "stopped":
            rows.append([t.name, t.status, f"{t.step}/{t.total_steps}", "", "", ""])
            continue
        info = t.record.payload(ModelInfo) if t.record else None
        overall = {k: v for k, v in info.metrics.items() if "/" not in k} if info else {}  # per-task ones: metrics.csv
        rows.append([t.name, t.status, info.steps if info else "", info.train_seconds if info else "",
                     format_metrics(overall) if info else "", t.record.output if t.record else ""])
    return text_table(["model", "status", "steps", "train s", "validation", "checkpoint"], rows)


# ---------------------------------------------------------------------------------- evaluation
def run_evaluation(run_dir: Path | None, opts: EvalOptions = EvalOptions(), cfg: RunConfig | None = None) -> list[dict]:
    """Evaluate (or finish evaluating) the models (``opts.models``, else the run's) on every task
    (``opts.tasks``, else the config's) and seed (``evaluation.selected_seeds``): the evaluate
    stage (and ``evaluate-train`` with ``opts.train_episodes``). Returns the per-episode records
    (dicts of ``EvalRecord`` with ``seen``: the seed was a training seed) in task, seed order.
    Output in ``evaluation_folder``; cfg: the run config (default: the run's, or the one shipped
    beside the models). Without a run, the evaluation folder is the runner's directory."""
    models_dir = models_folder(run_dir, opts.models)
    target = opts.target()
    cfg = eval_run_config(run_dir, models_dir, target) if cfg is None else cfg.model_copy(update={"evaluation": target})
    episode_items(cfg)  # bad seeds: refused before any folder exists
    folder = evaluation_folder(run_dir, opts)
    home = Path(run_dir) if run_dir is not None else folder
    graph = GRAPH.with_folder(STAGE, folder.resolve()).with_folder(TRAIN_STAGE, (folder / TRAIN_DIR).resolve())
    stages = (STAGE, TRAIN_STAGE) if opts.train_episodes else (STAGE,)
    run_pipeline(cfg, home, RunOptions(stages=stages, force=opts.force, keep_outputs=opts.keep_outputs, address=opts.address),
                 graph=graph)
    return episode_records(folder, cfg, read_manifest(folder).items)


def evaluation_folder(run_dir: Path | None, opts: EvalOptions) -> Path:
    """Where an evaluation goes: ``opts.out``, else ``<run>/eval``, else ``runs/eval-<models folder name>``."""
    if opts.out is not None:
        return Path(opts.out)
    if run_dir is not None:
        return Path(run_dir) / EVAL_DIR
    return Path("runs") / f"eval-{models_folder(None, opts.models).resolve().name}"
