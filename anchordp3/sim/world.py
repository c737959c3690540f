"""One simulated episode's world: table, wall, lights, robot, cameras, clutter, and stepping.

World frame: table centred at x = y = 0, top at z ≈ 0.74 m, the robot behind the table edge at
y < 0 facing +y; the robot's left arm is at -x.
"""

from __future__ import annotations

import os

import numpy as np
import sapien

from anchordp3.schemas.sim import WorldConfig
from anchordp3.sim.actors import Part, build_actor
from anchordp3.sim.appearance import Lights, surface_material
from anchordp3.sim.cameras import CameraRig, ViewCapture
from anchordp3.sim.robot import Robot
from anchordp3.sim.seeding import rng

TABLE_TOP = 0.74
TABLE_HALF_XY = (0.6, 0.35)


class _PhysicsOnlyScene(sapien.Scene):
    """A scene without a render system (SAPIEN's own destructor assumes one)."""

    def __del__(self):
        for e in list(self.entities):
            self.remove_entity(e)


_RENDERER: list = []  # one renderer per process: SAPIEN frees it (and its compiled shaders) with the last scene
# Mesa's CPU Vulkan driver (lavapipe) rasterises on the calling thread when this is 0, instead of
# handing each draw to a pool of its own threads: a tenth less CPU per frame at the stages' image
# sizes, and a worker that reserves one core uses one. Read when the renderer is made; a value set
# in the environment wins, and a GPU's driver ignores it.
LAVAPIPE_THREADS = "0"


def _make_scene(render: bool) -> sapien.Scene:
    if not render:
        return _PhysicsOnlyScene([sapien.physx.PhysxCpuSystem()])
    try:
        if not _RENDERER:
            os.environ.setdefault("LP_NUM_THREADS", LAVAPIPE_THREADS)
            _RENDERER.append(sapien.render.SapienRenderer())
        return sapien.Scene()
    except RuntimeError as e:
        raise RuntimeError(
            f"no Vulkan rendering device ({e}). On a machine without a GPU install Mesa lavapipe >= 24.3 "
            "(Debian 12: `apt-get install -t bookworm-backports mesa-vulkan-drivers`, done by scripts/setup.sh)"
        ) from None


