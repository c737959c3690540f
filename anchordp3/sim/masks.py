"""Simulator-supervised masks of task-critical objects, two ways, each pixel labelled with its
object's *role*: 0 for anything not critical, ``k`` for the task's ``k``-th critical object (the
order of ``Task.critical_objects()``), ``ROBOT_ROLE`` for the robot's links (with
``include_robot``); a pixel is critical when its label is not 0.

* ``segmentation``: one render; a pixel's role is that of the entity SAPIEN's segmentation names.
* ``depth_diff`` (the AnchorDP3 report's method): render, re-render with every critical entity
  invisible, and mark the pixels whose depth changed by more than a tolerance, each with the role
  of the entity the full render shows there.
"""

from __future__ import annotations

import numpy as np
import sapien

from anchordp3.schemas.dataset import MAX_OBJECT_ROLES, ROBOT_ROLE
from anchordp3.sim.cameras import ViewCapture
from anchordp3.sim.world import World


Roles = list[tuple[int, list[sapien.Entity]]]  # (role, its entities)


def critical_roles(world: World, names: list[str], include_robot: bool) -> Roles:
    """Role ``k + 1`` for the ``k``-th named object or marker (its entity), and ``ROBOT_ROLE``
    for the robot's links when ``include_robot``."""
    if len(names) > MAX_OBJECT_ROLES:
        raise ValueError(f"critical objects: {len(names)}, more than the {MAX_OBJECT_ROLES} roles a label holds")
    roles = [(k + 1, [world.objects[n] if n in world.objects else world.markers[n]])
             for k, n in enumerate(names) if n in world.objects or n in world.markers]
    if include_robot:
        roles.append((ROBOT_ROLE, [link.entity for link in world.robot.articulation.links]))
    return roles


def role_table(roles: Roles) -> np.ndarray:
    """``(max id + 1,) uint8``: the role of each per-scene segmentation id (0 for the rest)."""
    table = np.zeros(max((e.per_scene_id for _, ents in roles for e in ents), default=0) + 1, np.uint8)
    for role, ents in roles:
        table[[e.per_scene_id for e in ents]] = role
    return table


def _roles_of(segmentation: np.ndarray, table: np.ndarray) -> np.ndarray:
    """``(H, W) uint8``: each pixel's role from its segmentation id."""
    ids = np.asarray(segmentation)
    return np.where(ids < len(table), table[np.minimum(ids, len(table) - 1)], 0).astype(np.uint8)


def segmentation_masks(captures: list[ViewCapture], roles: Roles) -> np.ndarray:
    """``(V, H, W) uint8``: each pixel's role, from the view's segmentation ids."""
    table = role_table(roles)
    return np.stack([_roles_of(c.segmentation, table) for c in captures])


def depth_diff_masks(world: World, captures: list[ViewCapture], roles: Roles, tolerance: float) -> np.ndarray:
    """``(V, H, W) uint8``: where hiding every critical entity changes a view's depth by more than
    ``tolerance`` metres (or turns a hit into no hit), the role of the entity the capture shows
    there (``captures`` were taken with them visible, with segmentation); 0 elsewhere. Their
    visibility is restored afterwards."""
    entities = [e for _, ents in roles for e in ents]
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
    table = role_table(roles)
    masks = []
    for full, occluded in zip(captures, hidden):
        d0, d1 = full.depth, occluded.depth
        changed = (d0 > 0) & ((d1 == 0) | (np.abs(d1 - d0) > tolerance))
        masks.append(np.where(changed, _roles_of(full.segmentation, table), 0).astype(np.uint8))
    return np.stack(masks)
