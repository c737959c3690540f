"""Simulator-supervised masks of task-critical objects, two ways.

* ``segmentation``: one render; a pixel is critical when SAPIEN's per-entity segmentation id
  belongs to a critical entity.
* ``depth_diff`` (the AnchorDP3 report's method): render, re-render with every critical entity
  invisible, and mark the pixels whose depth changed by more than a tolerance.
"""

from __future__ import annotations

import numpy as np
import sapien

from anchordp3.sim.cameras import ViewCapture
from anchordp3.sim.world import World


def critical_entities(world: World, names: list[str], include_robot: bool) -> list[sapien.Entity]:
    """The entities of the named objects and markers, plus the robot's links."""
    ents = [world.objects[n] for n in names if n in world.objects] + [world.markers[n] for n in names if n in world.markers]
    if include_robot:
        ents += [link.entity for link in world.robot.articulation.links]
    return ents


def segmentation_masks(captures: list[ViewCapture], entities: list[sapien.Entity]) -> np.ndarray:
    """``(V, H, W) uint8``: 1 where a view's segmentation id is one of ``entities``."""
    ids = np.array(sorted({e.per_scene_id for e in entities}), dtype=np.int32)
    return np.stack([np.isin(c.segmentation, ids) for c in captures]).astype(np.uint8)


def depth_diff_masks(world: World, captures: list[ViewCapture], entities: list[sapien.Entity], tolerance: float) -> np.ndarray:
    """``(V, H, W) uint8``: 1 where hiding ``entities`` changes a view's depth by more than
    ``tolerance`` metres (or turns a hit into no hit). ``captures`` were taken with them visible;
    their visibility is restored afterwards."""
    bodies = [b for e in entities for b in e.components if isinstance(b, sapien.render.RenderBodyComponent)]
    saved = [b.visibility for b in bodies]
    try:
        for b in bodies:
            b.visibility = 0.0
        hidden = world.capture(segmentation=False)
    finally:
        for b, v in zip(bodies, saved):
            b.visibility = v
        world.scene.update_render()
    masks = []
    for full, occluded in zip(captures, hidden):
        d0, d1 = full.depth, occluded.depth
        masks.append((d0 > 0) & ((d1 == 0) | (np.abs(d1 - d0) > tolerance)))
    return np.stack(masks).astype(np.uint8)
