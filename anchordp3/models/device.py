"""Device choice and mixed precision: CUDA when present, autocast on CUDA only."""

from __future__ import annotations

import contextlib

import torch


def pick_device(preference: str = "auto") -> torch.device:
    """``auto`` -> ``cuda`` when available else ``cpu``; ``cpu`` / ``cuda`` / ``cuda:1`` as given.

    Asking for CUDA on a machine without it is a clear error."""
    if preference == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(preference)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device: {preference!r} requested but torch sees no CUDA device; use 'cpu' or 'auto'")
    return device


def autocast(device: torch.device | str, enabled: bool = True) -> contextlib.AbstractContextManager:
    """Mixed precision on CUDA (bf16 where supported, else fp16); a no-op context on CPU or when disabled.

    fp16 needs a ``torch.amp.GradScaler`` in the training loop; bf16 does not (see ``needs_grad_scaler``)."""
    device = torch.device(device)
    if not enabled or device.type != "cuda":
        return contextlib.nullcontext()
    return torch.autocast("cuda", dtype=autocast_dtype(device))


def autocast_dtype(device: torch.device | str) -> torch.dtype:
    """The reduced precision autocast uses on ``device``: bf16 when the GPU supports it, else fp16."""
    device = torch.device(device)
    if device.type == "cuda" and torch.cuda.is_bf16_supported():
        return torch.bfloat16
    return torch.float16


def needs_grad_scaler(device: torch.device | str, enabled: bool = True) -> bool:
    """True when autocast on ``device`` runs in fp16, whose gradients need loss scaling."""
    device = torch.device(device)
    return enabled and device.type == "cuda" and autocast_dtype(device) == torch.float16


def seed_everything(seed: int) -> torch.Generator:
    """Seed torch's global RNGs (CPU and CUDA) and return a CPU generator seeded the same way."""
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)
