"""Tiling camera images into one labelled picture."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw


def mosaic(images: list[np.ndarray], labels: list[str], cols: int = 2, title: str | None = None) -> Image.Image:
    """Tile ``images`` (each ``(H, W, 3) uint8``, same size) ``cols`` per row, each with its label
    in the corner and an optional title strip on top."""
    h, w = images[0].shape[:2]
    rows = (len(images) + cols - 1) // cols
    top = 18 if title else 0
    canvas = Image.new("RGB", (cols * w, rows * h + top), (20, 20, 20))
    draw = ImageDraw.Draw(canvas)
    for i, (img, label) in enumerate(zip(images, labels)):
        x, y = (i % cols) * w, top + (i // cols) * h
        canvas.paste(Image.fromarray(img), (x, y))
        draw.rectangle([x, y, x + 7 * len(label) + 6, y + 14], fill=(0, 0, 0))
        draw.text((x + 3, y + 1), label, fill=(255, 255, 255))
    if title:
        draw.text((4, 3), title, fill=(255, 255, 255))
    return canvas
