"""Distractor objects: varied procedural shapes placed outside the task objects' areas."""

from __future__ import annotations

import numpy as np
import sapien

from anchordp3.sim.actors import Part
from anchordp3.sim.world import World

# Where clutter may go (x, y ranges on the table top, metres): the reachable part of the table.
CLUTTER_REGION = ((-0.45, 0.45), (-0.25, 0.3))


def random_shape(rng: np.random.Generator) -> tuple[list[Part], float]:
    """One distractor: a box, cylinder, sphere, capsule or a two-part compound, random size and
    colour. Returns its parts and the height of its centre above the table (metres)."""
    rgba = (*rng.uniform(0.05, 0.95, 3), 1.0)
    kind = int(rng.integers(5))
    if kind == 0:
        h = rng.uniform([0.012, 0.012, 0.01], [0.035, 0.035, 0.03])
        return [Part("box", tuple(h), rgba=rgba)], float(h[2])
    if kind == 1:
        r, hl = rng.uniform(0.012, 0.03), rng.uniform(0.01, 0.03)  # upright cylinder: rotate x axis to z
        return [Part("cylinder", (r, hl), sapien.Pose(q=[0.7071068, 0, 0.7071068, 0]), rgba)], hl
    if kind == 2:
        r = rng.uniform(0.012, 0.025)
        return [Part("sphere", (r,), rgba=rgba)], r
    if kind == 3:
        r, hl = rng.uniform(0.01, 0.02), rng.uniform(0.015, 0.04)  # capsule lying down
        return [Part("capsule", (r, hl), rgba=rgba)], r
    base = rng.uniform([0.015, 0.015, 0.008], [0.03, 0.03, 0.015])
    top_r = rng.uniform(0.008, 0.014)
    rgba2 = (*rng.uniform(0.05, 0.95, 3), 1.0)
    parts = [Part("box", tuple(base), rgba=rgba),
             Part("sphere", (top_r,), sapien.Pose([0, 0, base[2] + top_r]), rgba2)]
    return parts, float(base[2])


def add_clutter(world: World, keep_out: list[tuple[tuple[float, float], float]], max_count: int) -> list[str]:
    """Place 0..``max_count`` distractors on the table, each at least its radius plus the keep-out
    radius away from every ``((x, y), radius)`` in ``keep_out`` and from each other. Draws from the
    layout stream (physics-relevant) whether or not the world renders. Returns their names."""
    rng = world.layout_rng
    n = int(rng.integers(0, max_count + 1)) if max_count > 0 else 0
    placed: list[tuple[tuple[float, float], float]] = []
    names = []
    for i in range(n):
        parts, z = random_shape(rng)
        radius = 0.045
        for _ in range(30):
            xy = (float(rng.uniform(*CLUTTER_REGION[0])), float(rng.uniform(*CLUTTER_REGION[1])))
            if all(np.hypot(xy[0] - c[0], xy[1] - c[1]) > r + radius for c, r in keep_out + placed):
                yaw = rng.uniform(-np.pi, np.pi)
                pose = sapien.Pose([xy[0], xy[1], world.table_top + z + 0.002], [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])
                name = f"clutter_{i}"
                world.add_object(name, parts, pose, density=300.0)
                placed.append((xy, radius))
                names.append(name)
                break
    return names
