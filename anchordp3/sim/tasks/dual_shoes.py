"""``place_dual_shoes`` (both arms): put a pair of shoes side by side on a mat, toes the same way.

A left and a right shoe (one procedural model, mirrored) lie on their own sides of the table at
random headings. Both arms grasp at once (each the shoe on its side, across the upper at the
shoe's centre of mass), then the left arm puts its shoe on the left target and goes home, then the
right arm does the same. The success check follows RoboTwin's ``dual_shoes_place`` (REFERENCE.md:
both shoes within 0.05 m of their targets, upright, grippers open) and adds the alignment this task
is about: each shoe's heading (heel → toe) within ``heading_tolerance`` of the mat's.

Shoe frame: origin at the bottom centre of the sole, x from heel to toe, y to the shoe's own left,
z up; sizes in metres, angles in radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sapien

from anchordp3.schemas.tasks import PLACE_DUAL_SHOES
from anchordp3.sim.actors import Part
from anchordp3.sim.expert import Expert, top_down_pose
from anchordp3.sim.poses import HOME_FINGER_YAW, entity_yaw, held_place_pose, wrap_angle, yaw_pose
from anchordp3.sim.tasks.base import Task
from anchordp3.sim.tasks.shapes import FINGER_TIP_BELOW_TCP, box, jittered, pick_colour, target_pad, upright

UPPER_COLOURS = {"white": (0.92, 0.92, 0.9), "black": (0.08, 0.08, 0.09), "red": (0.78, 0.12, 0.1),
                 "blue": (0.12, 0.28, 0.72), "grey": (0.5, 0.52, 0.55), "brown": (0.45, 0.28, 0.14),
                 "pink": (0.92, 0.55, 0.68), "green": (0.15, 0.5, 0.25)}
SOLE_COLOURS = {"white": (0.93, 0.93, 0.91), "black": (0.1, 0.1, 0.1), "gum": (0.72, 0.52, 0.3)}
MAT_COLOURS = [(0.35, 0.3, 0.26), (0.2, 0.25, 0.35), (0.55, 0.5, 0.42), (0.3, 0.33, 0.3)]
OPENING = (0.12, 0.1, 0.09, 1.0)  # the dark inside of the shoe, seen through the foot opening
FINGER_OUTER = 0.057  # open fingers: outer face this far from the TCP along the finger axis, metres


@dataclass(frozen=True)
class ShoeSize:
    """One pair's dimensions (metres): length, sole width, sole thickness, upper height at the
    heel, vamp height, and how far the toe bulges to the inner side."""

    length: float
    width: float
    sole: float
    heel_height: float
    vamp_height: float
    toe_shift: float


def shoe_size(rng: np.random.Generator) -> ShoeSize:
    """A random pair size: 0.15–0.19 long, 0.058–0.072 wide (fits the open gripper across)."""
    length, width = rng.uniform(0.15, 0.19), rng.uniform(0.058, 0.072)
    heel = rng.uniform(0.04, 0.055)
    return ShoeSize(length, width, rng.uniform(0.01, 0.016), heel, heel * rng.uniform(0.5, 0.7), width * rng.uniform(0.05, 0.12))


def shoe_parts(size: ShoeSize, foot: str, upper_rgba: tuple[float, ...], sole_rgba: tuple[float, ...],
               lace_rgba: tuple[float, ...]) -> list[Part]:
    """A shoe of ``size`` for ``foot`` (``left`` or ``right``): a sole with a round heel and a toe
    that bulges to the inner side (the right side, -y, of a left shoe), a high quarter with a
    rounded heel counter, a lower vamp with a rounded toe cap, and a visual-only dark foot opening
    and laces."""
    s = -1.0 if foot == "left" else 1.0  # the inner (big-toe) side
    L, W, t = size.length, size.width, size.sole
    r = W / 2
    wu = W - 0.008  # the upper sits 4 mm inside the sole's rim
    ru = wu / 2
    x_quarter = -0.05 * L  # where the high quarter meets the low vamp
    toe_y = s * size.toe_shift
    hu, hv = size.heel_height, size.vamp_height
    parts = [
        box(-L / 2 + r, L / 2 - r, -r, r, 0.0, t, sole_rgba),
        upright(r, t / 2, -L / 2 + r, 0.0, t / 2, sole_rgba),
        upright(r, t / 2, L / 2 - r, toe_y, t / 2, sole_rgba),
        box(-L / 2 + r, x_quarter, -ru, ru, t, t + hu, upper_rgba),
        upright(ru, hu / 2, -L / 2 + r, 0.0, t + hu / 2, upper_rgba),
        box(x_quarter, L / 2 - r, -ru + toe_y / 2, ru + toe_y / 2, t, t + hv, upper_rgba),
        upright(ru, hv * 0.45, L / 2 - r, toe_y, t + hv * 0.45, upper_rgba),
        # visual only: the collar (foot opening) and three laces across the vamp
        box(-L / 2 + r - 0.6 * ru, x_quarter - 0.006, -0.7 * ru, 0.7 * ru, t + hu, t + hu + 0.002, OPENING, collide=False),
    ]
    for i in range(3):
        x = x_quarter + 0.012 + i * 0.014
        parts.append(box(x - 0.003, x + 0.003, -0.75 * ru, 0.75 * ru, t + hv, t + hv + 0.0015, lace_rgba, collide=False))
    return parts


class PlaceDualShoes(Task):
    """Both arms put a pair of shoes side by side on the mat, toes pointing the mat's way."""

    spec = PLACE_DUAL_SHOES
    position_tolerance = 0.05  # shoe origin to its target, metres (RoboTwin)
    heading_tolerance = np.deg2rad(20.0)  # shoe heading to the mat's, radians
    upright_tolerance = np.deg2rad(20.0)  # shoe z axis to vertical, radians
    drop = 0.004  # the sole is released this far above the table, metres

    def build(self) -> None:
        rng = self.rng
        self.size = size = shoe_size(rng)
        self.colour, upper = pick_colour(rng, UPPER_COLOURS)
        sole_name = list(SOLE_COLOURS)[int(rng.integers(len(SOLE_COLOURS)))]
        sole = jittered(rng, SOLE_COLOURS[sole_name])
        laces = jittered(rng, (0.95, 0.95, 0.93) if self.colour in ("black", "blue", "brown", "green", "red") else (0.1, 0.1, 0.1))
        # the mat: toes point away from the robot (+y) give or take the yaw noise
        self.heading = float(np.pi / 2 + 0.5 * self.random_yaw())
        # a gap wide enough that the second gripper's open fingers clear the first shoe
        gap = FINGER_OUTER + 0.01 + size.toe_shift - size.width / 2 + rng.uniform(0.0, 0.015)
        sep = size.width + gap
        centre = np.array(self.table_xy((-0.04, -0.13), (0.04, -0.09), [], radius=0.0))
        across = np.array([np.cos(self.heading - np.pi / 2), np.sin(self.heading - np.pi / 2)])  # shoe-frame -y: towards +x
        self.targets = {"left": centre - across * sep / 2, "right": centre + across * sep / 2}
        top = self.world.table_top
        mat_rgba = jittered(rng, MAT_COLOURS[int(rng.integers(len(MAT_COLOURS)))])
        half = (size.length / 2 + 0.025, (sep + size.width) / 2 + 0.025)
        self.world.add_marker("mat", target_pad(*half, mat_rgba), yaw_pose(*centre, top, self.heading))
        radius = size.length / 2 + 0.015
        avoid = [(tuple(self.targets[a]), radius) for a in ("left", "right")]
        self.shoes = {}
        for arm in ("left", "right"):
            x0, x1 = (-0.3, -0.15) if arm == "left" else (0.15, 0.3)
            xy = self.table_xy((x0, 0.0), (x1, 0.2), avoid, radius)
            avoid.append((xy, radius))
            name = f"{arm}_shoe"
            self.world.add_object(name, shoe_parts(size, arm, upper, sole, laces),
                                  yaw_pose(*xy, top, float(rng.uniform(-np.pi, np.pi))), density=300.0)
            self.shoes[arm] = name
        self.keep_out = avoid + [(tuple(centre), half[1] + 0.02)]

    def critical_objects(self) -> list[str]:
        return [self.shoes["left"], self.shoes["right"], "mat"]

    def instruction(self) -> str:
        return f"Use both arms to put the pair of {self.colour} shoes side by side on the mat, toes pointing forward."

    # ----------------------------------------------------------------------------- expert
    def _grasp_pose(self, arm: str) -> tuple[np.ndarray, float]:
        """Top-down TCP pose across the upper at the shoe's centre of mass, and its finger yaw:
        of the two equivalent finger directions, the one that keeps both this grasp and the later
        place (turned by the shoe's heading error) nearest the wrist's comfortable yaw."""
        e = self.world.objects[self.shoes[arm]]
        com = e.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent).cmass_local_pose.p
        m = e.pose.to_transformation_matrix()
        point = m[:3, :3] @ np.array([com[0], com[1], self.size.sole + FINGER_TIP_BELOW_TCP + 0.004]) + m[:3, 3]
        yaw = entity_yaw(e.pose)
        turn = wrap_angle(self.heading - yaw)
        options = [wrap_angle(yaw + k * np.pi / 2) for k in (-1, 1)]
        finger = min(options, key=lambda f: max(abs(wrap_angle(f - HOME_FINGER_YAW)), abs(wrap_angle(f + turn - HOME_FINGER_YAW))))
        return top_down_pose(point, finger), finger

    def plan(self, expert: Expert) -> None:
        grasps = {arm: self._grasp_pose(arm) for arm in ("left", "right")}
        expert.grasp_pair({arm: g[0] for arm, g in grasps.items()}, self.shoes)
        for arm in ("left", "right"):
            shoe = self.world.objects[self.shoes[arm]]
            goal = [*self.targets[arm], self.world.table_top + self.drop]
            expert.place(arm, held_place_pose(shoe.pose, expert.robot.ee_pose(arm), grasps[arm][1], goal, self.heading),
                         self.shoes[arm])
            expert.home((arm,))

    # ----------------------------------------------------------------------------- success
    def shoe_conditions(self, arm: str) -> dict[str, bool]:
        """The ``arm``-side shoe: at its target on the mat, upright, toes along the mat's heading."""
        pose = self.world.objects[self.shoes[arm]].pose
        m = pose.to_transformation_matrix()
        return {f"{arm}_shoe_on_mat": float(np.linalg.norm(np.asarray(pose.p[:2]) - self.targets[arm])) < self.position_tolerance,
                f"{arm}_shoe_upright": bool(float(m[2, 2]) > np.cos(self.upright_tolerance)),
                f"{arm}_shoe_toes_forward": bool(abs(wrap_angle(entity_yaw(pose) - self.heading)) < self.heading_tolerance)}

    def shoe_ok(self, arm: str) -> bool:
        """Whether the ``arm``-side shoe is upright at its target with the mat's heading."""
        return all(self.shoe_conditions(arm).values())

    def evaluate(self) -> dict[str, bool]:
        return {**self.shoe_conditions("left"), **self.shoe_conditions("right"),
                "released": self.gripper_open("left") and self.gripper_open("right")}
