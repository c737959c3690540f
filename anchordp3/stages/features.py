"""Features stage: rendered frames → fused, cropped, downsampled point clouds with 11-d features.

Per frame: back-project every view's depth with its intrinsics and extrinsics into the world
frame, fuse the views, crop to the workspace box and drop the table (points up to
``table_margin`` above its top, estimated from the cloud), then farthest-point-sample N points and compute
``(x, y, z, r, g, b, nx, ny, nz, c1, c2)`` (normals by PCA over K neighbours, oriented towards the
configured camera; curvature from the neighbours' normal cross products), with the per-point
critical label carried from the masks.

Output item: ``features/<task>/<seed:06d>.npz`` with F frames:
``points (F, N, 11) float32``, ``labels (F, N) uint8``, ``state (F, 32) float32``,
``anchors (F, H, 32) float32``, ``t (F,) int64``, ``kind (F,) uint8`` (0 expert, 1 DAgger).
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from anchordp3.geometry.features import point_features
from anchordp3.geometry.pointcloud import Cloud, backproject, fuse_views, table_top_height
from anchordp3.schemas.stages import FeaturesConfig
from anchordp3.stages.files import features_file, save_npz
from anchordp3.stages.render import load_frames


def frame_cloud(frames: dict[str, np.ndarray], i: int, cfg: FeaturesConfig) -> Cloud:
    """The fused, cropped cloud of frame ``i`` of a rendered-frames file (colours in [0, 1],
    labels: roles, 0 not critical): inside the workspace box and, with ``table_margin``, above the table top."""
    box = (np.asarray(cfg.workspace_lo), np.asarray(cfg.workspace_hi))
    views = [backproject(frames["depth"][i, v], frames["K"][i, v], frames["cam2world"][i, v], frames["rgb"][i, v], frames["mask"][i, v], box)
             for v in range(frames["depth"].shape[1])]
    cloud = fuse_views(views)  # already inside the workspace box
    if cfg.table_margin is None or len(cloud.points) == 0:
        return cloud
    keep = cloud.points[:, 2] > table_top_height(cloud.points) + cfg.table_margin
    return Cloud(cloud.points[keep], cloud.colors[keep], cloud.labels[keep])


def frame_seed(task: str, seed: int, t: int, kind: int) -> int:
    """The FPS start seed of one frame: derived from its identity, never random."""
    return zlib.crc32(f"{task}/{seed}/{t}/{kind}".encode())


def frame_features(frames: dict[str, np.ndarray], i: int, cfg: FeaturesConfig, fps_seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``points (N, 11) float32`` and ``labels (N,) uint8`` of frame ``i``."""
    cloud = frame_cloud(frames, i, cfg)
    if len(cloud.points) == 0:
        raise ValueError(f"frame {i}: no point inside the workspace box {cfg.workspace_lo}..{cfg.workspace_hi}")
    names = [str(v) for v in frames["views"]]
    if cfg.normal_view not in names:
        raise ValueError(f"normal_view: no view named {cfg.normal_view!r} (views: {names})")
    viewpoint = frames["cam2world"][i, names.index(cfg.normal_view)][:3, 3]
    idx, feats = point_features(cloud.points, cloud.colors, cfg.n_points, cfg.k, viewpoint, fps_seed, cfg.eps)
    return feats, cloud.labels[idx]


def run_features(task: str, seed: int, frames_path: Path, out_dir: Path, cfg: FeaturesConfig) -> str:
    """Compute and write one episode's features; returns the output's relative path."""
    frames = load_frames(frames_path)
    F = len(frames["t"])
    points = np.zeros((F, cfg.n_points, 11), np.float32)
    labels = np.zeros((F, cfg.n_points), np.uint8)
    for i in range(F):
        points[i], labels[i] = frame_features(frames, i, cfg, frame_seed(task, seed, int(frames["t"][i]), int(frames["kind"][i])))
    rel = features_file(task, seed)
    save_npz(Path(out_dir) / rel, {
        "points": points, "labels": labels, "state": frames["state"].astype(np.float32),
        "anchors": frames["anchors"].astype(np.float32), "t": frames["t"].astype(np.int64), "kind": frames["kind"].astype(np.uint8),
    })
    return rel


def load_features(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a features file (see the module docstring)."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
