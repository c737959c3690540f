"""Exponential moving average of a model's weights, used for inference (Diffusion Policy's schedule).

``decay(step) = clamp(1 - (1 + step / inv_gamma) ** -power, min_value, max_value)`` with
``step`` counted from ``update_after_step``; early on the average follows the model closely, later
it changes slowly (up to 0.9999). Buffers (e.g. normalizers) are copied, not averaged.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn

from anchordp3.schemas.training import EMAConfig


class ExponentialMovingAverage(nn.Module):
    """Holds ``averaged_model``, a frozen copy of the model in eval mode; ``step(model)`` after
    every optimizer step; predict with ``ema.averaged_model``. Its ``state_dict`` holds the
    averaged weights and the step count."""

    def __init__(self, model: nn.Module, config: EMAConfig | None = None) -> None:
        super().__init__()
        self.config = config or EMAConfig()
        self.averaged_model = copy.deepcopy(model).eval().requires_grad_(False)
        self.register_buffer("optimization_step", torch.zeros((), dtype=torch.long))

    def decay(self, optimization_step: int) -> float:
        """The averaging weight of the old value at ``optimization_step`` (0 = copy the model)."""
        c = self.config
        step = max(0, optimization_step - c.update_after_step - 1)
        if step <= 0:
            return 0.0
        value = 1.0 - (1.0 + step / c.inv_gamma) ** -c.power
        return max(c.min_value, min(value, c.max_value))

    @torch.no_grad()
    def step(self, model: nn.Module) -> float:
        """Move the average toward ``model``'s current weights; returns the decay used."""
        d = self.decay(int(self.optimization_step))
        for avg, new in zip(self.averaged_model.parameters(), model.parameters(), strict=True):
            if new.requires_grad:
                avg.lerp_(new.detach().to(avg.dtype), 1.0 - d)
            else:
                avg.copy_(new.detach())
        for avg_b, new_b in zip(self.averaged_model.buffers(), model.buffers(), strict=True):
            avg_b.copy_(new_b)
        self.optimization_step += 1
        return d

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        """Calls the averaged model."""
        return self.averaged_model(*args, **kwargs)

    def train(self, mode: bool = True) -> ExponentialMovingAverage:
        """The averaged model always stays in eval mode."""
        super().train(mode)
        self.averaged_model.eval()
        return self
