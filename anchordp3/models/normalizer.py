"""Per-dimension min/max normalizer to [-1, 1] (DP3's "limits" mode), stored as module buffers so a
checkpoint's ``state_dict`` carries it."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from torch import nn

RANGE_EPS = 1e-4  # a dimension whose max - min is below this counts as constant


class MinMaxNormalizer(nn.Module):
    """Maps each of the last-axis ``dim`` values affinely from ``[min, max]`` to ``[-1, 1]``.

    A constant dimension (range < ``RANGE_EPS``) is only shifted: its fitted value maps to 0 and the
    round trip stays exact. An unfitted normalizer is the identity. Works on any shape ``(..., dim)``.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim
        self.register_buffer("min", -torch.ones(dim))
        self.register_buffer("max", torch.ones(dim))
        self.register_buffer("scale", torch.ones(dim))
        self.register_buffer("offset", torch.zeros(dim))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))

    @classmethod
    def from_stats(cls, stats: Mapping[str, object]) -> MinMaxNormalizer:
        """A normalizer fitted from ``{"min": (..., dim), "max": (..., dim)}`` (arrays, lists or tensors).

        Extra leading axes (e.g. per-horizon stats ``(H, dim)``) are reduced by min / max."""
        lo, hi = _as_2d(stats, "min"), _as_2d(stats, "max")
        if lo.shape != hi.shape:
            raise ValueError(f"stats: min {tuple(lo.shape)} and max {tuple(hi.shape)} differ in shape")
        norm = cls(lo.shape[-1])
        norm.set_limits(lo.min(dim=0).values, hi.max(dim=0).values)
        return norm

    @classmethod
    def fit(cls, data: torch.Tensor | np.ndarray) -> MinMaxNormalizer:
        """A normalizer fitted on samples ``(..., dim)``."""
        x = torch.as_tensor(np.asarray(data) if not isinstance(data, torch.Tensor) else data, dtype=torch.float64)
        x = x.reshape(-1, x.shape[-1])
        return cls.from_stats({"min": x.min(dim=0).values, "max": x.max(dim=0).values})

    def set_limits(self, lo: torch.Tensor, hi: torch.Tensor, min_range: float = 0.0) -> None:
        """Fit in place from per-dimension limits ``lo, hi: (dim,)``. A dimension spanning less than
        ``min_range`` (data units) is mapped as if it spanned ``min_range`` around its centre, so
        a nearly constant one is not stretched hundreds of times (0: DP3's plain limits)."""
        lo = torch.as_tensor(lo, dtype=torch.float64).reshape(-1)
        hi = torch.as_tensor(hi, dtype=torch.float64).reshape(-1)
        if lo.numel() != self.dim or hi.numel() != self.dim:
            raise ValueError(f"stats: expected {self.dim} dims, got min {lo.numel()} / max {hi.numel()}")
        if not torch.isfinite(lo).all() or not torch.isfinite(hi).all():
            raise ValueError("stats: min / max contain NaN or inf")
        if (hi < lo).any():
            raise ValueError(f"stats: max < min at dims {torch.nonzero(hi < lo).flatten().tolist()}")
        if min_range > 0:
            widen = torch.clamp(min_range - (hi - lo), min=0.0) / 2
            lo, hi = lo - widen, hi + widen
        span = hi - lo
        const = span < RANGE_EPS
        scale = torch.where(const, torch.ones_like(span), 2.0 / span)
        offset = torch.where(const, -(lo + hi) / 2, -1.0 - lo * scale)
        for name, value in (("min", lo), ("max", hi), ("scale", scale), ("offset", offset)):
            getattr(self, name).copy_(value.to(getattr(self, name).dtype))
        self.fitted.fill_(True)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """``x: (..., dim)`` in data units -> same shape, roughly in [-1, 1]."""
        self._check(x)
        return x * self.scale.to(x.dtype) + self.offset.to(x.dtype)

    def unnormalize(self, y: torch.Tensor) -> torch.Tensor:
        """Inverse of ``normalize``: ``y: (..., dim)`` -> data units."""
        self._check(y)
        return (y - self.offset.to(y.dtype)) / self.scale.to(y.dtype)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Same as ``normalize``."""
        return self.normalize(x)

    def stats(self) -> dict[str, torch.Tensor]:
        """The fitted limits ``{"min": (dim,), "max": (dim,)}``."""
        return {"min": self.min.clone(), "max": self.max.clone()}

    def extra_repr(self) -> str:
        return f"dim={self.dim}, fitted={bool(self.fitted)}"

    def _check(self, x: torch.Tensor) -> None:
        if x.shape[-1] != self.dim:
            raise ValueError(f"normalizer: last axis {x.shape[-1]} != dim {self.dim}")


def _as_2d(stats: Mapping[str, object], key: str) -> torch.Tensor:
    if key not in stats:
        raise KeyError(f"stats: missing {key!r} (expected keys 'min' and 'max')")
    value = stats[key]
    t = value.detach().to(torch.float64) if isinstance(value, torch.Tensor) else torch.as_tensor(np.asarray(value, dtype=np.float64))
    return t.reshape(-1, t.shape[-1]) if t.ndim else t.reshape(1, 1)
