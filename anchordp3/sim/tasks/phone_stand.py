"""``place_phone_stand`` (one arm): stand a phone on a phone stand, leaning on its back plate.

A phone lies flat on one side of the table and a stand (a base plate with a front lip and a back
plate leaning back by 15–25°) faces the robot nearby. The arm on the phone's side grasps the
phone top-down across its width at its centre, tilts it to the back plate's slope (fingers along
the stand's width, approach into the plate), moves it in from the front and above until its lower
edge is just above the base between lip and plate, opens, and backs off along the plate normal.

The success check follows RoboTwin's (REFERENCE.md): the phone's functional point (the centre of
its lower short edge) within (0.045, 0.02, 0.02) m of the stand's (the centre of the line where
the back plate meets the base), here in the stand's frame (across, depth, up); and the phone
leaning on the plate: its long axis within ``lean_tolerance`` of the plate's. Grippers open.

Frames: the phone's origin is its centre, x along its length, z through its thickness; the
stand's origin is the bottom centre of its base, x across, y towards the back plate (the stand
faces -y), z up. Sizes are metres, angles radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sapien

from anchordp3.schemas.tasks import PLACE_PHONE_STAND
from anchordp3.sim.actors import Part, pose_matrix
from anchordp3.sim.expert import Expert, top_down_pose
from anchordp3.sim.poses import entity_yaw, grasp_yaw, wrap_angle, yaw_pose
from anchordp3.sim.tasks.base import Task
from anchordp3.sim.tasks.shapes import FINGER_TIP_BELOW_TCP, box, jittered, pick_colour

PHONE_COLOURS = {"black": (0.07, 0.07, 0.08), "white": (0.9, 0.9, 0.9), "silver": (0.72, 0.74, 0.77),
                 "blue": (0.2, 0.32, 0.62), "gold": (0.85, 0.72, 0.45), "pink": (0.9, 0.62, 0.68),
                 "green": (0.3, 0.5, 0.38)}
STAND_COLOURS = {"black": (0.1, 0.1, 0.11), "white": (0.88, 0.88, 0.86), "grey": (0.5, 0.52, 0.55),
                 "wooden": (0.62, 0.45, 0.28), "red": (0.7, 0.15, 0.12)}
SCREEN = (0.04, 0.05, 0.07, 1.0)


@dataclass(frozen=True)
class PhoneModel:
    """A phone: parts in its frame, colour name, length, width, thickness (metres)."""

    parts: list[Part]
    colour: str
    length: float
    width: float
    thickness: float


def phone_model(rng: np.random.Generator) -> PhoneModel:
    """A phone 0.13–0.16 × 0.062–0.074 × 0.008–0.011 (fits across the open gripper): a slab with
    a dark screen on one face, a camera block on the other and a few buttons on one side."""
    L, W, t = rng.uniform(0.13, 0.16), rng.uniform(0.062, 0.074), rng.uniform(0.008, 0.011)
    colour, rgba = pick_colour(rng, PHONE_COLOURS)
    border = rng.uniform(0.003, 0.006)
    cam = rng.uniform(0.012, 0.02)
    parts = [
        Part("box", (L / 2, W / 2, t / 2), rgba=rgba),
        box(-L / 2 + border, L / 2 - border, -W / 2 + border, W / 2 - border, t / 2, t / 2 + 0.0006, SCREEN, collide=False),
        box(L / 2 - 0.008 - cam, L / 2 - 0.008, W / 2 - 0.008 - cam, W / 2 - 0.008, -t / 2 - 0.0012, -t / 2,
            jittered(rng, SCREEN[:3], 0.02), collide=False),
        box(0.01, 0.03, W / 2, W / 2 + 0.0008, -0.002, 0.002, jittered(rng, rgba[:3], 0.05), collide=False),
    ]
    return PhoneModel(parts, colour, L, W, t)


@dataclass(frozen=True)
class StandModel:
    """A phone stand: parts in its frame, colour name, the back plate's lean from vertical
    (radians), and the stand's functional point (3,) in its frame: the centre of the line where
    the plate's front face meets the base's top."""

    parts: list[Part]
    colour: str
    lean: float
    functional_point: tuple[float, float, float]
    radius: float

    @property
    def up(self) -> np.ndarray:
        """The plate's up direction in the stand frame, (3,) unit."""
        return np.array([0.0, np.sin(self.lean), np.cos(self.lean)])

    @property
    def normal(self) -> np.ndarray:
        """The plate's front-face normal in the stand frame (towards the front and up), (3,) unit."""
        return np.array([0.0, -np.cos(self.lean), np.sin(self.lean)])


