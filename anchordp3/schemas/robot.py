"""``RobotSpec``: which URDF is the robot and which of its joints and links are what.

Any URDF robot with two arms of equal joint count and a parallel-jaw gripper per arm can be
configured; the state layout follows from the arms' joint count (``StateLayout(dof)``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from functools import cached_property
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, model_validator

from anchordp3.schemas.state import ARMS, StateLayout

ASSETS_DIR = Path(__file__).resolve().parent.parent / "sim" / "assets"


class ArmSpec(BaseModel):
    """One arm: its joints, end-effector link and gripper."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    joints: list[str] = Field(description="Arm joint names, base to wrist, as in the URDF.")
    ee_link: str = Field(description="Link whose pose is the end-effector (tool centre point) pose.")
    gripper_joints: list[str] = Field(description="Finger joints driven together by one gripper command.")
    gripper_open: float = Field(description="Finger joint position when fully open (URDF units).")
    gripper_closed: float = Field(description="Finger joint position when fully closed (URDF units).")
    home_qpos: list[float] = Field(description="Arm joint positions of the home (HM) pose, radians.")

    @model_validator(mode="after")
    def _check(self) -> "ArmSpec":
        if len(self.home_qpos) != len(self.joints):
            raise ValueError(f"home_qpos has {len(self.home_qpos)} values for {len(self.joints)} joints")
        if not self.gripper_joints:
            raise ValueError("gripper_joints: at least one finger joint is needed")
        if self.gripper_open == self.gripper_closed:
            raise ValueError("gripper_open and gripper_closed must differ")
        return self

    def gripper_to_joint(self, g: float) -> float:
        """Normalised gripper opening (0 closed, 1 open) → finger joint position."""
        return self.gripper_closed + g * (self.gripper_open - self.gripper_closed)

    def joint_to_gripper(self, q: float) -> float:
        """Finger joint position → normalised gripper opening (0 closed, 1 open)."""
        return (q - self.gripper_closed) / (self.gripper_open - self.gripper_closed)


class RobotSpec(BaseModel):
    """The robot: URDF, arms, and joint drive gains (position drives, as RoboTwin's)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    urdf: str = Field(
        default="dual_arm.urdf",
        description="URDF path (absolute, or relative to the working directory); a bare name not found there is "
                    "looked up in the package's sim/assets folder.",
    )
    left: ArmSpec = Field(default_factory=lambda: shipped_arm("left"),
                          description="The arm on the robot's left (world -x); default: the shipped robot's joint and link names.")
    right: ArmSpec = Field(default_factory=lambda: shipped_arm("right"),
                           description="The arm on the robot's right (world +x); default: the shipped robot's joint and link names.")
    arm_stiffness: float = Field(default=1000.0, gt=0, description="Arm joint drive stiffness.")
    arm_damping: float = Field(default=200.0, ge=0, description="Arm joint drive damping.")
    gripper_stiffness: float = Field(default=2000.0, gt=0, description="Finger joint drive stiffness.")
    gripper_damping: float = Field(default=100.0, ge=0, description="Finger joint drive damping.")
    gripper_force_limit: float = Field(default=40.0, gt=0, description="Finger drive force limit, N.")
    max_joint_speed: float = Field(default=1.2, gt=0, description="Expert joint-space speed limit, rad/s.")

    @cached_property
    def urdf_path(self) -> Path:
        """The resolved URDF file."""
        p = Path(self.urdf)
        return (p if p.is_absolute() or p.exists() else ASSETS_DIR / p).resolve()

    @property
    def dof(self) -> int:
        """Joints per arm."""
        return len(self.left.joints)

    @property
    def layout(self) -> StateLayout:
        """The state / action layout that this robot implies."""
        return StateLayout(self.dof)

    def arm(self, name: str) -> ArmSpec:
        """The spec of arm ``name`` (``left`` or ``right``)."""
        if name not in ARMS:
            raise ValueError(f"arm must be one of {ARMS}, got {name!r}")
        return self.left if name == "left" else self.right

    @model_validator(mode="after")
    def _check_against_urdf(self) -> "RobotSpec":
        if len(self.left.joints) != len(self.right.joints):
            raise ValueError("left and right arms must have the same number of joints")
        path = self.urdf_path
        if not path.is_file():
            raise ValueError(f"urdf: file not found: {path}")
        try:
            root = ET.parse(path).getroot()
        except ET.ParseError as e:
            raise ValueError(f"urdf: {path} is not valid XML ({e})") from None
        joints = {j.get("name"): j for j in root.iter("joint")}
        links = {link.get("name") for link in root.iter("link")}
        named = self.left.joints + self.left.gripper_joints + self.right.joints + self.right.gripper_joints
        if len(set(named)) != len(named):
            raise ValueError("joints: every arm and gripper joint must be named once, across both arms")
        for side in ARMS:
            arm = self.arm(side)
            for j in arm.joints + arm.gripper_joints:
                if j not in joints:
                    raise ValueError(f"{side}: joint {j!r} is not in {path.name}")
                if joints[j].get("type") == "fixed":
                    raise ValueError(f"{side}: joint {j!r} is fixed, an actuated joint is needed")
            if arm.ee_link not in links:
                raise ValueError(f"{side}.ee_link: link {arm.ee_link!r} is not in {path.name}")
            for j, q in zip(arm.joints, arm.home_qpos):
                _check_limit(joints[j], q, f"{side}.home_qpos")
            for j in arm.gripper_joints:
                for q, name in ((arm.gripper_open, "gripper_open"), (arm.gripper_closed, "gripper_closed")):
                    _check_limit(joints[j], q, f"{side}.{name}")
        return self


def _check_limit(joint: ET.Element, q: float, field: str) -> None:
    """Raise when ``q`` lies outside the URDF ``<limit>`` of ``joint`` (continuous joints have none)."""
    lim = joint.find("limit")
    if joint.get("type") == "continuous" or lim is None or lim.get("lower") is None:
        return
    lo, hi = float(lim.get("lower")), float(lim.get("upper"))
    if not lo - 1e-9 <= q <= hi + 1e-9:
        raise ValueError(f"{field}: {q} is outside joint {joint.get('name')!r} limits [{lo}, {hi}]")


def shipped_arm(side: str) -> ArmSpec:
    """One arm of the robot shipped with the package (``side``: left or right): six revolute
    joints ``<side>_joint1..6``, end-effector link ``<side>_ee``, two prismatic fingers."""
    return ArmSpec(
        joints=[f"{side}_joint{i}" for i in range(1, 7)],
        ee_link=f"{side}_ee",
        gripper_joints=[f"{side}_finger_left", f"{side}_finger_right"],
        gripper_open=0.045,
        gripper_closed=0.0,
        home_qpos=[0.0, 0.0, 1.7, 0.0, 1.44, 0.0],
    )


def default_robot() -> RobotSpec:
    """The robot shipped with the package: two 6-DoF arms with parallel-jaw grippers."""
    return RobotSpec()
