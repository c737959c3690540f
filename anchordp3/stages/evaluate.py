"""Evaluate stage: one closed-loop episode of the trained models in the simulator (no Ray).

Each decision: render the four cameras → fused, cropped, FPS-sampled 11-d point features → the
segmenter's critical probability as the 12th channel → the policy (EMA weights, with the point
encoder of the task the classifier read from a held-out-family instruction) predicts the next
8 anchors → the first anchor's joint and gripper targets are executed by a smooth joint-space
motion timed as the expert times its moves (a run trained on the dense baseline's plan predicts
the next 8 commanded actions instead, and its first ``dense.execute`` are followed at the plan's
action spacing). Repeat until success, the task's step limit, or ``max_decisions``. Carrying out
the expert's own labels this way succeeds (``stages/oracle.py``): the protocol's ceiling is checked.

Failure modes: ``None`` on success, else ``layout_failure`` / ``unstable`` (the scene could not be
built or settled), ``no_points`` (nothing inside the workspace box), ``wrong_task`` (the
classifier picked another task and the episode failed), ``step_limit``, ``max_decisions``.
"""

from __future__ import annotations

import io
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from anchordp3.models.encoders import append_critical_probability
from anchordp3.models.instructions import episode_instruction
from anchordp3.schemas.run import RunConfig
from anchordp3.schemas.stages import AnchorsConfig
from anchordp3.schemas.training import TASK_NAMES, task_id
from anchordp3.sim.closed_loop import EvalEpisode, Observation
from anchordp3.sim.tasks.base import LayoutFailure
from anchordp3.stages.features import frame_features
from anchordp3.stages.train_classifier import load_classifier
from anchordp3.stages.train_policy import load_policy
from anchordp3.stages.train_segmenter import load_segmenter

MODELS_DIR = "models"
FAILURE_MODES = ("layout_failure", "unstable", "no_points", "wrong_task", "step_limit", "max_decisions")


@dataclass
class EvalRecord:
    """The outcome of one evaluation episode."""

    task: str
    seed: int
    instruction: str
    predicted_task: str
    success: bool
    steps: int
    step_limit: int
    decisions: int
    failure: str | None
    seconds: float

    def to_dict(self) -> dict:
        return asdict(self)


class EvalModels:
    """The three trained models of a run, loaded once per process (EMA policy weights)."""

    def __init__(self, run_dir: Path, device: str | torch.device = "cpu"):
        d = Path(run_dir) / MODELS_DIR
        for name in ("segmenter", "classifier", "policy"):
            if not (d / name / "model.pt").is_file():
                raise FileNotFoundError(f"{d / name / 'model.pt'}: no trained {name}; run `anchordp3 train all` first")
        self.device = torch.device(device)
        self.segmenter = load_segmenter(d / "segmenter" / "model.pt", self.device)
        self.classifier = load_classifier(d / "classifier" / "model.pt", self.device)
        self.policy = load_policy(d / "policy" / "model.pt", self.device, ema=True)

    def classify(self, text: str) -> int:
        """The model task id the instruction names."""
        return int(self.classifier.predict([text])[0])

    @torch.no_grad()
    def anchors(self, points: np.ndarray, state: np.ndarray, task: int, noise_seed: int) -> np.ndarray:
        """``points (N, 11)``, ``state (32,)`` → the predicted next anchors ``(H, 32)``."""
        pts = torch.from_numpy(np.asarray(points, dtype=np.float32))[None].to(self.device)
        prob = self.segmenter.probabilities(pts)
        obs = {"points": append_critical_probability(pts, prob),
               "state": torch.from_numpy(np.asarray(state, dtype=np.float32))[None].to(self.device),
               "task_id": torch.tensor([task], dtype=torch.long, device=self.device)}
        gen = torch.Generator().manual_seed(noise_seed)
        return self.policy.predict(obs, generator=gen)[0].cpu().numpy()


def frames_dict(obs: Observation) -> dict[str, np.ndarray]:
    """One observation as a one-frame rendered-frames dict (masks zero: the segmenter decides)."""
    v = obs.views
    return {
        "rgb": np.stack([c.rgb for c in v])[None],
        "depth": np.stack([c.depth for c in v]).astype(np.float32)[None],
        "mask": np.zeros((1, len(v)) + v[0].depth.shape, dtype=np.uint8),
        "K": np.stack([c.K for c in v]).astype(np.float64)[None],
        "cam2world": np.stack([c.cam2world for c in v]).astype(np.float64)[None],
        "views": np.array([c.name for c in v]),
    }


