"""Lightweight PointNet++ segmenter: which points belong to task-critical objects.

Input ``points: (B, N, 11) float32`` = ``(x, y, z, r, g, b, nx, ny, nz, c1, c2)`` with xyz in
metres; output ``(B, N)`` logits of the critical class. Set abstraction (FPS + ball query + shared
MLP + max-pool) goes down, feature propagation (3-NN inverse-distance interpolation + skip
features + MLP) comes back to every input point. Grouping runs in plain torch
(``pointnet2_ops``), so the same code trains on CPU and CUDA.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from anchordp3.models.normalizer import MinMaxNormalizer
from anchordp3.models.pointnet2_ops import (
    ball_query,
    farthest_point_sample,
    gather,
    interpolate,
    three_nn,
)
from anchordp3.schemas.training import SegmenterConfig


def mlp(widths: list[int] | tuple[int, ...], in_dim: int) -> nn.Sequential:
    """Shared MLP over the last axis: (Linear -> LayerNorm -> ReLU) per width."""
    layers: list[nn.Module] = []
    for w in widths:
        layers += [nn.Linear(in_dim, w), nn.LayerNorm(w), nn.ReLU(inplace=True)]
        in_dim = w
    return nn.Sequential(*layers)


class SetAbstraction(nn.Module):
    """One level down: ``npoint`` FPS centroids, ``nsample`` neighbours within ``radius`` each,
    shared MLP on ``[relative xyz / radius, features]``, max over the neighbours."""

    def __init__(self, npoint: int, radius: float, nsample: int, in_channels: int, widths: tuple[int, ...]) -> None:
        super().__init__()
        self.npoint, self.radius, self.nsample = npoint, radius, nsample
        self.mlp = mlp(widths, in_channels + 3)
        self.out_channels = widths[-1]

    def forward(self, xyz: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """xyz: (B, N, 3) metres; features: (B, N, C) -> centroids (B, S, 3), features (B, S, C')."""
        npoint = min(self.npoint, xyz.shape[1])
        centroids = gather(xyz, farthest_point_sample(xyz, npoint))  # (B, S, 3)
        groups = ball_query(self.radius, self.nsample, xyz, centroids)  # (B, S, K)
        rel = (gather(xyz, groups) - centroids.unsqueeze(2)) / self.radius  # (B, S, K, 3)
        grouped = torch.cat([rel.to(features.dtype), gather(features, groups)], dim=-1)
        return centroids, self.mlp(grouped).amax(dim=2)


class FeaturePropagation(nn.Module):
    """One level up: interpolate coarse features at the fine points (3-NN, inverse distance),
    concatenate the fine level's own features, shared MLP."""

    def __init__(self, coarse_channels: int, skip_channels: int, widths: tuple[int, ...]) -> None:
        super().__init__()
        self.mlp = mlp(widths, coarse_channels + skip_channels)
        self.out_channels = widths[-1]

    def forward(self, fine_xyz: torch.Tensor, coarse_xyz: torch.Tensor, fine_features: torch.Tensor, coarse_features: torch.Tensor) -> torch.Tensor:
        """fine_xyz: (B, N, 3); coarse_xyz: (B, S, 3); fine_features: (B, N, C1);
        coarse_features: (B, S, C2) -> (B, N, C')."""
        idx, w = three_nn(fine_xyz, coarse_xyz)
        up = interpolate(coarse_features, idx, w)
        return self.mlp(torch.cat([up, fine_features], dim=-1))


class PointNet2Segmenter(nn.Module):
    """Per-point binary segmentation of task-critical objects.

    The 11 input channels pass through an input normalizer (identity until ``set_normalizer`` is
    called with dataset statistics; saved in the ``state_dict``); neighbourhoods use the raw xyz.
    """

    def __init__(self, config: SegmenterConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or SegmenterConfig()
        self.normalizer = MinMaxNormalizer(config.in_channels)
        self.down = nn.ModuleList()
        channels = [config.in_channels]
        for sa in config.set_abstraction:
            self.down.append(SetAbstraction(sa.npoint, sa.radius, sa.nsample, channels[-1], sa.mlp))
            channels.append(sa.mlp[-1])
        self.up = nn.ModuleList()
        coarse = channels[-1]
        for level, widths in enumerate(config.feature_propagation):
            skip = channels[-2 - level]
            self.up.append(FeaturePropagation(coarse, skip, widths))
            coarse = widths[-1]
        self.head = nn.Sequential(
            nn.Linear(coarse, config.head_hidden), nn.LayerNorm(config.head_hidden), nn.ReLU(inplace=True),
            nn.Dropout(config.dropout), nn.Linear(config.head_hidden, 1),
        )

    def set_normalizer(self, stats: Mapping[str, object]) -> None:
        """Fit the input normalizer from point statistics ``{"min": (11,), "max": (11,)}``."""
        fitted = MinMaxNormalizer.from_stats(stats)
        self.normalizer.set_limits(fitted.min, fitted.max)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """points: (B, N, in_channels) float32, xyz first (metres) -> logits (B, N)."""
        if points.ndim != 3 or points.shape[-1] != self.config.in_channels:
            raise ValueError(f"segmenter: expected points (B, N, {self.config.in_channels}), got {tuple(points.shape)}")
        xyz = points[..., :3].contiguous()
        xyzs, feats = [xyz], [self.normalizer(points)]
        for sa in self.down:
            c, f = sa(xyzs[-1], feats[-1])
            xyzs.append(c)
            feats.append(f)
        f = feats[-1]
        for level, fp in enumerate(self.up):
            fine = len(xyzs) - 2 - level
            f = fp(xyzs[fine], xyzs[fine + 1], feats[fine], f)
        return self.head(f).squeeze(-1)

    @torch.no_grad()
    def probabilities(self, points: torch.Tensor) -> torch.Tensor:
        """points: (B, N, 11) -> critical-object probability (B, N) in [0, 1], float32."""
        return torch.sigmoid(self(points).float())


def segmentation_loss(logits: torch.Tensor, labels: torch.Tensor, pos_weight: float | None = None) -> torch.Tensor:
    """Binary cross-entropy of per-point logits: critical or not. logits: (B, N); labels: (B, N)
    roles, any integer dtype (critical: not 0) -> scalar."""
    weight = None if pos_weight is None else torch.tensor(pos_weight, device=logits.device, dtype=torch.float32)
    return F.binary_cross_entropy_with_logits(logits.float(), (labels > 0).float(), pos_weight=weight)


@dataclass
class SegmentationCounts:
    """Confusion counts of the critical class, accumulated over batches (``add``), then read as
    ``iou``, ``precision``, ``recall``. An empty denominator (nothing predicted / nothing to find)
    reads as 1.0: no mistake was possible."""

    tp: int = 0
    fp: int = 0
    fn: int = 0
    tn: int = 0

    def add(self, logits: torch.Tensor, labels: torch.Tensor, threshold: float = 0.5) -> SegmentationCounts:
        """Count one batch. logits: (B, N) raw scores; labels: (B, N) roles (critical: not 0); a point is predicted
        critical when sigmoid(logit) > threshold. Returns self."""
        pred = torch.sigmoid(logits.detach().float()) > threshold
        true = labels.detach().bool()
        self.tp += int((pred & true).sum())
        self.fp += int((pred & ~true).sum())
        self.fn += int((~pred & true).sum())
        self.tn += int((~pred & ~true).sum())
        return self

    @property
    def iou(self) -> float:
        """tp / (tp + fp + fn) of the critical class."""
        return _ratio(self.tp, self.tp + self.fp + self.fn)

    @property
    def precision(self) -> float:
        """tp / (tp + fp)."""
        return _ratio(self.tp, self.tp + self.fp)

    @property
    def recall(self) -> float:
        """tp / (tp + fn)."""
        return _ratio(self.tp, self.tp + self.fn)

    def as_dict(self) -> dict[str, float]:
        """``{"iou", "precision", "recall"}`` as floats."""
        return {"iou": self.iou, "precision": self.precision, "recall": self.recall}


def segmentation_metrics(logits: torch.Tensor, labels: torch.Tensor, threshold: float = 0.5) -> dict[str, float]:
    """IoU, precision and recall of the critical class over a whole batch.

    logits: (B, N) or (N,); labels: same shape, {0, 1}."""
    return SegmentationCounts().add(logits, labels, threshold).as_dict()


def _ratio(num: int, den: int) -> float:
    return 1.0 if den == 0 else num / den
