"""``anchordp3 demo``: the whole system on the embedded tiny default, in minutes on two CPU cores.

Today: the data stages through ``run`` (rollout → anchors → render → features → write) on the
embedded ``configs/demo.yaml``, then a picture of one rendered frame. Training and evaluation
join as they land.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from anchordp3.pipeline.report import data_summary
from anchordp3.pipeline.runner import RunOptions, run_pipeline
from anchordp3.pipeline.show import show_frame
from anchordp3.schemas.run import RunConfig, load_run_config

DEMO_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "demo.yaml"


def demo_config(seeds: str | None = None) -> RunConfig:
    """The embedded demo config, optionally with other seeds."""
    cfg = load_run_config(DEMO_CONFIG)
    return cfg.model_copy(update={"seeds": seeds}) if seeds else cfg


def run_demo(run_dir: Path, cfg: RunConfig, say: Callable[[str], None] = print, address: str | None = None) -> Path:
    """Run the demo's data stages into ``run_dir`` (resuming if it exists), print what the dataset
    holds, and draw its first rendered frame; returns the picture's path."""
    run_dir = Path(run_dir)
    run_pipeline(cfg, run_dir, RunOptions(address=address), say=say)
    say(data_summary(run_dir))
    png = show_frame(run_dir, run_dir / "frame.png", frame=1)
    say(f"\nA rendered frame, its masks and its labelled cloud: {png}")
    say(f"Inspect the run: anchordp3 status {run_dir} | anchordp3 inspect {run_dir} render | anchordp3 show {run_dir} --frame 3")
    return png