def stand_model(rng: np.random.Generator, phone_thickness: float) -> StandModel:
    """A stand 0.08–0.11 wide: a base plate 0.07–0.09 deep, a lip along its front edge, a back
    plate 0.08–0.1 tall leaning back 15–25° propped by a brace from the table behind it. The channel between lip and
    plate takes a phone of ``phone_thickness`` leaning on the plate."""
    bw, bd, bt = rng.uniform(0.08, 0.11), rng.uniform(0.07, 0.09), rng.uniform(0.008, 0.012)
    lean, ph, pw = rng.uniform(np.deg2rad(15), np.deg2rad(25)), rng.uniform(0.08, 0.1), bw * rng.uniform(0.7, 1.0)
    pt, lip_t, lip_h = 0.006, 0.006, rng.uniform(0.008, 0.012)
    colour, rgba = pick_colour(rng, STAND_COLOURS)
    y_plate = bd / 2 - 0.025  # the plate's front face meets the base here
    channel = phone_thickness / np.cos(lean) + rng.uniform(0.008, 0.014)
    up = np.array([0.0, np.sin(lean), np.cos(lean)])
    normal = np.array([0.0, -np.cos(lean), np.sin(lean)])
    foot = np.array([0.0, y_plate, bt])
    tilt = [np.cos(-lean / 2), np.sin(-lean / 2), 0.0, 0.0]  # about x: the box's z axis onto ``up``
    brace = foot + up * ph * 0.7 - normal * pt  # where the brace meets the plate's back, stand frame
    parts = [
        box(-bw / 2, bw / 2, -bd / 2, bd / 2, 0.0, bt, rgba),
        Part("box", (pw / 2, pt / 2, ph / 2), sapien.Pose(foot + up * ph / 2 - normal * pt / 2, tilt), rgba),
        box(-bw / 2, bw / 2, y_plate - channel - lip_t, y_plate - channel, bt, bt + lip_h, rgba),
        box(-0.006, 0.006, brace[1], brace[1] + 0.008, 0.0, brace[2], rgba),
    ]
    return StandModel(parts, colour, float(lean), tuple(foot), float(np.hypot(bw, bd) / 2 + 0.03))


