"""Which CPU kernels the models use: the fast paths (default) or PyTorch's standard ones.

Two inference paths are faster on the CPU than PyTorch's own kernels at this project's sizes:
``unet1d.SequenceConv1d`` (a short-sequence convolution as one matrix product) and the C
farthest-point sampling in ``pointnet2_ops``. Both compute the same results (to float rounding for
the convolution, exactly for FPS). ``reference_kernels()`` switches them off for a block, so a
benchmark can time today's and the reference path side by side and a test can compare them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

_FAST = [True]


def fast_kernels() -> bool:
    """True unless inside ``reference_kernels()``."""
    return _FAST[-1]


@contextlib.contextmanager
def reference_kernels() -> Iterator[None]:
    """Within the block, models run PyTorch's standard kernels (no fast paths)."""
    _FAST.append(False)
    try:
        yield
    finally:
        _FAST.pop()
