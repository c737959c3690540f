"""Optimizer and learning-rate schedule from an ``OptimizerConfig`` (DP3: AdamW, warm-up, cosine)."""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch

from anchordp3.schemas.training import OptimizerConfig


def make_optimizer(params: Iterable[torch.nn.Parameter] | Iterable[dict], config: OptimizerConfig) -> torch.optim.AdamW:
    """AdamW with ``config``'s lr, betas and weight decay (parameter groups may override them)."""
    return torch.optim.AdamW(params, lr=config.lr, betas=config.betas, weight_decay=config.weight_decay)


def make_lr_schedule(optimizer: torch.optim.Optimizer, config: OptimizerConfig, total_steps: int) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up over ``config.warmup_steps`` then cosine to 0 at ``total_steps`` (or constant).

    Call ``.step()`` once per optimizer step."""
    warmup = min(config.warmup_steps, max(total_steps - 1, 0))

    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        if config.schedule == "constant":
            return 1.0
        progress = min(1.0, (step - warmup) / max(1, total_steps - warmup))
        return 0.5 * (1.0 + math.cos(math.pi * progress))

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
