"""The stages after the data, declared once, and the whole graph: ``GRAPH`` (rollout → anchors →
render → features → write → train-segmenter → train-classifier → train-policy → evaluate →
evaluate-train).

The train stages have one item each (the model), run in the driver (its device, live progress,
resumable checkpoints); the evaluate stages have one item per task and seed, run in a pool of
actors like the data stages, with the same retries and crash triage. Their fingerprints come from
the files they read (the dataset's index, the models' checkpoints). A run does the train stages
when its config has a ``training`` section and the evaluate stages when it has an ``evaluation``
section (``Graph.targets``). The training hooks import their code when they first run, so reading the
graph (``status``, ``inspect``) loads no torch.
"""

from __future__ import annotations

from pathlib import Path

from anchordp3.pipeline.evaluation import (
    EVAL_DIR,
    PROTOCOL_MODULE,
    STAGE,
    TRAIN_DIR,
    TRAIN_STAGE,
    check_evaluation,
    episode_items,
    evaluation_fingerprint,
    report_evaluation,
    run_episode,
    train_target,
)
from anchordp3.pipeline.graph import BatchContext, BatchItem, Graph, Stage, StageOutput
from anchordp3.pipeline.work import DATA_GRAPH
from anchordp3.schemas.manifest import Fingerprint
from anchordp3.schemas.records import EvalEpisodeInfo, ModelInfo
from anchordp3.schemas.run import PoolConfig, RunConfig


def _no_part(cfg: RunConfig) -> dict:
    return {}  # batch stages fingerprint through ``Stage.fingerprint``


# ------------------------------------------------------------------------------------ training
def _train(run_dir: Path, cfg: RunConfig, item: BatchItem) -> StageOutput | None:
    from anchordp3.pipeline.training import train_item

    return train_item(run_dir, cfg, item)


def _model_fingerprint(name: str):
    def fingerprint(ctx: BatchContext, cfg: RunConfig) -> Fingerprint:
        from anchordp3.pipeline.training import model_fingerprint

        return model_fingerprint(ctx, cfg, name)

    return fingerprint


def _check_training(ctx: BatchContext, cfg: RunConfig) -> None:
    from anchordp3.pipeline.training import check_train_stages

    check_train_stages(ctx, cfg)


def _trains(cfg: RunConfig) -> bool:
    return cfg.training is not None


def _train_stage(name: str, after: tuple[str, ...]) -> Stage:
    return Stage(f"train-{name}", f"models/{name}", _train, ModelInfo, f"anchordp3.stages.train_{name}", _no_part,
                 items=lambda cfg: [name], after=after, fingerprint=_model_fingerprint(name), wanted=_trains,
                 check=_check_training, in_driver=True, phase="train")


# ---------------------------------------------------------------------------------- evaluation
def _train_items(cfg: RunConfig) -> list[str]:
    return episode_items(train_target(cfg))


def _train_episode(run_dir: Path, cfg: RunConfig, item: BatchItem) -> StageOutput:
    return run_episode(run_dir, train_target(cfg), item)


def _check_train(ctx: BatchContext, cfg: RunConfig) -> None:
    check_evaluation(ctx, train_target(cfg))


def _train_report(ctx: BatchContext, cfg: RunConfig, records: dict) -> None:
    report_evaluation(ctx, train_target(cfg), records)


def _eval_pool(cfg: RunConfig) -> PoolConfig:
    """``evaluation.workers`` actors of ``cpus_per_worker`` CPUs; on ``device: cuda`` each takes
    an equal share of one GPU (``auto``: of the cluster's GPUs when it has any, ``Stage.gpu_share``)."""
    ev = cfg.evaluation
    if ev is None:
        return PoolConfig()
    gpus = {"cpu": 0.0, "auto": None}.get(ev.device, 1.0 / ev.workers)
    return PoolConfig(workers=ev.workers, cpus=ev.cpus_per_worker, gpus=gpus)


def _evaluates(cfg: RunConfig) -> bool:
    return cfg.evaluation is not None


def _evaluates_training_seeds(cfg: RunConfig) -> bool:
    return cfg.evaluation is not None and cfg.evaluation.train_episodes > 0


EVALUATE = Stage(STAGE, EVAL_DIR, run_episode, EvalEpisodeInfo, PROTOCOL_MODULE, _no_part,
                 items=episode_items, fingerprint=evaluation_fingerprint, wanted=_evaluates, check=check_evaluation,
                 report=report_evaluation, pool=_eval_pool, gpu_share=True, phase="eval")
EVALUATE_TRAIN = Stage(TRAIN_STAGE, f"{EVAL_DIR}/{TRAIN_DIR}", _train_episode, EvalEpisodeInfo, PROTOCOL_MODULE, _no_part,
                       items=_train_items, fingerprint=evaluation_fingerprint, wanted=_evaluates_training_seeds,
                       check=_check_train, report=_train_report, pool=_eval_pool, gpu_share=True, phase="eval-train")

GRAPH = Graph(DATA_GRAPH.stages + (
    _train_stage("segmenter", ("write",)),
    _train_stage("classifier", ()),
    _train_stage("policy", ("write",)),
    EVALUATE,
    EVALUATE_TRAIN,
), former=DATA_GRAPH.former)


def stage_folder(run_dir: Path, stage: str) -> Path:
    """Where stage ``stage`` of the graph keeps its outputs and manifest in ``run_dir``."""
    return Path(run_dir) / GRAPH[stage].folder