def decision_seed(task: str, seed: int, decision: int) -> int:
    """FPS and diffusion-noise seed of one decision: derived from its identity, never random."""
    return zlib.crc32(f"eval/{task}/{seed}/{decision}".encode())


def act(ep: EvalEpisode, pred: np.ndarray, cfg: AnchorsConfig) -> int:
    """Carry out one decision's prediction ``pred (H, 32)``: the first anchor by a smooth motion,
    or, for a run of the dense plan (predicted commanded actions), a chunk of ``dense.execute``
    actions at the plan's spacing. Returns the control steps used."""
    if cfg.plan == "dense":
        return ep.follow(pred[:cfg.dense.execute], cfg.dense.action_stride)
    return ep.execute(pred[0])


STRIP_FRAMES = 8  # frames in an episode's strip picture, evenly spaced over its decisions


def write_strip(path: Path, frames: list[tuple[np.ndarray, str]], title: str) -> Path:
    """An episode's frame strip: up to ``STRIP_FRAMES`` of its ``(rgb (H, W, 3) uint8, label)``
    frames, evenly spaced and always with the last, side by side; written atomically as PNG."""
    from anchordp3.stages.files import atomic_write_bytes
    from anchordp3.viz.mosaic import mosaic

    if len(frames) > STRIP_FRAMES:
        idx = np.unique(np.linspace(0, len(frames) - 1, STRIP_FRAMES).round().astype(int))
        frames = [frames[i] for i in idx]
    img = mosaic([f for f, _ in frames], [label for _, label in frames], cols=len(frames), title=title)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


def evaluate_episode(run_dir: Path, task: str, seed: int, models: EvalModels, cfg: RunConfig,
                     max_decisions: int | None = None, strip: Path | None = None) -> EvalRecord:
    """Run one closed-loop episode of ``task`` on ``seed`` with ``models``; see the module docstring.
    strip: when given, the head camera's view at each decision and at the end is drawn there."""
    del run_dir  # the models are already loaded; kept for the stage's uniform signature
    t0 = time.perf_counter()
    frames: list[tuple[np.ndarray, str]] = []
    text = episode_instruction(task, seed, split="val").text
    predicted = models.classify(text)
    pred_name = TASK_NAMES[predicted] if 0 <= predicted < len(TASK_NAMES) else str(predicted)

    def record(success: bool, steps: int, limit: int, decisions: int, failure: str | None) -> EvalRecord:
        if not success and failure in ("step_limit", "max_decisions") and predicted != task_id(task):
            failure = "wrong_task"
        if strip is not None and frames:
            frames.append((ep.observe().views[0].rgb, f"end t{ep.steps}"))
            write_strip(strip, frames, f"{task} seed {seed}: {'success' if success else failure} - {text}")
        return EvalRecord(task=task, seed=seed, instruction=text, predicted_task=pred_name, success=success,
                          steps=steps, step_limit=limit, decisions=decisions, failure=None if success else failure,
                          seconds=time.perf_counter() - t0)

    try:
        ep = EvalEpisode(task, seed, cfg.world())
    except LayoutFailure:
        return record(False, 0, 0, 0, "layout_failure")
    if not ep.stable:
        return record(False, 0, ep.step_limit, 0, "unstable")
    decisions = 0
    while True:
        if ep.success():
            return record(True, ep.steps, ep.step_limit, decisions, None)
        if ep.steps >= ep.step_limit:
            return record(False, ep.steps, ep.step_limit, decisions, "step_limit")
        if max_decisions is not None and decisions >= max_decisions:
            return record(False, ep.steps, ep.step_limit, decisions, "max_decisions")
        obs = ep.observe()
        if strip is not None:
            frames.append((obs.views[0].rgb, f"d{decisions} t{ep.steps}"))
        s = decision_seed(task, seed, decisions)
        try:
            points, _ = frame_features(frames_dict(obs), 0, cfg.features, s)
        except ValueError:
            return record(False, ep.steps, ep.step_limit, decisions, "no_points")
        act(ep, models.anchors(points, obs.state, predicted, s), cfg.anchors)
        decisions += 1
