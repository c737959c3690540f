"""``anchordp3 demo``: the whole system on the embedded tiny default, well under half an hour on
two CPU cores: one run of the whole graph on ``configs/demo.yaml`` (the data stages rollout →
anchors → render → features → write, a picture of one rendered frame once they are done, the
three models trained with ``configs/demo_training.yaml``, closed-loop evaluation ending with the
success table), and
beside it the shipped models (``--models pretrained``, made as their ``SHIPPED.md`` says) on
unseen seeds of each of their tasks, so a newcomer sees a policy do the tasks.
Re-running resumes wherever it stopped.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from anchordp3.pipeline.evaluation import (
    EVAL_DIR,
    PRETRAINED,
    PRETRAINED_DIR,
    episode_records,
    evaluation_summary,
)
from anchordp3.pipeline.evaluation import STAGE as EVAL_STAGE
from anchordp3.pipeline.report import data_summary
from anchordp3.pipeline.runner import RunOptions, run_pipeline
from anchordp3.pipeline.shipping import SHIPPED_FILE
from anchordp3.pipeline.show import show_frame
from anchordp3.pipeline.store import read_manifest
from anchordp3.pipeline.targets import Trained, run_evaluation, training_summary
from anchordp3.pipeline.training import load_training_config, model_status
from anchordp3.schemas.evaluation import EvalOptions, EvaluationConfig
from anchordp3.schemas.run import RunConfig, load_run_config
from anchordp3.schemas.training import MODELS, TrainingConfig

log = logging.getLogger(__name__)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
DEMO_CONFIG = CONFIGS / "demo.yaml"
DEMO_TRAINING = CONFIGS / "demo_training.yaml"


@dataclass(frozen=True)
class DemoOptions:
    """episodes: evaluation episodes per task; max_decisions: cap on policy calls per evaluation
    episode of the demo's own policy (keeps the demo's length bounded: minutes of training do not
    do the tasks, and a failing episode runs to the cap); pretrained_max_decisions: the same for
    the shipped models (a single-arm task takes 9-12 decisions, the block tasks 30-50, the
    bottles about 55); train/evaluate: stop earlier when False;
    training: the training settings (None: the embedded ``configs/demo_training.yaml``);
    pretrained_episodes: unseen seeds per task on which the shipped models are evaluated after the
    demo's own (0: skip)."""

    episodes: int = 1
    max_decisions: int | None = 8
    pretrained_max_decisions: int | None = 60
    workers: int = 2
    train: bool = True
    evaluate: bool = True
    address: str | None = None
    training: TrainingConfig | None = None
    pretrained_episodes: int = 2


PRETRAINED_EVAL_DIR = "eval-pretrained"


def shipped_models_present() -> bool:
    """Whether the package ships trained models (``anchordp3/pretrained/``)."""
    return all((PRETRAINED_DIR / m / "model.pt").is_file() for m in MODELS)


def demo_config(seeds: str | None = None) -> RunConfig:
    """The embedded demo config, optionally with other seeds."""
    cfg = load_run_config(DEMO_CONFIG)
    return cfg.model_copy(update={"seeds": seeds}) if seeds else cfg


def demo_run_config(cfg: RunConfig, opts: DemoOptions) -> RunConfig:
    """The demo as one run config: the data run and, as ``opts`` asks, its training and evaluation."""
    training = (opts.training or load_training_config(DEMO_TRAINING)) if opts.train else None
    evaluation = EvaluationConfig(episodes=opts.episodes, workers=opts.workers, max_decisions=opts.max_decisions) \
        if opts.train and opts.evaluate else None
    return cfg.model_copy(update={"training": training, "evaluation": evaluation})


def run_demo(run_dir: Path, cfg: RunConfig, opts: DemoOptions = DemoOptions()) -> Path:
    """Run the demo into ``run_dir`` (resuming if it exists): one run of the graph (data, then
    training and evaluation as ``opts`` asks), then the shipped models on unseen seeds; returns
    the evaluation report's path (or the frame picture's when evaluation is off)."""
    run_dir = Path(run_dir)
    png = run_dir / "frame.png"
    target = demo_run_config(cfg, opts)

    def phase_done(phase: str, seconds: float) -> None:
        log.info(f"== {phase} done in {seconds:.0f} s")
        if phase == "data":
            log.info(data_summary(run_dir))
            show_frame(run_dir, png, frame=1)
            log.info(f"\nA rendered frame, its masks and its labelled cloud: {png}")

    log.info("== the run: rollout → anchors → render → features → write"
             + (" → the segmenter, the instruction classifier, the anchor diffusion policy" if target.training else "")
             + (" → closed-loop evaluation on held-out seeds and phrasings" if target.evaluation else ""))
    run_pipeline(target, run_dir, RunOptions(address=opts.address, redo=(EVAL_STAGE,), on_phase=phase_done))
    if target.training is not None:
        log.info(training_summary([Trained(n, "done", model_status(run_dir, n).record) for n in MODELS]))
    if target.evaluation is None:
        return png
    folder = run_dir / EVAL_DIR
    log.info("\n" + evaluation_summary(episode_records(folder, target, read_manifest(folder).items)))
    report = folder / "report.md"
    log.info(f"\nReport: {report} | chart: {folder / 'success.png'} | training curves: {run_dir / 'models'}/*/loss.png")
    if opts.pretrained_episodes and shipped_models_present():
        log.info(f"\n== and the shipped policy (`--models pretrained`, {PRETRAINED_DIR / SHIPPED_FILE}) on the same kind of unseen seeds")
        shipped = EvalOptions(models=PRETRAINED, episodes=opts.pretrained_episodes, workers=opts.workers, address=opts.address,
                              max_decisions=opts.pretrained_max_decisions, out=run_dir / PRETRAINED_EVAL_DIR, force=True)
        log.info("\n" + evaluation_summary(run_evaluation(None, shipped)))
        log.info(f"Report: {run_dir / PRETRAINED_EVAL_DIR / 'report.md'}")
    log.info(f"Inspect the run: anchordp3 status {run_dir} | anchordp3 inspect {run_dir} render | anchordp3 show {run_dir} --frame 3")
    return report
