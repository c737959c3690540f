"""A picture of one frame: the four camera images over the fused cloud coloured by RGB and by label."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

CRITICAL = np.array([0.95, 0.25, 0.1])  # label 1
OTHER = np.array([0.72, 0.72, 0.75])    # label 0


def _cloud_axes(ax, points: np.ndarray, colors: np.ndarray, title: str) -> None:
    ax.scatter(points[:, 0], points[:, 1], points[:, 2], c=np.clip(colors, 0, 1), s=1.5 if len(points) > 5000 else 5.0, linewidths=0, depthshade=False)
    ax.set_title(title, fontsize=9)
    ax.view_init(elev=40, azim=-90)  # from behind the robot, looking along +y
    lo, hi = points.min(axis=0), points.max(axis=0) + 1e-3
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(hi - lo), zoom=1.35)  # metres equal on every axis
    ax.set_axis_off()


def frame_figure(out: Path, points: np.ndarray, colors: np.ndarray, labels: np.ndarray, images: list[np.ndarray] | None = None,
                 masks: list[np.ndarray] | None = None, view_names: list[str] | None = None, title: str = "") -> Path:
    """Save a PNG: camera images (critical pixels tinted) on top when given, then the cloud
    coloured by RGB beside the same cloud coloured by label (critical points in orange-red).

    points: (M, 3) metres; colors: (M, 3) in [0, 1]; labels: (M,) roles (critical: not 0); images: V of (H, W, 3) uint8;
    masks: V of (H, W) roles."""
    n_img = len(images) if images else 0
    fig = plt.figure(figsize=(12, 9.5 if n_img else 5.5), dpi=100)
    grid = fig.add_gridspec(3 if n_img else 1, n_img or 1, height_ratios=[1, 1, 2.6] if n_img else [1])
    for v in range(n_img):
        ax = fig.add_subplot(grid[0, v])
        img = images[v].astype(np.float32) / 255.0
        ax.imshow(img)
        ax.set_title(view_names[v] if view_names else f"view {v}", fontsize=9)
        ax.set_axis_off()
        if masks is not None:
            ax = fig.add_subplot(grid[1, v])
            m = masks[v].astype(bool)[..., None]
            ax.imshow(np.where(m, 0.45 * img + 0.55 * CRITICAL, 0.35 * img))
            ax.set_title("critical mask", fontsize=8)
            ax.set_axis_off()
    labels = np.asarray(labels).astype(bool)
    bottom = grid[-1, :].subgridspec(1, 2)
    for j, (cols, name) in enumerate([(colors, "fused cloud, RGB"),
                                      (np.where(labels[:, None], CRITICAL, OTHER), f"labels: {labels.sum()} of {len(labels)} critical")]):
        ax = fig.add_subplot(bottom[0, j], projection="3d")
        _cloud_axes(ax, points, cols, name)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
