"""Conditional 1-D U-Net over the anchor sequence (Diffusion Policy's action expert).

Residual blocks of Conv1d -> GroupNorm -> Mish; every block is modulated by FiLM (per-channel
scale and bias) computed from ``[sinusoidal diffusion-step embedding, observation feature]``.
The temporal axis (H anchors) is halved at each level but the last and doubled back on the way up;
H = 8 with three levels goes 8 -> 4 -> 2 -> 4 -> 8.
"""

from __future__ import annotations

import math
from itertools import pairwise

import torch
import torch.nn.functional as F
from torch import nn

from anchordp3.models.kernels import fast_kernels
from anchordp3.schemas.training import UNetConfig


class SinusoidalStepEmbedding(nn.Module):
    """Transformer-style sinusoidal embedding of the diffusion step. t: (B,) -> (B, dim)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / max(half - 1, 1))
        angles = t.float().unsqueeze(-1) * freqs
        return torch.cat([angles.sin(), angles.cos()], dim=-1)


class SequenceConv1d(nn.Conv1d):
    """``nn.Conv1d`` (same parameters, same checkpoints) that, for inference on the CPU, runs as one
    matrix product over the unfolded sequence: on the U-Net's short sequences (T <= 8 at batch 1)
    PyTorch's CPU convolution kernels cost ~10x more than the arithmetic. Training (gradients on)
    and CUDA use the standard convolution, and so does ``kernels.reference_kernels()``.
    x: (B, C_in, T) -> (B, C_out, T_out)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not fast_kernels() or torch.is_grad_enabled() or x.device.type != "cpu" or self.groups != 1 or self.dilation != (1,) or \
                self.padding_mode != "zeros" or not isinstance(self.padding, tuple):
            return super().forward(x)
        (k,), (stride,), (pad,) = self.kernel_size, self.stride, self.padding
        cols = F.pad(x, (pad, pad)).unfold(2, k, stride)  # (B, C_in, T_out, k)
        b, _, t_out, _ = cols.shape
        flat = cols.permute(0, 2, 1, 3).reshape(b * t_out, -1)  # (B * T_out, C_in * k)
        weight = self.weight.reshape(self.out_channels, -1)
        y = flat @ weight.t() if self.bias is None else torch.addmm(self.bias, flat, weight.t())
        return y.reshape(b, t_out, self.out_channels).transpose(1, 2)


class ConvNormMish(nn.Module):
    """Conv1d (same padding) -> GroupNorm -> Mish. x: (B, C_in, T) -> (B, C_out, T)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, n_groups: int) -> None:
        super().__init__()
        self.block = nn.Sequential(
            SequenceConv1d(in_channels, out_channels, kernel_size, padding=kernel_size // 2),
            nn.GroupNorm(n_groups, out_channels),
            nn.Mish(),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.block(x)


class FiLMResidualBlock(nn.Module):
    """Two ``ConvNormMish`` with FiLM between them, plus a (1x1-projected) residual.

    x: (B, C_in, T); cond: (B, cond_dim) -> (B, C_out, T)."""

    def __init__(self, in_channels: int, out_channels: int, cond_dim: int, kernel_size: int, n_groups: int) -> None:
        super().__init__()
        self.conv1 = ConvNormMish(in_channels, out_channels, kernel_size, n_groups)
        self.conv2 = ConvNormMish(out_channels, out_channels, kernel_size, n_groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * out_channels))
        self.residual = SequenceConv1d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.conv1(x)
        scale, bias = self.film(cond).unsqueeze(-1).chunk(2, dim=1)  # (B, C_out, 1) each
        h = self.conv2(scale * h + bias)
        return h + self.residual(x)


class ConditionalUnet1D(nn.Module):
    """Denoiser of an anchor sequence given the diffusion step and an observation feature.

    sample: (B, T, input_dim) noisy (normalised) anchors; timestep: (B,) or scalar int;
    global_cond: (B, cond_dim) -> (B, T, input_dim). T must be divisible by 2^(levels - 1).
    """

    def __init__(self, input_dim: int, cond_dim: int, config: UNetConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or UNetConfig()
        k, g, e = config.kernel_size, config.n_groups, config.step_embed_dim
        self.step_encoder = nn.Sequential(SinusoidalStepEmbedding(e), nn.Linear(e, 4 * e), nn.Mish(), nn.Linear(4 * e, e))
        film_dim = e + cond_dim
        dims = [input_dim, *config.down_dims]
        levels = len(config.down_dims)
        self.down = nn.ModuleList()
        for i, (cin, cout) in enumerate(pairwise(dims)):
            last = i == levels - 1
            self.down.append(nn.ModuleList([
                FiLMResidualBlock(cin, cout, film_dim, k, g),
                FiLMResidualBlock(cout, cout, film_dim, k, g),
                nn.Identity() if last else SequenceConv1d(cout, cout, 3, stride=2, padding=1),
            ]))
        mid = config.down_dims[-1]
        self.mid = nn.ModuleList([FiLMResidualBlock(mid, mid, film_dim, k, g), FiLMResidualBlock(mid, mid, film_dim, k, g)])
        self.up = nn.ModuleList()
        for cout, cin in reversed(list(pairwise(config.down_dims))):
            self.up.append(nn.ModuleList([
                FiLMResidualBlock(2 * cin, cout, film_dim, k, g),
                FiLMResidualBlock(cout, cout, film_dim, k, g),
                nn.ConvTranspose1d(cout, cout, 4, stride=2, padding=1),
            ]))
        self.final = nn.Sequential(ConvNormMish(config.down_dims[0], config.down_dims[0], k, g), SequenceConv1d(config.down_dims[0], input_dim, 1))
        self.downsamples = levels - 1

    def forward(self, sample: torch.Tensor, timestep: torch.Tensor | int, global_cond: torch.Tensor) -> torch.Tensor:
        b, t, _ = sample.shape
        if t % (2 ** self.downsamples):
            raise ValueError(f"unet: horizon {t} not divisible by {2 ** self.downsamples} ({self.downsamples + 1} levels)")
        timestep = torch.as_tensor(timestep, device=sample.device).reshape(-1).expand(b)
        cond = torch.cat([self.step_encoder(timestep).to(global_cond.dtype), global_cond], dim=-1)
        x = sample.transpose(1, 2)  # (B, C, T)
        skips = []
        for block1, block2, downsample in self.down:
            x = block2(block1(x, cond), cond)
            skips.append(x)
            x = downsample(x)
        for block in self.mid:
            x = block(x, cond)
        for block1, block2, upsample in self.up:
            x = torch.cat([x, skips.pop()], dim=1)
            x = upsample(block2(block1(x, cond), cond))
        return self.final(x).transpose(1, 2)
