"""Fine-tune the instruction classifier: instruction text -> task id (one of ``TASK_NAMES``).

Trains on the instruction bank's training phrasing families (``generate_instructions``), the
pretrained encoder at ``optim.lr`` and the new head at ``head_lr``; validation measures accuracy
(and loss) on the held-out families, i.e. on sentence structures never seen in training. The
bank, not the episode dataset, is the training data, so this stage does not read the dataset.

``train_classifier(config, out_dir, device)`` trains (resuming when ``out_dir`` holds a
checkpoint) and writes ``model.pt``; ``load_classifier(path)`` gives back a ready module.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from anchordp3.models.classifier import InstructionClassifier, classification_loss
from anchordp3.models.device import autocast, needs_grad_scaler, seed_everything
from anchordp3.models.instructions import generate_instructions
from anchordp3.models.optim import make_lr_schedule, make_optimizer
from anchordp3.schemas.tasks import TASK_NAMES
from anchordp3.schemas.training import ClassifierConfig, TrainingConfig
from anchordp3.stages.training_loop import (
    TrainingJob,
    TrainResult,
    batches_per_epoch,
    epoch_batches,
    load_checkpoint,
    optimizer_step,
    run_training,
)

log = logging.getLogger(__name__)

KIND = "classifier"
PROGRESS_S = 10.0  # seconds between progress lines while scoring the held-out instructions
EVAL_BATCH = 256


def _quiet_transformers() -> None:
    """No "Loading weights" progress bars from transformers in the training log."""
    from transformers.utils import logging

    logging.disable_progress_bar()


class ClassifierJob(TrainingJob):
    """The classifier's fine-tuning on the instruction bank (see ``TrainingJob``)."""

    name = KIND

    def __init__(self, config: TrainingConfig, device: torch.device) -> None:
        self.cfg, self.device, self.seed = config.classifier, device, config.seed
        self.mixed_precision = config.mixed_precision
        _quiet_transformers()
        bank = generate_instructions(self.cfg.instructions)
        self.train_texts, train_y = bank.texts_and_labels("train")
        self.val_texts, val_y = bank.texts_and_labels("val")
        self.train_y, self.val_y = torch.tensor(train_y), torch.tensor(val_y)
        self.val_families = sorted(bank.val_families)
        optim = self.cfg.optim
        self.steps_per_epoch = batches_per_epoch(len(self.train_texts), optim.batch_size)
        self.total_steps = optim.total_steps(len(self.train_texts))
        seed_everything(self.seed)
        self.model = InstructionClassifier(self.cfg.model).to(device).train()
        self.model.freeze_below(self.cfg.tune_layers)
        self.params = [p for p in self.model.parameters() if p.requires_grad]
        groups = self.model.parameter_groups(optim.lr, self.cfg.head_lr, optim.weight_decay)
        self.optimizer = make_optimizer(groups, optim)
        self.schedule = make_lr_schedule(self.optimizer, optim, self.total_steps)
        self.scaler = torch.amp.GradScaler("cuda") if needs_grad_scaler(device, self.mixed_precision) else None

    def batches(self, start_step: int) -> Iterator[tuple[list[str], torch.Tensor]]:
        for idx in epoch_batches(len(self.train_texts), self.cfg.optim.batch_size, self.seed, start_step):
            yield [self.train_texts[i] for i in idx], self.train_y[idx]

    def train_step(self, batch: tuple[list[str], torch.Tensor]) -> dict[str, float]:
        texts, labels = batch
        with autocast(self.device, self.mixed_precision):
            logits = self.model.logits(texts)
        loss = classification_loss(logits, labels.to(self.device))
        optimizer_step(loss, self.optimizer, self.schedule, self.scaler, self.params, self.cfg.optim.grad_clip_norm)
        accuracy = float((logits.detach().argmax(-1).cpu() == labels).float().mean())
        return {"loss": float(loss.detach()), "accuracy": accuracy, "lr": self.schedule.get_last_lr()[0]}

    @torch.no_grad()
    def evaluate(self) -> dict[str, float]:
        """``loss`` and ``accuracy`` over every instruction of the held-out phrasing families (a
        progress line every ``PROGRESS_S`` seconds: on a CPU this takes a minute or more)."""
        self.model.eval()
        total, correct = 0.0, 0
        t0 = last = time.perf_counter()
        try:
            for i in range(0, len(self.val_texts), EVAL_BATCH):
                if time.perf_counter() - last > PROGRESS_S:
                    last, rate = time.perf_counter(), i / (time.perf_counter() - t0)
                    log.info(f"classifier: scored {i}/{len(self.val_texts)} held-out instructions, {rate:.0f}/s, "
                             f"ETA {(len(self.val_texts) - i) / rate:.0f} s")
                y = self.val_y[i:i + EVAL_BATCH]
                with autocast(self.device, self.mixed_precision):
                    logits = self.model.logits(self.val_texts[i:i + EVAL_BATCH])
                total += float(classification_loss(logits, y.to(self.device))) * len(y)
                correct += int((logits.argmax(-1).cpu() == y).sum())
        finally:
            self.model.train()
        n = max(len(self.val_texts), 1)
        return {"loss": total / n, "accuracy": correct / n}

    def export(self) -> dict[str, Any]:
        return {
            "kind": KIND,
            "config": self.cfg.model.model_dump(mode="json"),
            "training": self.cfg.model_dump(mode="json"),
            "weights_dir": self.cfg.model.weights_dir,  # as configured (None: the bundled MiniLM), never a machine path
            "state_dict": self.model.changed_state_dict(),
            "partial_state_dict": True,  # tensors equal to the pretrained encoder's load from weights_dir
            "tasks": list(TASK_NAMES),
            "val_families": self.val_families,
        }


def train_classifier(config: TrainingConfig, out_dir: Path, device: torch.device, fingerprint: str = "", stop_at: int | None = None) -> TrainResult:
    """Fine-tune (or resume) the classifier into ``out_dir`` (see ``run_training``)."""
    job = ClassifierJob(config, device)
    log.info(f"classifier: {len(job.train_texts)} train / {len(job.val_texts)} held-out instructions "
        f"(families {', '.join(job.val_families)}), {job.total_steps} steps of {config.classifier.optim.batch_size} on {device}")
    return run_training(job, out_dir, config.loop, fingerprint, stop_at)


def load_classifier(path: Path, device: torch.device | str = "cpu") -> InstructionClassifier:
    """The fine-tuned classifier of a ``model.pt`` in eval mode on ``device``. Its tokenizer and
    architecture come from the encoder folder named in the checkpoint's config (the bundled
    MiniLM by default), its weights from the checkpoint."""
    ckpt = load_checkpoint(path)
    if ckpt.get("kind") != KIND:
        raise ValueError(f"{path}: not a classifier checkpoint (kind {ckpt.get('kind')!r})")
    _quiet_transformers()
    model = InstructionClassifier(ClassifierConfig.model_validate(ckpt["config"]))
    missing, unexpected = model.load_state_dict(ckpt["state_dict"], strict=not ckpt.get("partial_state_dict", False))
    if unexpected or any(not k.startswith("encoder.") for k in missing):
        raise ValueError(f"{path}: classifier weights do not fit the encoder in {model.weights_dir}")
    return model.to(device).eval()
