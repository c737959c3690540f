"""The ``place_object_scale`` family (one arm): ``place_mouse``, ``place_stapler``, ``place_bell``.

An electronic scale and one procedurally built object lie on the same side of the table; the arm
on that side (x < 0: left) picks the object at its grasp affordance and puts it on the scale's pad.
The success check follows RoboTwin's (REFERENCE.md): the object's xy within 0.035 m of the
scale's functional point (pad centre, on top), the object above the scale, the gripper open.

Every object and the scale have their frame origin at the bottom centre of their footprint, z up,
x along their length; all sizes are metres, angles radians.
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import sapien

from anchordp3.schemas.tasks import PLACE_BELL, PLACE_MOUSE, PLACE_STAPLER
from anchordp3.sim.actors import Part, pose_matrix
from anchordp3.sim.expert import Expert, top_down_pose
from anchordp3.sim.poses import HOME_FINGER_YAW, entity_yaw, grasp_yaw, yaw_pose
from anchordp3.sim.tasks.base import LayoutFailure, Task
from anchordp3.sim.tasks.shapes import ACROSS, FINGER_TIP_BELOW_TCP
from anchordp3.sim.tasks.shapes import jittered as _rgba
from anchordp3.sim.tasks.shapes import pick_colour as _pick
from anchordp3.sim.tasks.shapes import upright as _upright

# Named colours (rgb) per category; the name goes into the instruction.
MOUSE_COLOURS = {"black": (0.08, 0.08, 0.09), "white": (0.9, 0.9, 0.88), "grey": (0.5, 0.52, 0.55),
                 "blue": (0.15, 0.3, 0.75), "red": (0.75, 0.12, 0.12), "pink": (0.93, 0.58, 0.7)}
STAPLER_COLOURS = {"black": (0.08, 0.08, 0.09), "red": (0.78, 0.1, 0.1), "blue": (0.12, 0.25, 0.7),
                   "green": (0.1, 0.55, 0.25), "grey": (0.55, 0.57, 0.6)}
BELL_COLOURS = {"silver": (0.78, 0.79, 0.82), "gold": (0.85, 0.68, 0.2), "copper": (0.72, 0.42, 0.2)}
DARK = {"black": (0.06, 0.06, 0.07), "dark grey": (0.22, 0.22, 0.24), "brown": (0.3, 0.18, 0.1)}
WHITE, BLACK, SILVER = (0.9, 0.9, 0.9), (0.1, 0.1, 0.11), (0.7, 0.72, 0.75)
STEEL, DARK_GLASS, LIGHT_GLASS = (0.55, 0.57, 0.6), (0.15, 0.17, 0.2), (0.82, 0.87, 0.92)
SCALE_STYLES = [(WHITE, STEEL), (WHITE, DARK_GLASS), (BLACK, STEEL), (BLACK, LIGHT_GLASS), (SILVER, DARK_GLASS)]  # (body, pad)


@dataclass(frozen=True)
class ObjectModel:
    """One procedurally built task object.

    parts: primitives in the object frame. colour: its colour's name. grasp_point: tool-centre
    target in the object frame (3,). grasp_axis: finger-opening direction in the object frame,
    radians about z; of the two π-apart finger yaws that grasp the object, the expert takes the one
    nearest ``rest_yaw + grasp_axis`` (its grasp of the object lying at rest), so over the
    randomized yaw range the grasp turns with the object and never jumps by π between two scenes
    (a demonstration set whose grasps jump is bimodal where the policy must be exact).
    symmetric_yaw: True when the object may be grasped and placed at any yaw (round
    objects), else grasps and placements are π-symmetric about ``grasp_axis``. rest_yaw: the
    object's yaw relative to the table (at spawn) and to the scale (when placed). radius: clearance
    radius of its footprint with the open fingers around it.
    """

    parts: list[Part]
    colour: str
    grasp_point: tuple[float, float, float]
    grasp_axis: float
    symmetric_yaw: bool
    rest_yaw: float
    radius: float


def mouse_model(rng: np.random.Generator) -> ObjectModel:
    """A computer mouse ~0.10 long × 0.055–0.065 wide × 0.03–0.04 high: a stadium-shaped shell with
    a rounded top (three capsules along its length) and a scroll wheel; it points along +x.
    Grasped across its width at the middle, the finger tips 5 mm above its bottom."""
    length, width, height = rng.uniform(0.095, 0.11), rng.uniform(0.055, 0.065), rng.uniform(0.03, 0.04)
    shell = rng.uniform(0.55, 0.62) * height  # height of the straight-walled lower shell
    colour, rgba = _pick(rng, MOUSE_COLOURS)
    straight = length / 2 - width / 2
    r_top = height - shell  # the top capsules' centres lie on the shell's top face
    r_side = 0.75 * r_top
    parts = [
        Part("box", (straight, width / 2, shell / 2), sapien.Pose([0, 0, shell / 2]), rgba),
        _upright(width / 2, shell / 2, straight, 0, shell / 2, rgba),
        _upright(width / 2, shell / 2, -straight, 0, shell / 2, rgba),
        Part("capsule", (r_top, straight * 0.9), sapien.Pose([-0.1 * straight, 0, shell]), rgba),
    ]
    for side in (-1, 1):
        y = side * (width / 2 - r_side - 0.004)
        parts.append(Part("capsule", (r_side, straight * 0.8), sapien.Pose([-0.1 * straight, y, shell]), rgba))
    wheel = sapien.Pose([0.55 * straight + 0.01, 0, shell + 0.6 * r_top], ACROSS)
    parts.append(Part("cylinder", (0.006, 0.003), wheel, _rgba(rng, DARK["black"]), collide=False))
    return ObjectModel(parts, colour, (0.0, 0.0, FINGER_TIP_BELOW_TCP + 0.005), -np.pi / 2, False, np.pi / 2,
                       max(length / 2, 0.06))


def stapler_model(rng: np.random.Generator) -> ObjectModel:
    """A stapler 0.13–0.16 long × 0.03–0.04 wide: a base plate and a top arm with rounded fronts, a
    hinge block at the back and a staple magazine under the arm, the arm raised 1–3 cm above the
    base plate. Grasped across its width at the middle, the finger tips 4 mm above its bottom."""
    length, width = rng.uniform(0.13, 0.16), rng.uniform(0.03, 0.04)
    plate, arm_t, top = rng.uniform(0.006, 0.009), rng.uniform(0.012, 0.016), rng.uniform(0.035, 0.045)
    hinge = rng.uniform(0.022, 0.03)
    colour, rgba = _pick(rng, STAPLER_COLOURS)
    base_rgba = _rgba(rng, DARK[("black", "dark grey")[int(rng.integers(2))]])
    front = length / 2 - width / 2
    arm_len = length - rng.uniform(0.004, 0.012)
    nose = arm_len - width / 2  # from the back end to the centre of the arm's rounded front
    under = top - arm_t  # arm underside
    mag_bottom = plate + rng.uniform(0.003, 0.006)
    mag_len = arm_len - hinge - 0.015
    parts = [
        Part("box", ((front + length / 2) / 2, width / 2, plate / 2), sapien.Pose([(front - length / 2) / 2, 0, plate / 2]),
             base_rgba),
        _upright(width / 2, plate / 2, front, 0, plate / 2, base_rgba),
        Part("box", (hinge / 2, width / 2, (under - plate) / 2), sapien.Pose([-length / 2 + hinge / 2, 0, (under + plate) / 2]),
             base_rgba),
        Part("box", (nose / 2, width / 2, arm_t / 2), sapien.Pose([(nose - length) / 2, 0, top - arm_t / 2]), rgba),
        _upright(width / 2, arm_t / 2, nose - length / 2, 0, top - arm_t / 2, rgba),
        Part("box", (mag_len / 2, 0.35 * width, (under - mag_bottom) / 2),
             sapien.Pose([-length / 2 + hinge + mag_len / 2, 0, (under + mag_bottom) / 2]), _rgba(rng, (0.6, 0.6, 0.62))),
    ]
    return ObjectModel(parts, colour, (0.0, 0.0, FINGER_TIP_BELOW_TCP + 0.004), -np.pi / 2, False, 0.0,
                       max(length / 2, 0.06))


def bell_model(rng: np.random.Generator) -> ObjectModel:
    """A desk bell: a round base 0.06–0.07 in diameter, a dome (a sphere on a short cylindrical
    skirt) and a knob on a stem. Grasped across the skirt, the finger tips 3 mm above the base."""
    r_base, h_base = rng.uniform(0.03, 0.035), rng.uniform(0.01, 0.014)
    r_dome = rng.uniform(0.022, 0.026)
    centre = max(r_dome + 0.001, h_base + 0.012)  # dome sphere centre: its bottom stays inside the skirt
    colour, rgba = _pick(rng, BELL_COLOURS)
    base_rgba = _pick(rng, DARK)[1]
    stem_len, knob = rng.uniform(0.006, 0.01), rng.uniform(0.005, 0.007)
    top = centre + r_dome
    parts = [
        _upright(r_base, h_base / 2, 0, 0, h_base / 2, base_rgba),
        _upright(r_dome, (centre - h_base) / 2, 0, 0, (centre + h_base) / 2, rgba),
        Part("sphere", (r_dome,), sapien.Pose([0, 0, centre]), rgba),
        _upright(0.003, stem_len / 2 + 0.001, 0, 0, top + stem_len / 2 - 0.001, rgba),
        Part("sphere", (knob,), sapien.Pose([0, 0, top + stem_len + knob * 0.6]), rgba),
    ]
    return ObjectModel(parts, colour, (0.0, 0.0, h_base + FINGER_TIP_BELOW_TCP + 0.003), 0.0, True, 0.0, 0.06)


@dataclass(frozen=True)
class ScaleModel:
    """An electronic scale: parts in its frame, the pad's top centre (3,) in that frame (the
    functional point) and its footprint radius, metres."""

    parts: list[Part]
    pad_top: tuple[float, float, float]
    radius: float


def scale_model(rng: np.random.Generator) -> ScaleModel:
    """A low box ~0.14 × 0.12 × 0.02 with a thin pad of another colour on top and a display strip
    at its front (-y) edge."""
    hx, hy, hz = rng.uniform(0.065, 0.075), rng.uniform(0.055, 0.065), rng.uniform(0.008, 0.012)
    pad_hz = 0.0015
    body_rgb, pad_rgb = SCALE_STYLES[int(rng.integers(len(SCALE_STYLES)))]
    body, pad = _rgba(rng, body_rgb), _rgba(rng, pad_rgb)
    pad_y = 0.01  # the pad sits behind the display strip
    parts = [
        Part("box", (hx, hy, hz), sapien.Pose([0, 0, hz]), body),
        Part("box", (hx - 0.01, hy - 0.02, pad_hz), sapien.Pose([0, pad_y, 2 * hz + pad_hz]), pad),
        Part("box", (0.022, 0.006, 0.0008), sapien.Pose([0.02 - hx + 0.022, -hy + 0.011, 2 * hz + 0.0008]),
             _rgba(rng, (0.25, 0.45, 0.35)), collide=False),
        Part("box", (0.006, 0.005, 0.0015), sapien.Pose([hx - 0.016, -hy + 0.011, 2 * hz + 0.0015]),
             _rgba(rng, DARK["black"]), collide=False),
    ]
    return ScaleModel(parts, (0.0, pad_y, 2 * (hz + pad_hz)), float(np.hypot(hx, hy)))


class _PlaceOnScale(Task):
    """Pick one object with the arm on its side and put it on the electronic scale's pad."""

    noun: ClassVar[str]
    xy_tolerance = 0.035  # object xy to the functional point, metres (RoboTwin)
    drop = 0.004  # the object's bottom is released this far above the pad, metres
    region = ((0.06, 0.32), (-0.12, 0.16))  # |x| and y ranges of object and scale centres, metres

    @abstractmethod
    def make_object(self) -> ObjectModel:
        """This category's object, drawn from ``self.rng``."""

    def build(self) -> None:
        self.model = self.make_object()
        self.scale_model = scale_model(self.rng)
        obj_xy, scale_xy = self._layout(self.model.radius + self.scale_model.radius + 0.01)
        top = self.world.table_top
        self.world.add_object("scale", self.scale_model.parts, yaw_pose(*scale_xy, top, self.random_yaw()), density=2000.0)
        self.world.add_object(self.noun, self.model.parts, yaw_pose(*obj_xy, top, self.model.rest_yaw + self.random_yaw()))
        self.arm = "left" if obj_xy[0] < 0 else "right"
        self.keep_out = [(tuple(obj_xy), self.model.radius + 0.02), (tuple(scale_xy), self.scale_model.radius + 0.02)]

    def _layout(self, separation: float) -> tuple[np.ndarray, np.ndarray]:
        """Object and scale centres (x, y) on one random side of the table, at least
        ``separation`` metres apart."""
        side = 1.0 if self.rng.uniform() < 0.5 else -1.0
        noise = self.world.cfg.randomization.object_pose_noise
        (x0, x1), (y0, y1) = self.region
        lo, hi = np.array([x0 - noise, y0 - noise]), np.array([x1 + noise, y1 + noise])
        for _ in range(1000):
            a, b = self.rng.uniform(lo, hi, size=(2, 2))
            if np.linalg.norm(a - b) > separation:
                return a * [side, 1.0], b * [side, 1.0]
        raise LayoutFailure(f"{self.name}: no layout with object and scale {separation:.2f} m apart")

    def critical_objects(self) -> list[str]:
        return [self.noun, "scale"]

    def instruction(self) -> str:
        return f"Pick up the {self.model.colour} {self.noun} and place it on the electronic scale."

    def functional_point(self) -> np.ndarray:
        """World position (3,) of the scale pad's top centre, metres."""
        m = pose_matrix(self.world.objects["scale"].pose)
        return m[:3, :3] @ np.asarray(self.scale_model.pad_top) + m[:3, 3]

    def grasp_pose(self) -> tuple[np.ndarray, float]:
        """Where the expert grasps the object as it lies now: the TCP pose ``(4, 4)`` and the finger
        yaw (radians; for a round object the wrist's home yaw, any yaw grasps it)."""
        obj = self.world.objects[self.noun]
        m = pose_matrix(obj.pose)
        if self.model.symmetric_yaw:
            finger = HOME_FINGER_YAW
        else:
            rest = self.model.rest_yaw + self.model.grasp_axis  # not "nearest home": the mouse lies 90 degrees from it
            finger = grasp_yaw(entity_yaw(obj.pose) + self.model.grasp_axis, 2, preferred=rest)
        return top_down_pose(m[:3, :3] @ np.asarray(self.model.grasp_point) + m[:3, 3], finger), finger

    def plan(self, expert: Expert) -> None:
        grasp, finger = self.grasp_pose()
        expert.grasp(self.arm, grasp, self.noun)
        expert.place(self.arm, self._place_pose(expert, finger), self.noun)
        expert.home((self.arm,))

    def _place_pose(self, expert: Expert, finger: float) -> np.ndarray:
        """The TCP pose that sets the held object's origin ``drop`` above the functional point,
        at its rest yaw relative to the scale, from where the object sits in the hand now."""
        obj = self.world.objects[self.noun].pose
        offset = np.asarray(obj.p, dtype=np.float64) - expert.robot.ee_pose(self.arm)[:3, 3]
        if self.model.symmetric_yaw:
            place_finger = finger
        else:
            goal_yaw = entity_yaw(self.world.objects["scale"].pose) + self.model.rest_yaw
            place_finger = grasp_yaw(goal_yaw - (entity_yaw(obj) - finger), 2, preferred=finger)
        turn = place_finger - finger
        c, s = np.cos(turn), np.sin(turn)
        offset[:2] = [c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]]
        target = self.functional_point() + [0.0, 0.0, self.drop]
        return top_down_pose(target - offset, place_finger)

    def evaluate(self) -> dict[str, bool]:
        p = np.asarray(self.world.objects[self.noun].pose.p, dtype=np.float64)
        goal = self.functional_point()
        return {"over_pad": float(np.linalg.norm(p[:2] - goal[:2])) < self.xy_tolerance,  # RoboTwin's xy tolerance
                "on_pad": bool(p[2] > goal[2] - 0.01),  # not fallen beside it
                "released": self.gripper_open(self.arm)}


class PlaceMouse(_PlaceOnScale):
    """Put a computer mouse on the electronic scale."""

    spec = PLACE_MOUSE
    noun = "mouse"

    def make_object(self) -> ObjectModel:
        return mouse_model(self.rng)


class PlaceStapler(_PlaceOnScale):
    """Put a stapler on the electronic scale."""

    spec = PLACE_STAPLER
    noun = "stapler"

    def make_object(self) -> ObjectModel:
        return stapler_model(self.rng)


class PlaceBell(_PlaceOnScale):
    """Put a desk bell on the electronic scale."""

    spec = PLACE_BELL
    noun = "bell"

    def make_object(self) -> ObjectModel:
        return bell_model(self.rng)
