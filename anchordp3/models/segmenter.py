"""Lightweight PointNet++ segmenter: which points belong to task-critical objects.

Input ``points: (B, N, 11) float32`` = ``(x, y, z, r, g, b, nx, ny, nz, c1, c2)`` with xyz in
metres; output ``(B, N)`` logits of the critical class or, with ``roles`` R > 0, ``(B, N, R + 1)``
logits of each point's role: 0 none, k the task's k-th critical object (the data's labels). Set abstraction (FPS + ball query + shared
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
    """Per-point segmentation of task-critical objects: critical or not, or (``config.roles``) which
    critical object's role.

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
            nn.Dropout(config.dropout), nn.Linear(config.head_hidden, config.roles + 1 if config.roles else 1),
        )

    def set_normalizer(self, stats: Mapping[str, object]) -> None:
        """Fit the input normalizer from point statistics ``{"min": (11,), "max": (11,)}``."""
        fitted = MinMaxNormalizer.from_stats(stats)
        self.normalizer.set_limits(fitted.min, fitted.max)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """points: (B, N, in_channels) float32, xyz first (metres) -> logits (B, N), or (B, N, roles + 1)
        with roles."""
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
        out = self.head(f)
        return out if self.config.roles else out.squeeze(-1)

    @torch.no_grad()
    def probabilities(self, points: torch.Tensor) -> torch.Tensor:
        """points: (B, N, 11) -> critical-object probability (B, N) in [0, 1], float32 (with roles: 1 - the
        probability of no role)."""
        return critical_probability(self(points))

    @torch.no_grad()
    def predict(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """points: (B, N, 11) -> the critical probability (B, N) float32 and, with roles, each point's most
        likely role (B, N) uint8 (0 none), else None; one forward pass."""
        logits = self(points)
        return critical_probability(logits), point_roles(logits) if self.config.roles else None


def critical_probability(logits: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` critical logits or ``(B, N, roles + 1)`` role logits -> the probability that a point is
    critical ``(B, N)`` float32."""
    logits = logits.float()
    return torch.sigmoid(logits) if logits.ndim < 3 else 1 - torch.softmax(logits, dim=-1)[..., 0]


def point_roles(logits: torch.Tensor) -> torch.Tensor:
    """``(B, N, roles + 1)`` role logits -> each point's most likely role ``(B, N)`` uint8, 0 none."""
    return logits.argmax(-1).to(torch.uint8)


def segmentation_loss(logits: torch.Tensor, labels: torch.Tensor, pos_weight: float | None = None) -> torch.Tensor:
    """Cross-entropy of per-point logits against ``labels (B, N)`` roles, any integer dtype -> scalar:
    binary (critical: not 0) for ``logits (B, N)``; over the roles for ``logits (B, N, R + 1)``, where a
    label above R (the robot, 255, or a task with more objects) is refused. ``pos_weight``: the weight
    of the critical class (every role) against none (1)."""
    if logits.ndim < 3:
        weight = None if pos_weight is None else torch.tensor(pos_weight, device=logits.device, dtype=torch.float32)
        return F.binary_cross_entropy_with_logits(logits.float(), (labels > 0).float(), pos_weight=weight)
    roles = logits.shape[-1] - 1
    top = int(labels.max()) if labels.numel() else 0
    if top > roles:
        raise ValueError(f"segmenter.model.roles: {roles}, but a point is labelled role {top} (255: the robot, "
                         "render.include_robot); raise roles to the tasks' critical objects, or render without the robot")
    weight = None
    if pos_weight is not None:
        weight = torch.full((roles + 1,), float(pos_weight), device=logits.device)
        weight[0] = 1.0
    return F.cross_entropy(logits.float().flatten(0, 1), labels.long().flatten(), weight=weight)


@dataclass
class SegmentationCounts:
    """Confusion counts of the critical class, accumulated over batches (``add``), then read as
    ``iou``, ``precision``, ``recall`` and, for role logits, ``role_accuracy``. An empty denominator
    (nothing predicted / nothing to find) reads as 1.0: no mistake was possible."""

    tp: int = 0
    fp: int = 0
    fn: int = 0
    tn: int = 0
    role_hits: int = 0  # critical points given their own role (role logits only)
    role_points: int | None = None  # critical points counted for role_accuracy; None: binary logits

    def add(self, logits: torch.Tensor, labels: torch.Tensor, threshold: float = 0.5) -> SegmentationCounts:
        """Count one batch. logits: (B, N) raw scores or (B, N, R + 1) role logits; labels: (B, N) roles
        (critical: not 0); a point is predicted critical when its critical probability
        (``critical_probability``) > threshold. Returns self."""
        pred = critical_probability(logits.detach()) > threshold
        true = labels.detach().bool()
        if logits.ndim == 3:
            self.role_hits += int(((point_roles(logits.detach()).long() == labels.detach().long()) & true).sum())
            self.role_points = (self.role_points or 0) + int(true.sum())
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

    @property
    def role_accuracy(self) -> float:
        """Share of the critical points predicted with their own role (role logits only)."""
        return _ratio(self.role_hits, self.role_points or 0)

    def as_dict(self) -> dict[str, float]:
        """``{"iou", "precision", "recall"}`` as floats, and ``role_accuracy`` for role logits."""
        out = {"iou": self.iou, "precision": self.precision, "recall": self.recall}
        if self.role_points is not None:
            out["role_accuracy"] = self.role_accuracy
        return out


def segmentation_metrics(logits: torch.Tensor, labels: torch.Tensor, threshold: float = 0.5) -> dict[str, float]:
    """IoU, precision and recall of the critical class over a whole batch (and ``role_accuracy`` for role
    logits). logits: (B, N) or (B, N, R + 1); labels: (B, N) roles."""
    return SegmentationCounts().add(logits, labels, threshold).as_dict()


def _ratio(num: int, den: int) -> float:
    return 1.0 if den == 0 else num / den