class PlacePhoneStand(Task):
    """Put the phone on the stand, leaning on its back plate."""

    spec = PLACE_PHONE_STAND
    tolerance = (0.045, 0.02, 0.02)  # functional points, stand frame (across, depth, up), metres (RoboTwin)
    lean_tolerance = np.deg2rad(15.0)  # phone long axis to the plate's, radians
    edge_clearance = 0.004  # the phone's lower edge above the base when released, metres
    plate_gap = 0.003  # the phone's back face in front of the plate when released, metres
    pre = 0.09  # pre-place distance in front of and above the place pose, metres
    approach_rises = (0.6, 0.2, 1.2)  # pre-place directions tried: plate normal plus this much world up

    def build(self) -> None:
        rng = self.rng
        self.phone = phone_model(rng)
        self.stand = stand_model(rng, self.phone.thickness)
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        top = self.world.table_top
        stand_xy = self._xy(side, (-0.06, 0.06), (0.04, 0.14), [], self.stand.radius)
        phone_r = self.phone.length / 2 + 0.02
        phone_xy = self._xy(side, (0.1, 0.24), (-0.12, 0.02), [(stand_xy, self.stand.radius)], phone_r)
        self.world.add_object("stand", self.stand.parts, yaw_pose(*stand_xy, top, self.random_yaw()), density=1500.0)
        self.world.add_object("phone", self.phone.parts,
                              yaw_pose(*phone_xy, top + self.phone.thickness / 2, float(rng.uniform(-np.pi / 2, np.pi / 2))),
                              density=800.0)
        self.arm = "left" if side < 0 else "right"
        self.keep_out = [(stand_xy, self.stand.radius + 0.02), (phone_xy, phone_r + 0.01)]

    def _xy(self, side: float, xs, ys, avoid, radius: float) -> tuple[float, float]:
        """A free table position with ``side * x`` in ``xs`` and y in ``ys``."""
        x0, x1 = sorted((side * xs[0], side * xs[1]))
        return self.table_xy((x0, ys[0]), (x1, ys[1]), avoid, radius)

    def critical_objects(self) -> list[str]:
        return ["phone", "stand"]

    def instruction(self) -> str:
        return f"Pick up the {self.phone.colour} phone and put it on the {self.stand.colour} phone stand."

    # ----------------------------------------------------------------------------- geometry
    def _stand_frame(self) -> np.ndarray:
        return pose_matrix(self.world.objects["stand"].pose)

    def functional_points(self) -> tuple[np.ndarray, np.ndarray]:
        """World (3,) functional points of the phone (centre of its lower short edge) and of the
        stand (centre of the plate-base line)."""
        m = pose_matrix(self.world.objects["phone"].pose)
        ends = [m[:3, 3] + s * m[:3, 0] * self.phone.length / 2 for s in (-1.0, 1.0)]
        phone = min(ends, key=lambda p: float(p[2]))
        s = self._stand_frame()
        return phone, s[:3, :3] @ np.asarray(self.stand.functional_point) + s[:3, 3]

    # ----------------------------------------------------------------------------- expert
    def plan(self, expert: Expert) -> None:
        arm, phone = self.arm, self.world.objects["phone"]
        m = pose_matrix(phone.pose)
        finger = grasp_yaw(entity_yaw(phone.pose) + np.pi / 2, 2)
        grasp_at = m[:3, 3] + np.array([0.0, 0.0, -self.phone.thickness / 2 + FINGER_TIP_BELOW_TCP + 0.002])
        expert.grasp(arm, top_down_pose(grasp_at, finger), "phone", lift=0.1)
        place, away = self._place_pose(expert, finger)
        expert.place(arm, place, "phone", pre=self.pre, retreat=0.08, away=away)
        expert.home((arm,))

    def _place_pose(self, expert: Expert, finger: float) -> tuple[np.ndarray, np.ndarray]:
        """The tilted TCP pose ``(4, 4)`` that leans the held phone on the plate, and the world
        direction ``(3,)`` to come in from (in front of the plate and above it).

        Fingers along the stand's width, approach into the plate; the phone sits in the hand as
        measured now. The first of ``approach_rises`` and, for it, of the two finger directions
        (nearer the grasp's first) that the arm reaches at place and pre-place wins."""
        s = self._stand_frame()
        R, up, normal = s[:3, :3], s[:3, :3] @ self.stand.up, s[:3, :3] @ self.stand.normal
        tcp = expert.robot.ee_pose(self.arm)
        phone = pose_matrix(self.world.objects["phone"].pose)
        held = tcp[:3, :3].T @ (phone[:3, 3] - tcp[:3, 3])  # phone centre in the TCP frame
        centre = (R @ np.asarray(self.stand.functional_point) + s[:3, 3]
                  + up * (self.phone.length / 2 + self.edge_clearance) + normal * (self.phone.thickness / 2 + self.plate_gap))
        candidates = []
        for across in (R[:, 0], -R[:, 0]):
            pose = np.eye(4)
            pose[:3, 1], pose[:3, 2] = across, -normal
            pose[:3, 0] = np.cross(across, -normal)
            pose[:3, 3] = centre - pose[:3, :3] @ held
            candidates.append((abs(wrap_angle(np.arctan2(across[1], across[0]) - finger)), pose))
        candidates.sort(key=lambda c: c[0])
        for rise in self.approach_rises:
            away = normal + np.array([0.0, 0.0, rise])
            for _, pose in candidates:
                pre = pose.copy()
                pre[:3, 3] += self.pre * away / np.linalg.norm(away)
                if expert.reachable(self.arm, pose, pre):
                    return pose, away
        return candidates[0][1], normal + np.array([0.0, 0.0, self.approach_rises[0]])  # none: the move raises ik_failure

    # ----------------------------------------------------------------------------- success
    def evaluate(self) -> dict[str, bool]:
        phone_fp, stand_fp = self.functional_points()
        s = self._stand_frame()
        d = s[:3, :3].T @ (phone_fp - stand_fp)
        axis = pose_matrix(self.world.objects["phone"].pose)[:3, 0]
        plate_up = s[:3, :3] @ self.stand.up
        return {"phone_on_stand": all(abs(float(v)) < tol for v, tol in zip(d, self.tolerance)),
                "phone_leaning_on_plate": bool(abs(float(axis @ plate_up)) > np.cos(self.lean_tolerance)),
                "released": self.gripper_open(self.arm)}
