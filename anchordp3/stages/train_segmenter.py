"""Train the PointNet++ segmenter: ``(N, 11)`` points -> per-point task-critical probability.

Binary cross-entropy on the simulator's per-point labels of the training split; the input
normalizer is fitted from the dataset's point statistics (min/max per channel). Validation: loss
and IoU / precision / recall of the critical class over every validation sample.

``train_segmenter(dataset, config, out_dir, device)`` trains (resuming when ``out_dir`` holds a
checkpoint) and writes ``model.pt``; ``load_segmenter(path)`` gives back a ready module.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch

from anchordp3.dataset.reader import ShardedDataset
from anchordp3.dataset.torch_data import SplitDataset
from anchordp3.models.device import autocast, needs_grad_scaler, seed_everything
from anchordp3.models.optim import make_lr_schedule, make_optimizer
from anchordp3.models.segmenter import PointNet2Segmenter, SegmentationCounts, segmentation_loss
from anchordp3.schemas.training import SegmenterConfig, TrainingConfig
from anchordp3.stages.training_loop import (
    TrainingJob,
    TrainResult,
    batches_per_epoch,
    eval_batches,
    load_checkpoint,
    optimizer_step,
    run_training,
    to_device,
    train_batches,
)

log = logging.getLogger(__name__)

KIND = "segmenter"
SEGMENTER_KEYS = ("points", "labels")


def stats_limits(stats: Mapping[str, Any], key: str) -> dict[str, list[float]]:
    """``{"min", "max"}`` of array ``key`` from a dataset's ``stats`` (``NormStats`` or plain dicts)."""
    if key not in stats:
        raise ValueError(f"dataset stats: no {key!r} statistics (have {sorted(stats)})")
    s = stats[key]
    get = s.get if isinstance(s, Mapping) else lambda k: getattr(s, k)
    return {"min": list(get("min")), "max": list(get("max"))}


class SegmenterJob(TrainingJob):
    """The segmenter's training on one dataset (see ``TrainingJob``)."""

    name = KIND

    def __init__(self, data: ShardedDataset, config: TrainingConfig, device: torch.device) -> None:
        self.cfg, self.device, self.data = config.segmenter, device, data
        self.seed, self.loop = config.seed, config.loop
        self.mixed_precision = config.mixed_precision
        self.train_ds = SplitDataset(data, "train", keys=SEGMENTER_KEYS)
        self.val_ds = SplitDataset(data, "validation", keys=SEGMENTER_KEYS)
        optim = self.cfg.optim
        self.steps_per_epoch = batches_per_epoch(len(self.train_ds), optim.batch_size)
        self.total_steps = optim.total_steps(len(self.train_ds))
        seed_everything(self.seed)
        self.model = PointNet2Segmenter(self.cfg.model)
        self.model.set_normalizer(stats_limits(data.stats, "points"))
        self.model.to(device).train()
        self.params = list(self.model.parameters())
        self.optimizer = make_optimizer(self.params, optim)
        self.schedule = make_lr_schedule(self.optimizer, optim, self.total_steps)
        self.scaler = torch.amp.GradScaler("cuda") if needs_grad_scaler(device, self.mixed_precision) else None

    def batches(self, start_step: int) -> Iterator[dict[str, torch.Tensor]]:
        return train_batches(self.train_ds, self.cfg.optim.batch_size, self.seed, start_step, self.loop.loader_workers,
                             pin_memory=self.device.type == "cuda")

    def train_step(self, batch: Mapping[str, torch.Tensor]) -> dict[str, float]:
        b = to_device(batch, self.device)
        with autocast(self.device, self.mixed_precision):
            logits = self.model(b["points"])
        loss = segmentation_loss(logits, b["labels"], self.cfg.pos_weight)
        optimizer_step(loss, self.optimizer, self.schedule, self.scaler, self.params, self.cfg.optim.grad_clip_norm)
        return {"loss": float(loss.detach()), "lr": self.schedule.get_last_lr()[0]}

    @torch.no_grad()
    def evaluate(self) -> dict[str, float]:
        """``loss`` (mean BCE per point), ``iou``, ``precision``, ``recall`` of the critical class
        over the validation split; ``{}`` when the split is empty."""
        if len(self.val_ds) == 0:
            return {}
        self.model.eval()
        counts, total, n = SegmentationCounts(), 0.0, 0
        try:
            for batch in eval_batches(self.val_ds, self.cfg.optim.batch_size):
                b = to_device(batch, self.device)
                with autocast(self.device, self.mixed_precision):
                    logits = self.model(b["points"])
                total += float(segmentation_loss(logits, b["labels"], self.cfg.pos_weight)) * len(logits)
                n += len(logits)
                counts.add(logits, b["labels"], self.cfg.threshold)
        finally:
            self.model.train()
        return {"loss": total / n, **counts.as_dict()}

    def export(self) -> dict[str, Any]:
        return {
            "kind": KIND,
            "config": self.cfg.model.model_dump(mode="json"),
            "training": self.cfg.model_dump(mode="json"),
            "threshold": self.cfg.threshold,
            "state_dict": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
            "normalizer": {k: v.tolist() for k, v in self.model.normalizer.stats().items()},
            "tasks": list(self.data.tasks),
        }


def train_segmenter(data: ShardedDataset, config: TrainingConfig, out_dir: Path, device: torch.device,
                    fingerprint: str = "", stop_at: int | None = None) -> TrainResult:
    """Train (or resume) the segmenter on ``data`` into ``out_dir`` (see ``run_training``)."""
    job = SegmenterJob(data, config, device)
    log.info(f"segmenter: {len(job.train_ds)} train / {len(job.val_ds)} validation samples, {job.total_steps} steps "
        f"of {config.segmenter.optim.batch_size} on {device}")
    return run_training(job, out_dir, config.loop, fingerprint, stop_at)


def load_segmenter(path: Path, device: torch.device | str = "cpu") -> PointNet2Segmenter:
    """The trained segmenter of a ``model.pt`` in eval mode on ``device`` (normalizer included)."""
    ckpt = load_checkpoint(path)
    if ckpt.get("kind") != KIND:
        raise ValueError(f"{path}: not a segmenter checkpoint (kind {ckpt.get('kind')!r})")
    model = PointNet2Segmenter(SegmenterConfig.model_validate(ckpt["config"]))
    model.load_state_dict(ckpt["state_dict"])
    return model.to(device).eval()
