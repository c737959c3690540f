"""Building rigid actors from primitive parts, with visuals only when the scene renders."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import sapien

PartKind = Literal["box", "cylinder", "sphere", "capsule"]


@dataclass(frozen=True)
class Part:
    """One primitive shape of an actor.

    size: box half-extents (3,), cylinder/capsule (radius, half_length) along the part's x axis,
    sphere (radius,); metres. pose: part pose in the actor frame. rgba: colour in [0, 1].
    """

    kind: PartKind
    size: tuple[float, ...]
    pose: sapien.Pose = field(default_factory=sapien.Pose)
    rgba: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)
    collide: bool = True


def material(scene: sapien.Scene, friction: float) -> sapien.physx.PhysxMaterial:
    """A PhysX material with equal static and dynamic friction and no restitution."""
    return scene.create_physical_material(friction, friction, 0.0)


def build_actor(
    scene: sapien.Scene,
    name: str,
    parts: list[Part],
    pose: sapien.Pose,
    *,
    body: Literal["dynamic", "static", "kinematic"] = "dynamic",
    render: bool = True,
    density: float = 500.0,
    friction: float = 1.0,
    render_material: "sapien.render.RenderMaterial | None" = None,
) -> sapien.Entity:
    """Build an actor from ``parts`` at ``pose``.

    density: kg/m³ of the collision shapes. ``render_material`` overrides the parts' colours
    (used for textured surfaces). Visual shapes are skipped when ``render`` is False.
    """
    b = scene.create_actor_builder()
    mat = material(scene, friction)
    for p in parts:
        if p.collide:
            if p.kind == "box":
                b.add_box_collision(p.pose, half_size=p.size, material=mat, density=density)
            elif p.kind == "cylinder":
                b.add_cylinder_collision(p.pose, radius=p.size[0], half_length=p.size[1], material=mat, density=density)
            elif p.kind == "capsule":
                b.add_capsule_collision(p.pose, radius=p.size[0], half_length=p.size[1], material=mat, density=density)
            else:
                b.add_sphere_collision(p.pose, radius=p.size[0], material=mat, density=density)
        if render:
            m = render_material if render_material is not None else sapien.render.RenderMaterial(base_color=list(p.rgba))
            if p.kind == "box":
                b.add_box_visual(p.pose, half_size=p.size, material=m)
            elif p.kind == "cylinder":
                b.add_cylinder_visual(p.pose, radius=p.size[0], half_length=p.size[1], material=m)
            elif p.kind == "capsule":
                b.add_capsule_visual(p.pose, radius=p.size[0], half_length=p.size[1], material=m)
            else:
                b.add_sphere_visual(p.pose, radius=p.size[0], material=m)
    b.set_initial_pose(pose)
    if body == "static":
        return b.build_static(name=name)
    if body == "kinematic":
        return b.build_kinematic(name=name)
    return b.build(name=name)


def pose_matrix(pose: sapien.Pose) -> np.ndarray:
    """``(4, 4)`` float64 homogeneous matrix of a SAPIEN pose."""
    return np.asarray(pose.to_transformation_matrix(), dtype=np.float64)


def matrix_pose(m: np.ndarray) -> sapien.Pose:
    """SAPIEN pose of a ``(4, 4)`` homogeneous matrix."""
    return sapien.Pose(np.asarray(m, dtype=np.float32))
