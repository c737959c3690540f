"""Observation encoders of the policy: one point-cloud encoder per task (no weight sharing), picked
per sample by task id, and a small state MLP."""

from __future__ import annotations

import torch
from torch import nn

from anchordp3.schemas.training import PointEncoderConfig, StateEncoderConfig


def append_critical_probability(points: torch.Tensor, probability: torch.Tensor) -> torch.Tensor:
    """The policy's point input: 11 features + the segmenter's critical probability.

    points: (B, N, 11); probability: (B, N) in [0, 1] (or the simulator's {0, 1} label)
    -> (B, N, 12) in the points' dtype."""
    return torch.cat([points, probability.unsqueeze(-1).to(points.dtype)], dim=-1)


class PointEncoder(nn.Module):
    """AnchorDP3's lightweight encoder: per-point MLP (Linear-LayerNorm-ReLU, width ``hidden_dim``)
    -> max-pool over points -> Linear to ``out_dim`` -> LayerNorm.

    points: (B, N, in_channels) -> (B, out_dim)."""

    def __init__(self, config: PointEncoderConfig | None = None) -> None:
        super().__init__()
        config = config or PointEncoderConfig()
        layers: list[nn.Module] = []
        width = config.in_channels
        for _ in range(config.num_layers):
            layers += [nn.Linear(width, config.hidden_dim), nn.LayerNorm(config.hidden_dim), nn.ReLU(inplace=True)]
            width = config.hidden_dim
        self.per_point = nn.Sequential(*layers)
        self.project = nn.Sequential(nn.Linear(config.hidden_dim, config.out_dim), nn.LayerNorm(config.out_dim))
        self.out_dim = config.out_dim

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """points: (B, N, in_channels), xyz first -> (B, out_dim)."""
        pooled = self.per_point(points).max(dim=1).values  # max, not amax: its backward is a gather, 10x cheaper on CPU
        return self.project(pooled)


class TaskConditionedEncoder(nn.Module):
    """``num_tasks`` independent ``PointEncoder`` s; sample ``b`` is encoded by encoder
    ``task_id[b]`` only, so in a mixed-task batch each encoder gets gradient from its own
    samples and an encoder whose task is absent gets none (its ``.grad`` stays None)."""

    def __init__(self, num_tasks: int, config: PointEncoderConfig | None = None) -> None:
        super().__init__()
        self.encoders = nn.ModuleList(PointEncoder(config) for _ in range(num_tasks))
        self.out_dim = self.encoders[0].out_dim

    def forward(self, points: torch.Tensor, task_id: torch.Tensor) -> torch.Tensor:
        """points: (B, N, C); task_id: (B,) long in [0, num_tasks) -> (B, out_dim)."""
        task_id = torch.as_tensor(task_id, device=points.device).reshape(-1)
        if task_id.numel() != points.shape[0]:
            raise ValueError(f"task_id: {task_id.numel()} ids for a batch of {points.shape[0]}")
        if task_id.numel() and (int(task_id.min()) < 0 or int(task_id.max()) >= len(self.encoders)):
            raise ValueError(f"task_id: ids must lie in [0, {len(self.encoders)}), got {task_id.tolist()}")
        pieces, order = [], []
        for k in torch.unique(task_id).tolist():
            rows = torch.nonzero(task_id == k).flatten()
            pieces.append(self.encoders[k](points.index_select(0, rows)))
            order.append(rows)
        feats = torch.cat(pieces)
        rows = torch.cat(order)
        return feats.new_empty(feats.shape).index_copy(0, rows, feats)


class StateEncoder(nn.Module):
    """Small MLP on the robot state: Linear(in_dim, hidden) -> ReLU -> Linear(hidden, hidden).

    state: (B, in_dim) -> (B, hidden_dim)."""

    def __init__(self, config: StateEncoderConfig | None = None) -> None:
        super().__init__()
        config = config or StateEncoderConfig()
        self.net = nn.Sequential(nn.Linear(config.in_dim, config.hidden_dim), nn.ReLU(inplace=True), nn.Linear(config.hidden_dim, config.hidden_dim))
        self.out_dim = config.hidden_dim

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        """state: (B, in_dim) normalised -> (B, hidden_dim)."""
        return self.net(state)
