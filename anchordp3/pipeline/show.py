"""``anchordp3 show``: find a frame (in a run, a rendered-frames file or a features file) and draw it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from anchordp3.schemas.stages import FRAME_KINDS, FeaturesConfig
from anchordp3.stages.features import frame_cloud
from anchordp3.viz.frame import frame_figure

MAX_PLOT_POINTS = 20_000


def find_frames_file(path: Path, episode: str | None = None) -> Path:
    """The file to show: ``path`` itself when it is a file, else in a run directory the rendered
    frames of ``episode`` (``task/seed``; default: the first rendered episode)."""
    path = Path(path)
    if path.is_file():
        return path
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: no such file or run directory")
    root = path / "render" / "frames"
    if episode:
        task, _, seed = episode.partition("/")
        if not task or not seed.isdigit():
            raise ValueError(f"--episode: expected TASK/SEED, e.g. place_mouse/3, got {episode!r}")
        f = root / task / f"{int(seed):06d}.npz"
        if not f.is_file():
            raise FileNotFoundError(f"{f}: episode {episode} has no rendered frames in this run")
        return f
    files = sorted(root.glob("*/*.npz"))
    if not files:
        raise FileNotFoundError(f"{path}: no rendered frames (expected {root}/<task>/<seed>.npz)")
    return files[0]


def show_frame(path: Path, out: Path, frame: int = 0, episode: str | None = None, cfg: FeaturesConfig = FeaturesConfig()) -> Path:
    """Draw frame ``frame`` of a run / frames file / features file into ``out`` (PNG)."""
    f = find_frames_file(path, episode)
    try:
        with np.load(f, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - any unreadable file is bad input
        raise ValueError(f"{f}: not a frames or features file ({type(e).__name__})") from None
    if "depth" in arrays:
        _check_index(f, frame, len(arrays["t"]))
        cloud = frame_cloud(arrays, frame, cfg)
        rng = np.random.default_rng(0)
        keep = np.sort(rng.choice(len(cloud.points), min(MAX_PLOT_POINTS, len(cloud.points)), replace=False))
        kind = FRAME_KINDS[int(arrays["kind"][frame])]
        title = f"{f.parent.name}/{f.stem} frame {frame}: step {int(arrays['t'][frame])} ({kind})"
        return frame_figure(out, cloud.points[keep], cloud.colors[keep], cloud.labels[keep], list(arrays["rgb"][frame]),
                            list(arrays["mask"][frame]), [str(v) for v in arrays["views"]], title)
    if "points" in arrays:
        _check_index(f, frame, len(arrays["t"]))
        p = arrays["points"][frame]
        kind = FRAME_KINDS[int(arrays["kind"][frame])]
        title = f"{f.parent.name}/{f.stem} frame {frame}: step {int(arrays['t'][frame])} ({kind}), {len(p)} sampled points"
        return frame_figure(out, p[:, :3], p[:, 3:6], arrays["labels"][frame], title=title)
    raise ValueError(f"{f}: not a frames or features file (arrays: {sorted(arrays)})")


def _check_index(f: Path, frame: int, n: int) -> None:
    if not 0 <= frame < n:
        raise ValueError(f"--frame: {f} has frames 0..{n - 1}, got {frame}")
