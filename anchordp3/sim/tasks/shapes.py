"""Small helpers for procedurally built task objects: colours and oriented primitive parts.

Sizes are metres; poses are in the object frame (origin at the bottom centre, z up).
"""

from __future__ import annotations

import numpy as np
import sapien

from anchordp3.sim.actors import Part

UPRIGHT = (0.7071068, 0.0, 0.7071068, 0.0)  # turns a part's x axis (a cylinder's axis) to vertical
ACROSS = (0.7071068, 0.0, 0.0, 0.7071068)  # turns a part's x axis to the frame's y axis
FINGER_TIP_BELOW_TCP = 0.015  # the finger tips reach this far below the tool centre point
PAD_HEIGHT = 0.008  # metres: a target pad's top above the table, clear of the features' table crop (5 mm)


def target_pad(half_x: float, half_y: float, rgba: tuple[float, ...]) -> list[Part]:
    """A flat target pad (a marker: seen, not touched) of ``2 half_x x 2 half_y`` metres, its bottom
    at the frame's origin and its top ``PAD_HEIGHT`` above: thicker than the features stage's
    table crop (``features.table_margin``, 5 mm), so the point cloud keeps it and the masks can name
    it (a 1 mm marker is cropped away with the table, and the goal it marks is then not observed).
    Objects set on it rest on the table and sink into it by that height."""
    return [Part("box", (half_x, half_y, PAD_HEIGHT / 2), sapien.Pose([0.0, 0.0, PAD_HEIGHT / 2]), rgba)]


def jittered(rng: np.random.Generator, rgb: tuple[float, float, float], jitter: float = 0.04) -> tuple[float, ...]:
    """``rgb`` with a small random shift per channel, opaque rgba."""
    return (*np.clip(np.asarray(rgb) + rng.uniform(-jitter, jitter, 3), 0.0, 1.0), 1.0)


def pick_colour(rng: np.random.Generator, palette: dict[str, tuple[float, float, float]]) -> tuple[str, tuple[float, ...]]:
    """A random named colour of ``palette``: its name and a jittered rgba."""
    name = list(palette)[int(rng.integers(len(palette)))]
    return name, jittered(rng, palette[name])


def upright(radius: float, half_height: float, x: float, y: float, z: float, rgba: tuple[float, ...],
            collide: bool = True) -> Part:
    """A vertical cylinder centred at (x, y, z)."""
    return Part("cylinder", (radius, half_height), sapien.Pose([x, y, z], UPRIGHT), rgba, collide)


def box(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float, rgba: tuple[float, ...], collide: bool = True) -> Part:
    """An axis-aligned box spanning [x0, x1] × [y0, y1] × [z0, z1]."""
    return Part("box", ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2),
                sapien.Pose([(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2]), rgba, collide)
