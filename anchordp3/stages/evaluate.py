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
classifier picked another task and the episode failed), and for an episode that ran out of steps
or decisions, ``not_released`` when the task's only unmet condition (``Task.evaluate``) is its
release (everything is in place, a gripper still holds on), else what the trace of its decisions
shows (``diagnose``): ``stalled`` (its last decisions no longer moved the robot), ``grasp_missed`` (a gripper closed but nothing came up),
``object_dropped`` (an object came up, then fell while no gripper opened),
``placed_wrong`` (an object was carried and, within ``RELEASE_DECISIONS`` of the last decision
that saw it up, a gripper closed then opened, whatever the other arm's does, but the task is not
done), else
``step_limit`` / ``max_decisions``. Every failed episode also records which of the task's named
conditions were unmet at its end (``EvalRecord.unmet``).
"""

from __future__ import annotations

import io
import time
import zlib
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from anchordp3.models.encoders import append_critical_probability
from anchordp3.models.instructions import episode_instruction
from anchordp3.schemas.evaluation import DECISION_SAMPLES, SKIP_REACHED
from anchordp3.schemas.run import RunConfig
from anchordp3.schemas.stages import AnchorsConfig
from anchordp3.schemas.state import ARMS, StateLayout
from anchordp3.schemas.tasks import TASK_NAMES, task_id
from anchordp3.sim.closed_loop import EvalEpisode, Observation, gripper_command
from anchordp3.sim.tasks.base import LayoutFailure
from anchordp3.stages.features import frame_features
from anchordp3.stages.train_classifier import load_classifier
from anchordp3.stages.train_policy import load_policy
from anchordp3.stages.train_segmenter import load_segmenter

FAILURE_MODES = ("layout_failure", "unstable", "no_points", "wrong_task", "not_released", "stalled", "grasp_missed",
                 "object_dropped", "placed_wrong", "step_limit", "max_decisions")
LIFTED = 0.03  # an object this far above where it settled has been picked up, metres
STALL_DECISIONS = 3  # this many decisions in a row without motion make a stall
RELEASE_DECISIONS = 2  # a gripper opening within this many decisions of the last that saw an object up released it
STALL_MOTION = 0.005  # joint motion (rad) and gripper change below which a decision did nothing


@dataclass(frozen=True)
class DecisionTrace:
    """What one decision did: the largest arm-joint motion it caused (rad), the gripper commands
    after it ``(2,)``, and how far the highest task object was lifted after it (metres)."""

    motion: float
    grippers: tuple[float, float]
    lift: float


def diagnose(trace: list[DecisionTrace], ran_out: str) -> str:
    """Why an episode that ran out of steps or decisions (``ran_out``) failed, from its decisions:
    see the module docstring."""
    last = trace[-STALL_DECISIONS:]
    if len(last) == STALL_DECISIONS and all(d.motion < STALL_MOTION for d in last) and \
            max(abs(a - b) for d, e in zip(last, last[1:]) for a, b in zip(d.grippers, e.grippers)) < STALL_MOTION:
        return "stalled"
    lifted = [d.lift > LIFTED for d in trace]
    if not any(lifted):
        return "grasp_missed" if any(min(d.grippers) < 0.5 for d in trace) else ran_out
    if lifted[-1]:
        return ran_out
    k = max(i for i, v in enumerate(lifted) if v)  # the last decision with an object up
    after = trace[k + 1:k + 1 + RELEASE_DECISIONS]  # a place lowers the object (one anchor), then opens
    released = any(a < 0.5 < b for d in after for a, b in zip(trace[k].grippers, d.grippers))
    return "placed_wrong" if released else "object_dropped"


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
    unmet: str = ""  # the task's conditions unmet at the end, comma-separated ("" on success)

    def to_dict(self) -> dict:
        return asdict(self)


class EvalModels:
    """The three trained models of a models folder (``<run>/models``, or shipped ones), loaded once
    per process (EMA policy weights); ``ddim_steps`` overrides the policy's DDIM steps per decision;
    ``samples`` anchor sequences are drawn per decision and their medoid carried out (1: one)."""

    def __init__(self, models_dir: Path, device: str | torch.device = "cpu", ddim_steps: int | None = None,
                 samples: int = DECISION_SAMPLES):
        d = Path(models_dir)
        for name in ("segmenter", "classifier", "policy"):
            if not (d / name / "model.pt").is_file():
                raise FileNotFoundError(f"{d / name / 'model.pt'}: no trained {name}; run `anchordp3 train all` first")
        self.device = torch.device(device)
        self.segmenter = load_segmenter(d / "segmenter" / "model.pt", self.device)
        self.classifier = load_classifier(d / "classifier" / "model.pt", self.device)
        self.policy = load_policy(d / "policy" / "model.pt", self.device, ema=True)
        objects = self.policy.config.objects
        if objects is not None and objects.source == "roles" and self.segmenter.config.roles < objects.tokens:
            raise ValueError(f"{d / 'segmenter'}: {self.segmenter.config.roles} roles, but the policy's tokens are "
                             f"roles 1..{objects.tokens} (policy.model.objects.source 'roles')")
        self.policy.unet.freeze()  # evaluation never changes the weights
        self.ddim_steps = ddim_steps  # None: the policy's own
        self.samples = samples

    def classify(self, text: str) -> int:
        """The model task id the instruction names."""
        return int(self.classifier.predict([text])[0])

    @torch.inference_mode()  # no autograd bookkeeping at all: 8 % off a CPU decision (49 -> 45 ms), same anchors
    def anchors(self, points: np.ndarray, state: np.ndarray, task: int, noise_seed: int) -> np.ndarray:
        """``points (N, 11)``, ``state (32,)`` → the predicted next anchors ``(H, 32)``."""
        gen = torch.Generator().manual_seed(noise_seed)
        obs = self.observation(points, state, task)
        return self.policy.predict(obs, generator=gen, steps=self.ddim_steps, samples=self.samples)[0].cpu().numpy()

    def observation(self, points: np.ndarray, state: np.ndarray, task: int) -> dict[str, torch.Tensor]:
        """``points (N, 11)``, ``state (32,)``, model task id -> the policy's one-sample observation: the
        points with the segmenter's critical probability, each point's role (None without a role
        head), the state and the task."""
        pts = torch.from_numpy(np.asarray(points, dtype=np.float32))[None].to(self.device)
        prob, roles = self.segmenter.predict(pts)
        return {"points": append_critical_probability(pts, prob), "roles": roles,
                "state": torch.from_numpy(np.asarray(state, dtype=np.float32))[None].to(self.device),
                "task_id": torch.tensor([task], dtype=torch.long, device=self.device)}


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




ROT_REACHED = 0.1  # rot6 entries: an anchor's rotation within about 6 degrees of the arm's counts as reached


def first_unreached(pred: np.ndarray, state: np.ndarray, commands: np.ndarray, within: float) -> int:
    """The first slot of ``pred (H, D)`` the robot in ``state (D,)`` (data units), its grippers
    commanded ``commands (arms,)`` (0 closed, 1 open), is not already at: some arm's end effector
    further than ``within`` metres from it, its rotation more than ``ROT_REACHED`` off in any rot6
    entry, or its gripper to be commanded otherwise (``gripper_command``: a gripper closed on an
    object stays partly open, yet its close is done); 0 where it is at every slot (nothing left to
    do but stand)."""
    layout = StateLayout.of_length(state.shape[-1])
    for h, anchor in enumerate(pred):
        grippers = gripper_command(np.array([anchor[layout.gripper(arm)] for arm in ARMS]))
        if (grippers != np.asarray(commands)).any():
            return h
        for arm in ARMS:
            if (np.linalg.norm(anchor[layout.ee_xyz(arm)] - state[layout.ee_xyz(arm)]) > within
                    or np.abs(anchor[layout.ee_rot6(arm)] - state[layout.ee_rot6(arm)]).max() > ROT_REACHED):
                return h
    return 0


def act(ep: EvalEpisode, pred: np.ndarray, cfg: AnchorsConfig, through: str = "pose", skip_reached: float = SKIP_REACHED) -> int:
    """Carry out one decision's prediction ``pred (H, 32)``: the first anchor (with ``skip_reached``
    metres, the first the robot is not already at, ``first_unreached``) by a smooth motion to its
    end-effector poses (``through="pose"``, IK) or its joint angles (``"joints"``, the report),
    or, for a run of the dense plan (predicted commanded actions), a chunk of ``dense.execute``
    actions at the plan's spacing. Returns the control steps used."""
    if cfg.plan == "dense":
        return ep.follow(pred[:cfg.dense.execute], cfg.dense.action_stride)
    first = first_unreached(pred, ep.robot.state(), ep.gripper_commands(), skip_reached) if skip_reached else 0
    return ep.execute(pred[first], through)