class World:
    """The scene of one episode, built deterministically from ``seed``.

    render: False builds physics only (no visuals, no cameras): the CPU rollout phase.
    """

    def __init__(self, cfg: WorldConfig, seed: int, render: bool = False):
        self.cfg, self.seed, self.render = cfg, int(seed), render
        self.layout_rng = rng(seed, "layout")
        self.appearance_rng = rng(seed, "appearance")
        self.scene = _make_scene(render)
        self.scene.set_timestep(1.0 / cfg.sim.physics_hz)
        r = cfg.randomization
        lo, hi = r.table_height_range
        self.table_top = TABLE_TOP + float(self.layout_rng.uniform(lo, hi))
        self._build_room()
        self.robot = Robot(self.scene, cfg.robot, render)
        self.objects: dict[str, sapien.Entity] = {}
        self.markers: dict[str, sapien.Entity] = {}
        self.lights: Lights | None = None
        self.cameras: CameraRig | None = None
        if render:
            self.lights = Lights(self.scene, self.appearance_rng, r)
            mounts = {f"{a}_ee": self.robot.ee_link[a].entity for a in ("left", "right")}
            self.cameras = CameraRig(self.scene, cfg.cameras, mounts, rng(seed, "cameras"), r.camera_jitter_pos, r.camera_jitter_rot_deg)

    # ----------------------------------------------------------------------------- building
    def _build_room(self) -> None:
        r, ar = self.cfg.randomization, self.appearance_rng
        ground = self.scene.create_actor_builder()
        ground.add_plane_collision(sapien.Pose(q=[0.7071068, 0, -0.7071068, 0]))
        if self.render:
            ground.add_plane_visual(sapien.Pose(q=[0.7071068, 0, -0.7071068, 0]), scale=[10, 10, 10],
                                    material=sapien.render.RenderMaterial(base_color=[0.35, 0.33, 0.3, 1]))
        ground.build_static(name="ground")
        hx, hy = TABLE_HALF_XY
        h = self.table_top / 2
        table_mat = surface_material(ar, r.textured_table, r.plain_texture_prob, (0.72, 0.62, 0.5, 1)) if self.render else None
        self.table = build_actor(self.scene, "table", [Part("box", (hx, hy, h))], sapien.Pose([0, 0, h]),
                                 body="static", render=self.render, render_material=table_mat, friction=0.8)
        if self.render:
            wall_mat = surface_material(ar, r.textured_wall, r.plain_texture_prob, (0.85, 0.85, 0.8, 1))
            build_actor(self.scene, "wall", [Part("box", (2.0, 0.02, 1.2), collide=False)], sapien.Pose([0, 0.9, 1.2]),
                        body="static", render=True, render_material=wall_mat)

    def add_object(self, name: str, parts: list[Part], pose: sapien.Pose, *, body: str = "dynamic",
                   density: float = 500.0, friction: float = 1.0) -> sapien.Entity:
        """Add a task or clutter object built from primitive parts; registered under ``name``."""
        if name in self.objects:
            raise ValueError(f"object {name!r} already exists")
        e = build_actor(self.scene, name, parts, pose, body=body, render=self.render, density=density, friction=friction)
        self.objects[name] = e
        return e

    def add_marker(self, name: str, parts: list[Part], pose: sapien.Pose) -> None:
        """A visual-only static object (e.g. a target pad): seen by cameras, absent from physics,
        and not built at all in physics-only worlds."""
        if self.render:
            self.markers[name] = build_actor(self.scene, name, [Part(p.kind, p.size, p.pose, p.rgba, collide=False) for p in parts],
                                             pose, body="static", render=True)

    # ----------------------------------------------------------------------------- stepping
    def step(self, n: int = 1) -> None:
        """Advance physics by ``n`` steps."""
        for _ in range(n):
            self.scene.step()

    def control_step(self, joint_action: np.ndarray) -> None:
        """Command a joint-space action and advance one control period."""
        self.robot.command(joint_action)
        self.step(self.cfg.sim.substeps)

    def settle_and_check(self) -> bool:
        """Let the new scene come to rest, then check that no dynamic object keeps rotating by more
        than the configured angle (RoboTwin's stability test). True when the scene is stable."""
        s = self.cfg.sim
        self.step(s.settle_steps)
        dyn = [e for e in self.objects.values() if isinstance(e.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent), sapien.physx.PhysxRigidDynamicComponent)]
        q0 = [e.pose.q for e in dyn]
        self.step(s.stability_steps)
        limit = np.deg2rad(s.stability_max_rot_deg)
        for e, q in zip(dyn, q0):
            dot = abs(float(np.dot(q, e.pose.q)))
            if 2 * np.arccos(min(1.0, dot)) > limit or e.pose.p[2] < self.table_top - 0.05:
                return False
        return True

    # ----------------------------------------------------------------------------- state
    def pack(self) -> bytes:
        """The exact physical state (poses, velocities, joint states), for restoring later."""
        return self.scene.physx_system.pack()

    def unpack(self, data: bytes) -> None:
        """Restore a state from :meth:`pack`; the commanded targets are the caller's to restore."""
        self.scene.physx_system.unpack(data)

    # ----------------------------------------------------------------------------- rendering
    def capture(self, segmentation: bool = True) -> list[ViewCapture]:
        """Render all views at the current instant (render worlds only)."""
        if self.cameras is None:
            raise RuntimeError("this world was built with render=False")
        if self.lights is not None:
            self.lights.before_render()
        self.scene.update_render()
        return self.cameras.capture(segmentation)

    def entity_ids(self, names: list[str], include_robot: bool = False) -> set[int]:
        """Segmentation ids (per-entity ``per_scene_id``) of the named objects and markers, plus the robot's links."""
        ids = {self.objects[n].per_scene_id for n in names if n in self.objects}
        ids |= {self.markers[n].per_scene_id for n in names if n in self.markers}
        if include_robot:
            ids |= {link.entity.per_scene_id for link in self.robot.articulation.links}
        return ids
