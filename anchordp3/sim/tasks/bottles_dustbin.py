"""``put_bottles_dustbin`` (both arms): put three bottles into a dustbin at one side of the table.

The dustbin stands in the back half of the table towards its left or right edge (as far out as
the head camera still sees it); only the arm on that side (the *bin arm*) reaches over its
middle. Bottles on the bin's side are picked by the bin arm and put in directly. A bottle on the
far side is picked by the *far arm* and handed over by place-in-the-middle-then-regrasp: the far
arm stands it upright at a handover spot mid-table and goes home, then the bin arm picks it there
and lowers it into the bin. (A true in-air handover, both grippers on one bottle, would need a
second grasp axis; standing the bottle on the table is as informative for the policy and far more
reliable.) Every scene has one or two far bottles, and a third when the bin's side has no room
left. That makes 34-43 anchors per episode, more than the report's 10-30 for one grasp-place
task: each handover is two grasp-places.

The success check follows RoboTwin's (REFERENCE.md): every bottle inside the bin, here its centre
(middle of its axis) within the bin's inner radius and above its floor, the lower end of its axis
below the rim.

Frames: a bottle's origin is the centre of its bottom, z along its axis; the bin's origin is the
centre of its floor's underside, z up. Sizes are metres, angles radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sapien

from anchordp3.schemas.tasks import PUT_BOTTLES_DUSTBIN
from anchordp3.sim.actors import Part
from anchordp3.sim.expert import Expert, top_down_pose
from anchordp3.sim.poses import HOME_FINGER_YAW, held_place_pose, yaw_pose
from anchordp3.sim.tasks.base import LayoutFailure, Task
from anchordp3.sim.tasks.shapes import FINGER_TIP_BELOW_TCP, jittered, pick_colour, upright

BOTTLE_COLOURS = {"green": (0.2, 0.58, 0.3), "blue": (0.3, 0.5, 0.85), "clear": (0.82, 0.88, 0.92),
                  "brown": (0.42, 0.24, 0.1), "orange": (0.95, 0.55, 0.12), "pink": (0.92, 0.55, 0.68)}
CAP_COLOURS = [(0.9, 0.9, 0.9), (0.1, 0.1, 0.1), (0.8, 0.1, 0.1), (0.15, 0.3, 0.8), (0.95, 0.8, 0.15)]
BIN_COLOURS = {"grey": (0.5, 0.52, 0.55), "green": (0.18, 0.45, 0.25), "blue": (0.15, 0.3, 0.65),
               "black": (0.1, 0.1, 0.11), "white": (0.88, 0.88, 0.86)}
N_BOTTLES = 3


@dataclass(frozen=True)
class BottleModel:
    """A bottle: parts in its frame, its colour's name, total height, body radius, and the TCP
    height of a top-down grasp around its cap (metres)."""

    parts: list[Part]
    colour: str
    height: float
    radius: float
    grasp_height: float


def bottle_model(rng: np.random.Generator) -> BottleModel:
    """A bottle 0.1–0.15 tall: a cylindrical body 0.044–0.056 across with a label band, a
    hemispherical shoulder, a neck and a slightly wider cap. Grasped top-down around neck and cap,
    the finger tips 4 mm above the shoulder."""
    rb, hb = rng.uniform(0.022, 0.028), rng.uniform(0.05, 0.08)
    rn, ln, lc = rng.uniform(0.011, 0.014), rng.uniform(0.012, 0.025), rng.uniform(0.012, 0.018)
    rc = rn + rng.uniform(0.001, 0.003)
    colour, rgba = pick_colour(rng, BOTTLE_COLOURS)
    cap = jittered(rng, CAP_COLOURS[int(rng.integers(len(CAP_COLOURS)))])
    label = jittered(rng, tuple(rng.uniform(0.1, 0.95, 3)), 0.0)
    label_h = hb * rng.uniform(0.3, 0.6)
    shoulder_top = hb + rb
    neck_z0 = shoulder_top - 0.003  # the neck starts inside the shoulder
    parts = [
        upright(rb, hb / 2, 0, 0, hb / 2, rgba),
        Part("sphere", (rb,), sapien.Pose([0, 0, hb]), rgba),
        upright(rn, ln / 2, 0, 0, neck_z0 + ln / 2, rgba),
        upright(rc, lc / 2, 0, 0, neck_z0 + ln + lc / 2, cap),
        upright(rb + 0.0008, label_h / 2, 0, 0, hb * 0.5, label, collide=False),
    ]
    return BottleModel(parts, colour, neck_z0 + ln + lc, rb, shoulder_top + FINGER_TIP_BELOW_TCP + 0.004)


@dataclass(frozen=True)
class BinModel:
    """A round dustbin: parts in its frame, colour name, inner radius, floor thickness and rim
    height above its bottom (metres)."""

    parts: list[Part]
    colour: str
    inner_radius: float
    floor: float
    height: float

    @property
    def outer_radius(self) -> float:
        return self.inner_radius + 0.008


def bin_model(rng: np.random.Generator) -> BinModel:
    """A round bin 0.16–0.2 across and 0.1–0.13 tall: a floor disc and a wall of 12–16 flat
    segments, a rim band of a second shade, and a pedal at its front (-y) side."""
    r, h = rng.uniform(0.08, 0.1), rng.uniform(0.1, 0.13)
    floor, wall = 0.006, 0.006
    n = int(rng.integers(12, 17))
    colour, rgba = pick_colour(rng, BIN_COLOURS)
    rim = jittered(rng, tuple(np.clip(np.asarray(rgba[:3]) * 0.6, 0, 1)), 0.0)
    parts = [upright(r + wall, floor / 2, 0, 0, floor / 2, rgba)]
    half_width = (r + wall) * np.tan(np.pi / n) + 0.002
    for i in range(n):
        a = 2 * np.pi * i / n
        q = [np.cos(a / 2), 0, 0, np.sin(a / 2)]
        c = (r + wall / 2) * np.array([np.cos(a), np.sin(a)])
        parts.append(Part("box", (wall / 2, half_width, h / 2), sapien.Pose([*c, h / 2], q), rgba))
        c = (r + wall / 2 + 0.0015) * np.array([np.cos(a), np.sin(a)])
        parts.append(Part("box", (wall / 2 + 0.0015, half_width, 0.006), sapien.Pose([*c, h - 0.006], q), rim, collide=False))
    parts.append(Part("box", (0.025, 0.015, 0.004), sapien.Pose([0, -(r + wall + 0.012), 0.006]), rim, collide=False))
    return BinModel(parts, colour, r, floor, h)


class PutBottlesDustbin(Task):
    """Put every bottle into the dustbin, handing far bottles over through the middle of the table.

    The bin arm lowers each bottle in upright where the bin has most room, the finger tips just
    above the rim, and lets go (a fall of a few centimetres)."""

    spec = PUT_BOTTLES_DUSTBIN
    drop_clearance = 0.025  # bottle bottom above the rim (and the bottles in the bin) when carried in, metres
    place_drop = 0.004  # bottle bottom above the table when stood at the handover spot, metres

    def build(self) -> None:
        rng = self.rng
        self.side = 1.0 if rng.uniform() < 0.5 else -1.0  # the bin's side of the table (+1: right, +x)
        self.bin_arm, self.far_arm = ("right", "left") if self.side > 0 else ("left", "right")
        self.bin = bin_model(rng)
        top = self.world.table_top
        bin_xy = self._xy((0.18, 0.22), (0.1, 0.15), [], self.bin.outer_radius)
        self.world.add_object("dustbin", self.bin.parts, yaw_pose(*bin_xy, top, self.random_yaw()), density=1500.0)
        handover = self._xy((-0.04, 0.04), (-0.14, -0.08), [], 0.0)
        self.handover = np.array(handover)
        avoid = [(bin_xy, self.bin.outer_radius + 0.01), (handover, 0.06)]
        n_far = 1 + int(rng.integers(2))
        self.bottles, self.models = [], {}
        for i in range(N_BOTTLES):
            model = bottle_model(rng)
            xy = None
            if i >= n_far:
                try:
                    xy = self._xy((0.06, 0.3), (-0.14, 0.14), avoid, model.radius + 0.045)
                except LayoutFailure:
                    pass  # no room left beside the bin: this one goes to the far side too
            if xy is None:
                xy = self._xy((-0.3, -0.08), (-0.1, 0.16), avoid, model.radius + 0.045)
            avoid.append((xy, model.radius + 0.045))
            name = f"bottle_{i}"
            self.world.add_object(name, model.parts, yaw_pose(*xy, top, float(rng.uniform(-np.pi, np.pi))), density=300.0)
            self.bottles.append(name)
            self.models[name] = model
        self.keep_out = avoid

    def _xy(self, xs: tuple[float, float], ys: tuple[float, float], avoid, radius: float) -> tuple[float, float]:
        """A free table position with ``|x|`` in ``xs`` on the bin's side (negative ``xs`` for the
        far side) and y in ``ys``."""
        x0, x1 = sorted((self.side * xs[0], self.side * xs[1]))
        return self.table_xy((x0, ys[0]), (x1, ys[1]), avoid, radius)

    def critical_objects(self) -> list[str]:
        return [*self.bottles, "dustbin"]

    def instruction(self) -> str:
        colours = list(dict.fromkeys(self.models[b].colour for b in self.bottles))  # unique, in order
        listed = f"three {colours[0]}" if len(colours) == 1 else ", ".join(colours[:-1]) + " and " + colours[-1]
        where = "right" if self.side > 0 else "left"
        return f"Put the {listed} bottles into the {self.bin.colour} dustbin on the {where}."

    # ----------------------------------------------------------------------------- expert
    def _grasp(self, expert: Expert, arm: str, bottle: str, lift: float) -> None:
        e = self.world.objects[bottle]
        m = e.pose.to_transformation_matrix()
        point = m[:3, 3] + m[:3, 2] * self.models[bottle].grasp_height
        expert.grasp(arm, top_down_pose(point, HOME_FINGER_YAW), bottle, lift=lift)

    def _place(self, expert: Expert, arm: str, bottle: str, goal_xyz, pre: float = 0.08) -> None:
        pose = held_place_pose(self.world.objects[bottle].pose, expert.robot.ee_pose(arm), HOME_FINGER_YAW, goal_xyz, None)
        expert.place(arm, pose, bottle, pre=pre, retreat=pre, hold_radius=self.models[bottle].height)

    def drop_points(self) -> list[np.ndarray]:
        """Candidate release points of bottles' bottom centres, ``(2,)`` world xy, metres, in order
        of preference: first three 120° apart around the bin's centre (the side away from the
        table's middle, the front, the middle side: a bottle carried in from the middle passes
        over none already there), then nine more on the same circle and the centre. None lies more
        than 2.5 cm behind the bin's centre: lifted high there, the bin arm would be out of reach."""
        b = self.world.objects["dustbin"].pose.to_transformation_matrix()
        radius = min(0.04, self.bin.inner_radius - max(m.radius for m in self.models.values()) - 0.012)
        angles = np.deg2rad([30.0, -90.0, 150.0, 0.0, -30.0, -60.0, -120.0, -150.0, 180.0, 60.0, 120.0, 90.0])
        local = [np.array([self.side * radius * np.cos(a), radius * np.sin(a), 0.0]) for a in angles] + [np.zeros(3)]
        points = [(b[:3, :3] @ p + b[:3, 3])[:2] for p in local]
        return [p for p in points if p[1] < b[1, 3] + 0.025]

    def _drop_xy(self, dropped: list[str]) -> np.ndarray:
        """The candidate release point farthest (in xy) from the bottles already in the bin, as
        they lie now (upright or toppled); the first candidate when the bin is empty."""
        def clearance(p: np.ndarray) -> float:
            gaps = [np.inf]
            for name in dropped:
                m = self.world.objects[name].pose.to_transformation_matrix()
                a, d = m[:2, 3], m[:2, 2] * self.models[name].height
                f = float(np.clip((p - a) @ d / max(float(d @ d), 1e-12), 0.0, 1.0))
                gaps.append(float(np.linalg.norm(p - (a + f * d))) - self.models[name].radius)
            return min(gaps)

        return max(self.drop_points(), key=clearance)  # max keeps the first of equals

    def _top(self, name: str) -> float:
        """World z of the highest point of bottle ``name`` as it lies now."""
        m = self.world.objects[name].pose.to_transformation_matrix()
        ends = [m[2, 3], m[2, 3] + m[2, 2] * self.models[name].height]
        return max(ends) + self.models[name].radius * float(np.hypot(m[2, 0], m[2, 1]))

    def _carry_height(self, dropped: list[str]) -> float:
        """World z of a bottle's bottom when carried over the bin: ``drop_clearance`` above the
        rim and above every bottle already in it."""
        rim = float(self.world.objects["dustbin"].pose.p[2]) + self.bin.height
        return max([rim, *(self._top(n) for n in dropped)]) + self.drop_clearance

    def _release_height(self, bottle: str, xy: np.ndarray, dropped: list[str]) -> float:
        """World z of the bottom of ``bottle`` when released at ``xy``: lowered into the bin so it
        lands upright, but with the finger tips 5 mm above the rim (the opening fingers clear the
        wall) and 1 cm above any bottle already in the bin near ``xy``."""
        floor = float(self.world.objects["dustbin"].pose.p[2]) + self.bin.floor
        rim = float(self.world.objects["dustbin"].pose.p[2]) + self.bin.height
        tips = self.models[bottle].grasp_height - FINGER_TIP_BELOW_TCP
        z = max(floor + 0.01, rim + 0.005 - tips)
        for name in dropped:
            m = self.world.objects[name].pose.to_transformation_matrix()
            a, d = m[:2, 3], m[:2, 2] * self.models[name].height
            f = float(np.clip((xy - a) @ d / max(float(d @ d), 1e-12), 0.0, 1.0))
            if float(np.linalg.norm(xy - (a + f * d))) < self.models[name].radius + self.models[bottle].radius + 0.005:
                z = max(z, self._top(name) + 0.01)
        return z

    def _to_bin(self, expert: Expert, bottle: str, dropped: list[str]) -> None:
        """The bin arm picks ``bottle``, lifts it clear of the bin and what is in it, carries it
        over where the bin has most room, lowers it in and lets go."""
        xy = self._drop_xy(dropped)
        carry = self._carry_height(dropped)
        release = self._release_height(bottle, xy, dropped)
        self._grasp(expert, self.bin_arm, bottle, lift=carry + 0.01 - float(self.world.objects[bottle].pose.p[2]))
        self._place(expert, self.bin_arm, bottle, [*xy, release], pre=max(carry - release, 0.02))
        dropped.append(bottle)

    def plan(self, expert: Expert) -> None:
        top = self.world.table_top
        near = [b for b in self.bottles if np.sign(self.world.objects[b].pose.p[0]) == self.side]
        # far bottles nearest the handover spot first: the far arm reaching for the spot would
        # sweep over a bottle left standing between
        far = sorted((b for b in self.bottles if b not in near),
                     key=lambda b: float(np.linalg.norm(self.world.objects[b].pose.p[:2] - self.handover)))
        dropped: list[str] = []
        for bottle in near:
            self._to_bin(expert, bottle, dropped)
        clear = max(m.height for m in self.models.values()) + 0.02  # carried over standing bottles
        for bottle in far:
            self._grasp(expert, self.far_arm, bottle, lift=clear)
            self._place(expert, self.far_arm, bottle, [*self.handover, top + self.place_drop])
            expert.home((self.far_arm,))
            self._to_bin(expert, bottle, dropped)
        expert.home((self.bin_arm,))

    # ----------------------------------------------------------------------------- success
    def bottle_in_bin(self, bottle: str) -> bool:
        """Whether ``bottle`` is inside the bin: its centre within the bin's inner radius and above
        its floor, and the lower end of its axis below the rim (a bottle may stick out of the top,
        not lie across it)."""
        m = self.world.objects[bottle].pose.to_transformation_matrix()
        h = self.models[bottle].height
        b = self.world.objects["dustbin"].pose.to_transformation_matrix()
        bottom, top, centre = (b[:3, :3].T @ (m[:3, 3] + m[:3, 2] * f - b[:3, 3]) for f in (0.0, h, h / 2))
        lower = min(float(bottom[2]), float(top[2]))
        return (float(np.hypot(centre[0], centre[1])) < self.bin.inner_radius
                and float(centre[2]) > self.bin.floor and lower < self.bin.height)

    def evaluate(self) -> dict[str, bool]:
        return {f"{b}_in_bin": self.bottle_in_bin(b) for b in self.bottles}
