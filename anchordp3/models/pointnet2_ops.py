"""PointNet++ grouping operations in plain, batched torch (no custom CUDA kernels; CPU and CUDA).

Shapes: ``B`` clouds, ``N`` points, ``S`` sampled centroids, ``K`` neighbours, ``C`` channels.
Coordinates are metres.
"""

from __future__ import annotations

import numpy as np
import torch

from anchordp3.models.kernels import fast_kernels

try:
    import fpsample
except ImportError:  # pragma: no cover - exercised only where fpsample is not installed
    fpsample = None


def square_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise squared Euclidean distances.

    a: (B, N, 3); b: (B, M, 3) -> (B, N, M) float32, clamped at 0. Always computed in float32, also
    under autocast (a bf16 matmul would blur neighbourhoods at millimetre scale)."""
    with torch.autocast(a.device.type, enabled=False):
        a, b = a.float(), b.float()
        d = (a * a).sum(-1, keepdim=True) - 2.0 * a @ b.transpose(1, 2) + (b * b).sum(-1).unsqueeze(1)
        return d.clamp_min_(0.0)


def gather(points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows of ``points`` by per-cloud index.

    points: (B, N, C); idx: (B, *I) long -> (B, *I, C)."""
    b, c = points.shape[0], points.shape[-1]
    flat = idx.reshape(b, -1)
    out = torch.gather(points, 1, flat.unsqueeze(-1).expand(-1, -1, c))
    return out.reshape(*idx.shape, c)


@torch.no_grad()
def farthest_point_sample(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
    """Indices of ``npoint`` points chosen by iterative farthest point sampling.

    Deterministic: the first pick is the point farthest from the cloud's centroid, each next pick
    the point farthest from all picks so far (ties -> lowest index). On the CPU with float32
    points the loop runs in ``fpsample`` (exact FPS, ~15x faster than the torch loop below, which
    CUDA and ``kernels.reference_kernels()`` use): the same picks, except that of exactly duplicated points it may pick another copy,
    so the picked coordinates, all that the segmenter uses, are always the same.
    xyz: (B, N, 3) -> (B, npoint) long. ``npoint`` must not exceed N."""
    b, n, _ = xyz.shape
    if npoint > n:
        raise ValueError(f"farthest_point_sample: npoint {npoint} > points {n}")
    centroid = xyz.mean(dim=1, keepdim=True)
    farthest = ((xyz - centroid) ** 2).sum(-1).argmax(dim=1)
    if fpsample is None or not fast_kernels() or xyz.device.type != "cpu" or xyz.dtype != torch.float32 or n < 2:
        return _fps_loop(xyz, npoint, farthest)
    picks = []
    for c, s in zip(xyz.detach(), farthest.tolist()):
        cloud = np.ascontiguousarray(c.numpy())
        fast = fpsample.fps_sampling(cloud, npoint, start_idx=s).astype(np.int64)
        # FPS picks a point where one already is only once the distinct points ran out; then the
        # loop's lowest-index rule decides the repeats
        if len(np.unique(cloud[fast], axis=0)) == npoint:
            picks.append(torch.from_numpy(fast))
        else:
            picks.append(_fps_loop(c[None], npoint, torch.tensor([s]))[0])
    return torch.stack(picks)


def _fps_loop(xyz: torch.Tensor, npoint: int, farthest: torch.Tensor) -> torch.Tensor:
    """The torch FPS loop from first picks ``farthest (B,)``: xyz (B, N, 3) -> (B, npoint) long."""
    b, n, _ = xyz.shape
    idx = torch.empty(b, npoint, dtype=torch.long, device=xyz.device)
    dist = torch.full((b, n), float("inf"), dtype=xyz.dtype, device=xyz.device)
    rows = torch.arange(b, device=xyz.device)
    for i in range(npoint):
        idx[:, i] = farthest
        picked = xyz[rows, farthest].unsqueeze(1)  # (B, 1, 3)
        dist = torch.minimum(dist, ((xyz - picked) ** 2).sum(-1))
        farthest = dist.argmax(dim=1)
    return idx


@torch.no_grad()
def ball_query(radius: float, nsample: int, xyz: torch.Tensor, centroids: torch.Tensor) -> torch.Tensor:
    """For each centroid, the ``nsample`` nearest points within ``radius`` (metres).

    Slots with no further point inside the ball repeat the nearest one (the centroid itself when it
    is a cloud point), so every group is full. If N < nsample, the nearest N are repeated likewise.
    xyz: (B, N, 3); centroids: (B, S, 3) -> (B, S, nsample) long."""
    n = xyz.shape[1]
    d = square_distance(centroids, xyz)  # (B, S, N)
    k = min(nsample, n)
    near_d, near_i = torch.topk(d, k, dim=-1, largest=False, sorted=True)
    outside = near_d > radius * radius
    near_i = torch.where(outside, near_i[..., :1].expand_as(near_i), near_i)
    if k < nsample:
        near_i = torch.cat([near_i, near_i[..., :1].expand(*near_i.shape[:-1], nsample - k)], dim=-1)
    return near_i


@torch.no_grad()
def three_nn(fine: torch.Tensor, coarse: torch.Tensor, eps: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor]:
    """The (up to) 3 nearest coarse points of every fine point and their inverse-distance weights.

    fine: (B, N, 3); coarse: (B, S, 3) -> idx (B, N, k) long, weights (B, N, k) summing to 1,
    k = min(3, S)."""
    d = square_distance(fine, coarse)
    k = min(3, coarse.shape[1])
    near_d, near_i = torch.topk(d, k, dim=-1, largest=False, sorted=True)
    w = 1.0 / (near_d.sqrt() + eps)
    return near_i, w / w.sum(-1, keepdim=True)


def interpolate(features: torch.Tensor, idx: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Weighted sum of coarse features at the fine points.

    features: (B, S, C); idx, weights: (B, N, k) -> (B, N, C)."""
    return (gather(features, idx) * weights.unsqueeze(-1).to(features.dtype)).sum(dim=2)