STRIP_FRAMES = 8  # frames in an episode's strip picture, evenly spaced over its decisions


def write_strip(path: Path, frames: list[tuple[np.ndarray, str]], title: str) -> Path:
    """An episode's frame strip: up to ``STRIP_FRAMES`` of its ``(rgb (H, W, 3) uint8, label)``
    frames, evenly spaced and always with the last, side by side; written atomically as PNG. When
    frames are left out, the title says how many of how many are shown."""
    from anchordp3.stages.files import atomic_write_bytes
    from anchordp3.viz.mosaic import mosaic

    if len(frames) > STRIP_FRAMES:
        idx = np.unique(np.linspace(0, len(frames) - 1, STRIP_FRAMES).round().astype(int))
        title = f"{title} ({len(idx)} of {len(frames)} frames, evenly spaced)"
        frames = [frames[i] for i in idx]
    img = mosaic([f for f, _ in frames], [label for _, label in frames], cols=len(frames), title=title)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


Watcher = Callable[[EvalEpisode, int, np.ndarray, np.ndarray], None]


def evaluate_episode(task: str, seed: int, models: EvalModels, cfg: RunConfig,
                     max_decisions: int | None = None, strip: Path | None = None, through: str = "pose",
                     watch: Watcher | None = None, skip_reached: float = SKIP_REACHED) -> EvalRecord:
    """Run one closed-loop episode of ``task`` on ``seed`` with ``models``; see the module docstring.
    strip: when given, the head camera's view at each decision and at the end is drawn there.
    through, skip_reached: how anchors are carried out (``act``). watch: called at each decision, before the
    prediction is carried out, with ``(episode, decision, points (N, 11), prediction (H, 32))``
    (diagnostics, e.g. ``benchmarks/grasp_errors.py``; it must not change the episode)."""
    t0 = time.perf_counter()
    frames: list[tuple[np.ndarray, str]] = []
    text = episode_instruction(task, seed, split="val").text
    predicted = models.classify(text)
    pred_name = TASK_NAMES[predicted] if 0 <= predicted < len(TASK_NAMES) else str(predicted)

    trace: list[DecisionTrace] = []

    def record(success: bool, steps: int, limit: int, decisions: int, failure: str | None,
               conditions: dict[str, bool] | None = None) -> EvalRecord:
        unmet = [name for name, met in (conditions or {}).items() if not met]
        if not success and failure in ("step_limit", "max_decisions"):
            if predicted != task_id(task):
                failure = "wrong_task"
            elif unmet == ["released"]:
                failure = "not_released"
            else:
                failure = diagnose(trace, failure)
        if strip is not None and frames:
            frames.append((ep.observe().views[0].rgb, f"end t{ep.steps}"))
            write_strip(strip, frames, f"{task} seed {seed}: {'success' if success else failure} - {text}")
        return EvalRecord(task=task, seed=seed, instruction=text, predicted_task=pred_name, success=success,
                          steps=steps, step_limit=limit, decisions=decisions, failure=None if success else failure,
                          seconds=time.perf_counter() - t0, unmet=",".join(unmet))

    try:
        ep = EvalEpisode(task, seed, cfg.world())
    except LayoutFailure:
        return record(False, 0, 0, 0, "layout_failure")
    if not ep.stable:
        return record(False, 0, ep.step_limit, 0, "unstable")
    decisions = 0
    joints = [i for a in ARMS for i in range(ep.layout.dim)[ep.layout.qpos(a)]]
    while True:
        conditions = ep.conditions()
        if all(conditions.values()):
            return record(True, ep.steps, ep.step_limit, decisions, None, conditions)
        if ep.steps >= ep.step_limit:
            return record(False, ep.steps, ep.step_limit, decisions, "step_limit", conditions)
        if max_decisions is not None and decisions >= max_decisions:
            return record(False, ep.steps, ep.step_limit, decisions, "max_decisions", conditions)
        obs = ep.observe()
        if strip is not None:
            frames.append((obs.views[0].rgb, f"d{decisions} t{ep.steps}"))
        s = decision_seed(task, seed, decisions)
        try:
            points, _ = frame_features(frames_dict(obs), 0, cfg.features, s)
        except ValueError:
            return record(False, ep.steps, ep.step_limit, decisions, "no_points", conditions)
        pred = models.anchors(points, obs.state, predicted, s)
        if watch is not None:
            watch(ep, decisions, points, pred)
        act(ep, pred, cfg.anchors, through, skip_reached)
        moved = float(np.abs(ep.robot.state()[joints] - obs.state[joints]).max())
        trace.append(DecisionTrace(moved, tuple(float(g) for g in ep.gripper_commands()), ep.lift()))
        decisions += 1
