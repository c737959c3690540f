"""Tiling camera images into one labelled picture."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

LINE = 14  # pixels per line of the default font


def mosaic(images: list[np.ndarray], labels: list[str], cols: int = 2, title: str | None = None) -> Image.Image:
    """Tile ``images`` (each ``(H, W, 3) uint8``, same size) ``cols`` per row, each with its label
    in the corner and an optional title on top, wrapped at word boundaries to the picture's width."""
    h, w = images[0].shape[:2]
    rows = (len(images) + cols - 1) // cols
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    lines = wrap(title, cols * w - 8, measure) if title else []
    top = LINE * len(lines) + 4 if lines else 0
    canvas = Image.new("RGB", (cols * w, rows * h + top), (20, 20, 20))
    draw = ImageDraw.Draw(canvas)
    for i, (img, label) in enumerate(zip(images, labels)):
        x, y = (i % cols) * w, top + (i // cols) * h
        canvas.paste(Image.fromarray(img), (x, y))
        draw.rectangle([x, y, x + draw.textlength(label) + 6, y + LINE], fill=(0, 0, 0))
        draw.text((x + 3, y + 1), label, fill=(255, 255, 255))
    for k, line in enumerate(lines):
        draw.text((4, 2 + LINE * k), line, fill=(255, 255, 255))
    return canvas


def wrap(text: str, width: float, draw: ImageDraw.ImageDraw) -> list[str]:
    """``text`` in lines no wider than ``width`` pixels (a word longer than that gets a line of its own)."""
    lines: list[str] = []
    for word in text.split():
        if lines and draw.textlength(f"{lines[-1]} {word}") <= width:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return lines
