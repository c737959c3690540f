"""Conditional 1-D U-Net over the anchor sequence (Diffusion Policy's action expert).

Residual blocks of Conv1d -> GroupNorm -> Mish; every block is modulated by FiLM (per-channel
scale and bias) computed from ``[sinusoidal diffusion-step embedding, observation feature]``.
The temporal axis (H anchors) is halved at each level but the last and doubled back on the way up;
H = 8 with three levels goes 8 -> 4 -> 2 -> 4 -> 8.
"""

from __future__ import annotations

import math
from itertools import pairwise, repeat

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


def _cpu_inference(conv: nn.Conv1d | nn.ConvTranspose1d, x: torch.Tensor) -> bool:
    """Whether ``conv`` may run its matrix-product path on ``x``: fast kernels on, no gradients, CPU,
    and a plain convolution (one group, no dilation, zero padding)."""
    return fast_kernels() and not torch.is_grad_enabled() and x.device.type == "cpu" and conv.groups == 1 \
        and conv.dilation == (1,) and conv.padding_mode == "zeros"


class SequenceConv1d(nn.Conv1d):
    """``nn.Conv1d`` (same parameters, same checkpoints) that, for inference on the CPU, runs as one
    matrix product over the unfolded sequence: on the U-Net's short sequences (T <= 8 at batch 1)
    PyTorch's CPU convolution kernels cost ~10x more than the arithmetic. Training (gradients on)
    and CUDA use the standard convolution, and so does ``kernels.reference_kernels()``.
    x: (B, C_in, T) -> (B, C_out, T_out)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not _cpu_inference(self, x) or not isinstance(self.padding, tuple):
            return super().forward(x)
        (k,), (stride,), (pad,) = self.kernel_size, self.stride, self.padding
        cols = F.pad(x, (pad, pad)).unfold(2, k, stride)  # (B, C_in, T_out, k)
        b, _, t_out, _ = cols.shape
        lo, hi = max(0, pad - (t_out - 1) * stride), min(k, pad + x.shape[2])  # taps that ever read an input
        flat = cols[..., lo:hi].permute(0, 2, 1, 3).reshape(b * t_out, -1)  # (B * T_out, C_in * taps)
        weight = self._tap_weight(lo, hi)
        y = flat @ weight.t() if self.bias is None else torch.addmm(self.bias, flat, weight.t())
        return y.reshape(b, t_out, self.out_channels).transpose(1, 2)

    _frozen: dict[tuple[int, int], torch.Tensor] | None = None  # tap weights kept by ``freeze``

    def _tap_weight(self, lo: int, hi: int) -> torch.Tensor:
        """The weight of taps ``lo..hi-1`` as ``(C_out, C_in * taps)``. On a sequence shorter than
        the kernel the outer taps only ever meet the zero padding (T = 2, kernel 5: two of five), so
        they are left out of the product, which is bound by reading the weight from memory. The
        slice is a copy (0.4 ms for 256 x 256 x 3): taken at every call, unless ``freeze`` said the
        weights are final, as a model loaded for evaluation (a cached copy would go stale when
        weights change in ways no version counter sees)."""
        if (lo, hi) == (0, self.kernel_size[0]):
            return self.weight.reshape(self.out_channels, -1)
        if self._frozen is None:
            return self.weight[:, :, lo:hi].reshape(self.out_channels, -1)
        if (lo, hi) not in self._frozen:
            self._frozen[(lo, hi)] = self.weight.detach()[:, :, lo:hi].reshape(self.out_channels, -1).contiguous()
        return self._frozen[(lo, hi)]

    def freeze(self) -> None:
        """Keep each sliced tap weight from its first use on: the weights will not change until
        ``train()`` or ``load_state_dict`` (which thaw it)."""
        self._frozen = {}

    def train(self, mode: bool = True) -> SequenceConv1d:
        self._frozen = None
        return super().train(mode)

    def _load_from_state_dict(self, *args, **kwargs) -> None:
        self._frozen = None
        super()._load_from_state_dict(*args, **kwargs)


class SequenceConvTranspose1d(nn.ConvTranspose1d):
    """``nn.ConvTranspose1d`` (same parameters, same checkpoints) that, for inference on the CPU, runs
    as one matrix product and a ``fold`` (col2im), where PyTorch's transposed-convolution kernel
    costs ~100 us on the U-Net's sequences of 2-4; the same conditions as ``SequenceConv1d``.
    x: (B, C_in, T) -> (B, C_out, T_out)."""

    def forward(self, x: torch.Tensor, output_size: list[int] | None = None) -> torch.Tensor:
        if not _cpu_inference(self, x) or output_size is not None or self.output_padding != (0,):
            return super().forward(x, output_size)
        (k,), (stride,), (pad,) = self.kernel_size, self.stride, self.padding
        b, _, t = x.shape
        t_out = (t - 1) * stride - 2 * pad + k
        cols = self.weight.reshape(self.in_channels, -1).t() @ x  # (B, C_out * k, T): every input's k contributions
        y = F.fold(cols, (1, t_out), (1, k), padding=(0, pad), stride=(1, stride))  # (B, C_out, 1, T_out)
        y = y.squeeze(2)
        return y if self.bias is None else y + self.bias[:, None]


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

    x: (B, C_in, T); cond: (B, cond_dim) -> (B, C_out, T). With ``film`` (B, 2 C_out), this
    block's row of ``ConditionalUnet1D.film_table``, the FiLM linear is not run and ``cond`` is unused."""

    def __init__(self, in_channels: int, out_channels: int, cond_dim: int, kernel_size: int, n_groups: int) -> None:
        super().__init__()
        self.conv1 = ConvNormMish(in_channels, out_channels, kernel_size, n_groups)
        self.conv2 = ConvNormMish(out_channels, out_channels, kernel_size, n_groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * out_channels))
        self.residual = SequenceConv1d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor | None, film: torch.Tensor | None = None) -> torch.Tensor:
        h = self.conv1(x)
        film = self.film(cond) if film is None else film
        scale, bias = film.unsqueeze(-1).chunk(2, dim=1)  # (B, C_out, 1) each
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
                SequenceConvTranspose1d(cout, cout, 4, stride=2, padding=1),
            ]))
        self.final = nn.Sequential(ConvNormMish(config.down_dims[0], config.down_dims[0], k, g), SequenceConv1d(config.down_dims[0], input_dim, 1))
        self.downsamples = levels - 1

    def freeze(self) -> None:
        """Declare the weights final (a model loaded for evaluation): the convolutions keep their
        sliced tap weights (``SequenceConv1d.freeze``) until ``train()`` or ``load_state_dict``."""
        for m in self.modules():
            if isinstance(m, SequenceConv1d):
                m.freeze()

    def film_blocks(self) -> list[FiLMResidualBlock]:
        """The FiLM blocks in the order ``forward`` runs them (``film_table``'s order)."""
        return [m for m in self.modules() if isinstance(m, FiLMResidualBlock)]

    def film_table(self, global_cond: torch.Tensor, timesteps: torch.Tensor) -> list[torch.Tensor]:
        """Every FiLM block's (scale, bias) at each of ``timesteps`` for one observation feature:
        a list over ``film_blocks()`` of ``(S, B, 2 C_out)``; ``forward(..., film=[f[i] for f in table])``
        then runs step i without its FiLM linears.

        A block's FiLM is ``W mish([step embedding, global_cond]) + b`` = ``W_step mish(step
        embedding) + (W_obs mish(global_cond) + b)``: the first term depends on the step only, the
        second on the observation only, so sampling computes both once per decision instead of
        every DDIM step (the FiLM linears hold about half the U-Net's weights, read from memory at
        each step otherwise). Equal to the per-step FiLM to float rounding.
        global_cond: (B, cond_dim); timesteps: (S,) diffusion steps."""
        e = self.config.step_embed_dim
        step = F.mish(self.step_encoder(torch.as_tensor(timesteps, device=global_cond.device).reshape(-1)).to(global_cond.dtype))
        obs = F.mish(global_cond)
        table = []
        for block in self.film_blocks():
            linear = block.film[1]
            table.append((step @ linear.weight[:, :e].t())[:, None] + F.linear(obs, linear.weight[:, e:], linear.bias)[None])
        return table

    def forward(self, sample: torch.Tensor, timestep: torch.Tensor | int, global_cond: torch.Tensor,
                film: list[torch.Tensor] | None = None) -> torch.Tensor:
        """``film``: one ``(B, 2 C_out)`` per FiLM block, a step's slice of ``film_table`` (the
        FiLM linears and the step encoder are then skipped); None computes them from the inputs."""
        b, t, _ = sample.shape
        if t % (2 ** self.downsamples):
            raise ValueError(f"unet: horizon {t} not divisible by {2 ** self.downsamples} ({self.downsamples + 1} levels)")
        if film is None:
            timestep = torch.as_tensor(timestep, device=sample.device).reshape(-1).expand(b)
            cond = torch.cat([self.step_encoder(timestep).to(global_cond.dtype), global_cond], dim=-1)
            films = repeat(None)
        else:
            cond, films = None, iter(film)
        x = sample.transpose(1, 2)  # (B, C, T)
        skips = []
        for block1, block2, downsample in self.down:
            x = block1(x, cond, next(films))
            x = block2(x, cond, next(films))
            skips.append(x)
            x = downsample(x)
        for block in self.mid:
            x = block(x, cond, next(films))
        for block1, block2, upsample in self.up:
            x = torch.cat([x, skips.pop()], dim=1)
            x = block1(x, cond, next(films))
            x = upsample(block2(x, cond, next(films)))
        return self.final(x).transpose(1, 2)
