"""Independent random streams derived from an episode seed.

Physics-relevant draws (layout, object shapes, clutter placement) and render-only draws
(textures, lights) come from different streams, so a scene built with rendering off has exactly
the same physics as the same seed built with rendering on.
"""

from __future__ import annotations

import zlib

import numpy as np


def rng(seed: int, stream: str) -> np.random.Generator:
    """A generator for ``stream`` (e.g. ``"layout"``, ``"appearance"``) of episode ``seed``."""
    return np.random.default_rng([int(seed), zlib.crc32(stream.encode())])
