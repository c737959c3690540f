"""The camera rig: world-mounted and wrist-mounted pinhole RGB-D cameras.

Conventions of every capture (one ``ViewCapture`` per camera):
- ``rgb (H, W, 3) uint8``; ``depth (H, W) float32`` metres along the optical axis, 0 = no hit;
- ``segmentation (H, W) int32``: SAPIEN per-entity id of each pixel (0 = background);
- ``K (3, 3)`` OpenCV intrinsics; ``cam2world (4, 4)`` OpenCV camera frame (x right, y down,
  z forward) to world, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sapien

from anchordp3.schemas.camera import CameraRigConfig, CameraSpec

# OpenGL camera frame (x right, y up, z backward) → OpenCV camera frame (x right, y down, z forward)
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class ViewCapture:
    """One camera's images and calibration at one instant (shapes in the module docstring)."""

    name: str
    rgb: np.ndarray
    depth: np.ndarray
    segmentation: np.ndarray
    K: np.ndarray
    cam2world: np.ndarray


def look_pose(position, forward, up) -> sapien.Pose:
    """SAPIEN camera pose at ``position`` looking along ``forward`` with image-up near ``up``."""
    f = np.asarray(forward, dtype=np.float64)
    f = f / np.linalg.norm(f)
    left = np.cross(np.asarray(up, dtype=np.float64), f)
    if np.linalg.norm(left) < 1e-6:  # forward parallel to up: pick any perpendicular
        left = np.cross([1.0, 0.0, 0.0] if abs(f[0]) < 0.9 else [0.0, 1.0, 0.0], f)
    left = left / np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = f, left, np.cross(f, left), position
    return sapien.Pose(m.astype(np.float32))


def _rotate(v: np.ndarray, axis_angle: np.ndarray) -> np.ndarray:
    """Rodrigues rotation of vector ``v`` by ``axis_angle`` (3,) radians."""
    theta = np.linalg.norm(axis_angle)
    if theta < 1e-12:
        return v
    k = axis_angle / theta
    return v * np.cos(theta) + np.cross(k, v) * np.sin(theta) + k * np.dot(k, v) * (1 - np.cos(theta))


class CameraRig:
    """Creates the configured cameras; world cameras get per-episode jitter from ``rng``."""

    def __init__(self, scene: sapien.Scene, cfg: CameraRigConfig, mounts: dict[str, sapien.Entity],
                 rng: np.random.Generator, jitter_pos: float = 0.0, jitter_rot_deg: float = 0.0):
        self.cfg = cfg
        self.cameras: list[tuple[CameraSpec, sapien.render.RenderCameraComponent]] = []
        fovy = np.deg2rad(cfg.fovy_deg)
        for spec in cfg.views:
            pos, fwd = np.asarray(spec.position, float), np.asarray(spec.forward, float)
            if spec.mount == "world":
                pos = pos + rng.uniform(-jitter_pos, jitter_pos, 3)
                fwd = _rotate(fwd, np.deg2rad(rng.uniform(-jitter_rot_deg, jitter_rot_deg, 3)))
                cam = scene.add_camera(spec.name, cfg.width, cfg.height, fovy, cfg.near, cfg.far)
                cam.entity.set_pose(look_pose(pos, fwd, spec.up))
            else:
                cam = scene.add_mounted_camera(spec.name, mounts[spec.mount], look_pose(pos, fwd, spec.up),
                                               cfg.width, cfg.height, fovy, cfg.near, cfg.far)
            self.cameras.append((spec, cam))

    @property
    def names(self) -> list[str]:
        """View names in capture order."""
        return [s.name for s, _ in self.cameras]

    def capture(self, segmentation: bool = True) -> list[ViewCapture]:
        """Render every view (the caller has already called ``scene.update_render()``)."""
        out = []
        for spec, cam in self.cameras:
            cam.take_picture()
            rgb = np.clip(cam.get_picture("Color")[..., :3] * 255 + 0.5, 0, 255).astype(np.uint8)
            pos = cam.get_picture("Position")  # OpenGL camera frame; [..., 3] < 1 where geometry was hit
            depth = np.where(pos[..., 3] < 1, -pos[..., 2], 0.0).astype(np.float32)
            seg = cam.get_picture("Segmentation")[..., 1].astype(np.int32) if segmentation else np.zeros(depth.shape, np.int32)
            cam2world = np.asarray(cam.get_model_matrix(), np.float64) @ _GL_TO_CV
            out.append(ViewCapture(spec.name, rgb, depth, seg, np.asarray(cam.get_intrinsic_matrix(), np.float64), cam2world))
        return out
