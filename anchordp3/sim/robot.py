"""The robot in a scene: drives, joint targets, 32-d state, and IK / FK via SAPIEN's pinocchio."""

from __future__ import annotations

import numpy as np
import sapien

from anchordp3.schemas.robot import RobotSpec
from anchordp3.schemas.state import ARMS
from anchordp3.sim.actors import matrix_pose, pose_matrix


class Robot:
    """A fixed-base articulation built from a ``RobotSpec``.

    Joint targets are commanded per arm as ``(dof,)`` joint positions plus a normalised gripper
    opening (0 closed, 1 open). Poses are world-frame ``(4, 4)`` matrices in metres.
    """

    def __init__(self, scene: sapien.Scene, spec: RobotSpec, render: bool):
        self.spec = spec
        self.layout = spec.layout
        loader = scene.create_urdf_loader()
        loader.fix_root_link = True
        builders = loader.parse(str(spec.urdf_path))[0]
        if len(builders) != 1:
            raise ValueError(f"urdf: {spec.urdf_path} must hold exactly one articulation, found {len(builders)}")
        finger_mat = scene.create_physical_material(1.5, 1.5, 0.0)
        for lb in builders[0].link_builders:
            if not render:
                lb.visual_records = []
            for rec in lb.collision_records:
                rec.material = finger_mat
        self.articulation: sapien.physx.PhysxArticulation = builders[0].build(fix_root_link=True)
        self.articulation.name = "robot"
        self.links = {link.name: link for link in self.articulation.links}
        for link in self.articulation.links:
            link.disable_gravity = True  # an ideal gravity-compensated arm, as position-controlled arms behave
        joints = self.articulation.active_joints
        self._joints = joints
        self._joint_index = {j.name: i for i, j in enumerate(joints)}
        self.arm_idx = {a: np.array([self._joint_index[n] for n in spec.arm(a).joints]) for a in ARMS}
        self.finger_idx = {a: np.array([self._joint_index[n] for n in spec.arm(a).gripper_joints]) for a in ARMS}
        self._link_index = {link.name: i for i, link in enumerate(self.articulation.links)}
        self.ee_link = {a: self.links[spec.arm(a).ee_link] for a in ARMS}
        for a in ARMS:
            for i in self.arm_idx[a]:
                joints[i].set_drive_properties(spec.arm_stiffness, spec.arm_damping, force_limit=1e6, mode="force")
            for i in self.finger_idx[a]:
                joints[i].set_drive_properties(spec.gripper_stiffness, spec.gripper_damping, force_limit=spec.gripper_force_limit, mode="force")
        self._disable_self_collision()
        self.pinocchio = self.articulation.create_pinocchio_model()
        self._target = np.zeros(self.articulation.dof)
        self.reset_home()

    # ----------------------------------------------------------------------------- commands
    def reset_home(self) -> None:
        """Teleport to the home pose with open grippers and command it."""
        q = np.zeros(self.articulation.dof)
        for a in ARMS:
            q[self.arm_idx[a]] = self.spec.arm(a).home_qpos
            q[self.finger_idx[a]] = self.spec.arm(a).gripper_to_joint(1.0)
        self.articulation.set_qpos(q)
        self.articulation.set_qvel(np.zeros_like(q))
        self._apply(q)

    def command(self, joint_action: np.ndarray) -> None:
        """Set drive targets from a joint-space action ``(2 * (dof + 1),)``: both arms' qpos and grippers."""
        q = self._target.copy()
        L = self.layout
        for a in ARMS:
            q[self.arm_idx[a]] = joint_action[L.qpos(a)]
            q[self.finger_idx[a]] = self.spec.arm(a).gripper_to_joint(float(joint_action[L.gripper(a)]))
        self._apply(q)

    def _apply(self, q: np.ndarray) -> None:
        self._target = q.astype(np.float64)
        for joint, x in zip(self._joints, self._target):
            joint.set_drive_target(float(x))

    def drive_targets(self) -> np.ndarray:
        """Every active joint's raw drive target (a copy), for ``restore_drive_targets``."""
        return self._target.copy()

    def restore_drive_targets(self, targets: np.ndarray) -> None:
        """Re-command raw drive targets saved by ``drive_targets`` (bit-exact)."""
        self._apply(np.asarray(targets, dtype=np.float64))

    def joint_target(self) -> np.ndarray:
        """The joint-space action currently commanded, ``(2 * (dof + 1),)``."""
        L = self.layout
        v = np.zeros(L.joint_dim)
        for a in ARMS:
            v[L.qpos(a)] = self._target[self.arm_idx[a]]
            v[L.gripper(a)] = self.spec.arm(a).joint_to_gripper(float(self._target[self.finger_idx[a]].mean()))
        return v

    # ----------------------------------------------------------------------------- state
    def qpos(self) -> np.ndarray:
        """All active joint positions, ``(n_active,)`` float64."""
        return np.asarray(self.articulation.get_qpos(), dtype=np.float64)

    def arm_qpos(self, arm: str) -> np.ndarray:
        """Joint positions of ``arm``, ``(dof,)`` radians."""
        return self.qpos()[self.arm_idx[arm]]

    def gripper(self, arm: str) -> float:
        """Measured normalised opening of ``arm``'s gripper (0 closed, 1 open)."""
        return self.spec.arm(arm).joint_to_gripper(float(self.qpos()[self.finger_idx[arm]].mean()))

    def ee_pose(self, arm: str) -> np.ndarray:
        """World pose of ``arm``'s end effector, ``(4, 4)``."""
        return pose_matrix(self.ee_link[arm].entity_pose)

    def state(self) -> np.ndarray:
        """The measured 32-d state (DESIGN.md's layout), float64."""
        return self.layout.pack(
            {a: self.arm_qpos(a) for a in ARMS},
            {a: self.gripper(a) for a in ARMS},
            {a: self.ee_pose(a) for a in ARMS},
        )

    def action_state(self, joint_action: np.ndarray) -> np.ndarray:
        """A joint-space action completed to the full 32-d layout with its FK end-effector poses."""
        L = self.layout
        ee = {a: self.fk(a, joint_action[L.qpos(a)]) for a in ARMS}
        return L.pack({a: joint_action[L.qpos(a)] for a in ARMS}, {a: float(joint_action[L.gripper(a)]) for a in ARMS}, ee)

    # ----------------------------------------------------------------------------- kinematics
    def fk(self, arm: str, arm_q: np.ndarray) -> np.ndarray:
        """World pose ``(4, 4)`` of ``arm``'s end effector at joint positions ``arm_q (dof,)``."""
        q = self._target.copy()
        q[self.arm_idx[arm]] = arm_q
        self.pinocchio.compute_forward_kinematics(q)
        local = self.pinocchio.get_link_pose(self._link_index[self.spec.arm(arm).ee_link])
        return pose_matrix(self.articulation.root_pose * local)

    def ik(self, arm: str, target: np.ndarray, seed_q: np.ndarray | None = None, tol: float = 2e-3) -> np.ndarray | None:
        """Joint positions ``(dof,)`` that put ``arm``'s end effector at world pose ``target (4, 4)``.

        Seeds from ``seed_q`` (default: the commanded joints); returns None when no solution within
        ``tol`` (metres / radians) exists inside the joint limits.
        """
        q0 = self._target.copy()
        if seed_q is not None:
            q0[self.arm_idx[arm]] = seed_q
        mask = np.zeros(self.articulation.dof, dtype=np.int32)
        mask[self.arm_idx[arm]] = 1
        local = self.articulation.root_pose.inv() * matrix_pose(target)
        link = self._link_index[self.spec.arm(arm).ee_link]
        q, ok, err = self.pinocchio.compute_inverse_kinematics(
            link, local, initial_qpos=q0, active_qmask=mask, eps=1e-5, max_iterations=300, dt=0.1, damp=1e-6
        )
        sol = np.asarray(q, dtype=np.float64)[self.arm_idx[arm]]
        if not ok and float(np.abs(err).max()) > tol:
            return None
        lim = self.articulation.get_qlimits()[self.arm_idx[arm]]
        if np.any(sol < lim[:, 0] - 1e-6) or np.any(sol > lim[:, 1] + 1e-6):
            return None
        return sol

    # ----------------------------------------------------------------------------- internals
    def _disable_self_collision(self) -> None:
        """Links of one arm never collide with each other or the base; the two arms still collide.

        An arm's links are the child of its first joint and everything below it.
        """
        members: dict[str, int] = {}
        for a, bit in (("left", 0b01), ("right", 0b10)):
            first = self.articulation.active_joints[self.arm_idx[a][0]].child_link
            members[first.name] = bit
        for link in self.articulation.links:  # parents come before children
            parent = link.get_parent()
            if link.name not in members and parent is not None and parent.name in members:
                members[link.name] = members[parent.name]
        for link in self.articulation.links:
            bits = members.get(link.name, 0b11)
            for shape in link.collision_shapes:
                g = shape.get_collision_groups()
                shape.set_collision_groups([g[0], g[1], bits, g[3]])
