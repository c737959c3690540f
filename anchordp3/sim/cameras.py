"""The camera rig: world-mounted and wrist-mounted pinhole RGB-D cameras.

Conventions of every capture (one ``ViewCapture`` per camera):
- ``rgb (H, W, 3) uint8``; ``depth (H, W) float32`` metres along the optical axis, 0 = no hit;
- ``segmentation (H, W) int32``: SAPIEN per-entity id of each pixel (0 = background);
- ``K (3, 3)`` OpenCV intrinsics: integer pixel coordinates at pixel centres, so the principal
  point is ``((W - 1) / 2, (H - 1) / 2)`` (SAPIEN's own matrix puts it at ``(W / 2, H / 2)``, the
  convention with pixel centres at ``i + 0.5``); ``cam2world (4, 4)`` OpenCV camera frame (x right,
  y down, z forward) to world, metres.

Three shader packs give the same images (``CameraRigConfig.shader``): SAPIEN's ``default``
(deferred shading, seven G-buffers) reads colour, camera-frame position and segmentation; SAPIEN's
``minimal`` (a forward pass and a composite pass) reads colour, the depth buffer (linearised here)
and segmentation; the project's own ``lambert`` (``sim/shaders/lambert``: one forward pass,
Lambertian surfaces under the scene's ambient, directional and point lights, no image-based light,
specular or shadows, none of which the scenes use to any visible degree) writes one packed buffer
per camera (colour bytes, float depth, segmentation ids), read back in one copy. Segmentation is identical across the three, depth equal to
``default``'s (``minimal``: within 0.1 mm), colours within one level of 255; on lavapipe ``lambert``
takes less than half of ``minimal``'s CPU per frame and ``minimal`` three quarters of ``default``'s.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sapien
from sapien.render import RenderCameraComponent

from anchordp3.schemas.camera import CameraRigConfig, CameraSpec

# OpenGL camera frame (x right, y up, z backward) → OpenCV camera frame (x right, y down, z forward)
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
# The project's own shader packs (a pack is a folder of GLSL sources SAPIEN compiles on first use).
_OWN_PACKS = {"lambert": Path(__file__).resolve().parent / "shaders" / "lambert"}


def shader_dir(shader: str) -> str:
    """What ``sapien.render.set_camera_shader_dir`` takes for a ``CameraRigConfig.shader`` name:
    SAPIEN's packs by name, the project's by path."""
    return str(_OWN_PACKS[shader]) if shader in _OWN_PACKS else shader


@dataclass
class ViewCapture:
    """One camera's images and calibration at one instant (shapes in the module docstring)."""

    name: str
    rgb: np.ndarray
    depth: np.ndarray
    segmentation: np.ndarray
    K: np.ndarray
    cam2world: np.ndarray


def opencv_intrinsics(sapien_K: np.ndarray) -> np.ndarray:
    """OpenCV ``K (3, 3)`` from SAPIEN's intrinsic matrix: the principal point moves half a pixel
    up and left (SAPIEN's pixel ``i`` spans ``[i, i + 1)``; OpenCV's pixel ``i`` is centred on ``i``)."""
    K = np.array(sapien_K, dtype=np.float64)
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    return K


def linear_depth(buffer: np.ndarray, projection: np.ndarray) -> np.ndarray:
    """Depth along the optical axis, ``(H, W) float32`` metres, 0 where nothing was hit, from a
    Vulkan depth buffer ``(H, W)`` in [0, 1] (1 = cleared) and the camera's OpenGL-style
    ``projection (4, 4)``: the buffer holds ``d = -P22 + P23 / z`` for depth ``z``."""
    d = np.asarray(buffer, dtype=np.float64)
    p22, p23 = float(projection[2, 2]), float(projection[2, 3])
    hit = d < 1.0
    z = np.zeros(d.shape, np.float64)
    z[hit] = p23 / (d[hit] + p22)
    return z.astype(np.float32)


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
        sapien.render.set_camera_shader_dir(shader_dir(cfg.shader))  # read when a camera is created
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
        read = _READERS[self.cfg.shader]
        out = []
        for spec, cam in self.cameras:
            cam.take_picture()
            rgb, depth, seg = read(cam, segmentation)
            cam2world = np.asarray(cam.get_model_matrix(), np.float64) @ _GL_TO_CV
            out.append(ViewCapture(spec.name, rgb, depth, seg, opencv_intrinsics(cam.get_intrinsic_matrix()), cam2world))
        return out


def _colour(cam: RenderCameraComponent) -> np.ndarray:
    """The camera's ``(H, W, 3) uint8`` colour image."""
    return np.clip(cam.get_picture("Color")[..., :3] * 255 + 0.5, 0, 255).astype(np.uint8)


def _read_default(cam: RenderCameraComponent, segmentation: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour, depth and segmentation of the ``default`` shader pack's buffers."""
    pos = cam.get_picture("Position")  # OpenGL camera frame; [..., 3] < 1 where geometry was hit
    depth = np.where(pos[..., 3] < 1, -pos[..., 2], 0.0).astype(np.float32)
    seg = cam.get_picture("Segmentation")[..., 1].astype(np.int32) if segmentation else np.zeros(depth.shape, np.int32)
    return _colour(cam), depth, seg


def _read_lambert(cam: RenderCameraComponent, segmentation: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour, depth and segmentation of the ``lambert`` pack: one buffer, ``(H, W, 4) uint32`` per
    pixel the colour's four bytes, the depth's float bits (0 where nothing was hit) and the entity
    id, read back in one copy and split without arithmetic."""
    packed = cam.get_picture("ColorDepthSegmentation")
    h, w = packed.shape[:2]
    rgb = np.ascontiguousarray(packed[..., 0]).view(np.uint8).reshape(h, w, 4)[..., :3]
    depth = np.ascontiguousarray(packed[..., 1]).view(np.float32)
    seg = packed[..., 2].astype(np.int32) if segmentation else np.zeros((h, w), np.int32)
    return rgb, depth, seg


def _read_minimal(cam: RenderCameraComponent, segmentation: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour, depth and segmentation of the ``minimal`` shader pack's buffers (its position
    buffer holds whole millimetres, so depth comes from the depth buffer)."""
    depth = linear_depth(cam.get_picture("GbufferDepth"), np.asarray(cam.get_projection_matrix(), np.float64))
    seg = cam.get_picture("PositionSegmentation")[..., 3].astype(np.int32) if segmentation else np.zeros(depth.shape, np.int32)
    return _colour(cam), depth, seg


_READERS = {"default": _read_default, "minimal": _read_minimal, "lambert": _read_lambert}
