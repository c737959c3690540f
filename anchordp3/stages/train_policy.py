"""Train the anchor diffusion policy: one frame (points, state, task) -> the next H anchors.

Input points get a 12th channel, the critical-object probability: the trained segmenter's
prediction (computed once for every sample and cached in ``critical_prob-<checksum>.npy``, with its
role head each point's role as well, ``roles-<checksum>.npy``) or the simulator's label (which is
the role). The dataset's task ids map to model task ids (``model_task_ids``), so each task
trains its own point encoder. Normalizers (state, anchors, points) are fitted from the dataset's
min/max statistics and travel in the checkpoint. AdamW with warm-up and cosine decay; EMA of the
weights after every step; validation with the EMA weights on the validation split: the diffusion
``loss`` (fixed noise, comparable across evaluations) and ``anchor_mse``, the mean squared error of
DDIM-sampled anchors in normalized units ([-1, 1] per dimension).

``train_policy(dataset, config, out_dir, device, segmenter=...)`` trains (resuming when ``out_dir``
holds a checkpoint) and writes ``model.pt``; ``load_policy(path)`` gives back a ready module.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anchordp3.dataset.reader import ShardedDataset
from anchordp3.dataset.torch_data import SplitDataset, collate_samples
from anchordp3.models.device import needs_grad_scaler, seed_everything
from anchordp3.models.ema import ExponentialMovingAverage
from anchordp3.models.encoders import append_critical_probability
from anchordp3.models.optim import make_lr_schedule, make_optimizer
from anchordp3.models.policy import AnchorDiffusionPolicy
from anchordp3.schemas.stages import FRAME_KINDS
from anchordp3.schemas.state import ARMS, rot6_matrices
from anchordp3.schemas.tasks import TASK_NAMES
from anchordp3.schemas.training import PolicyConfig, TrainingConfig, model_task_ids
from anchordp3.stages.files import atomic_write_bytes
from anchordp3.stages.train_segmenter import load_segmenter, stats_limits
from anchordp3.stages.training_loop import (
    Progress,
    TrainingJob,
    TrainResult,
    batches_per_epoch,
    eval_batches,
    load_checkpoint,
    optimizer_step,
    run_training,
    to_device,
    train_batches,
)

log = logging.getLogger(__name__)

KIND = "policy"
POLICY_KEYS = ("points", "labels", "state", "anchors")
VAL_NOISE_SEED = 12345  # the validation loss draws its noise from this seed every time
FIT_SAMPLES = 16384  # training samples (evenly spread) the per-choice offsets and yaws are fitted on


@dataclass(frozen=True)
class CriticalChannel:
    """Where the 12th point channel comes from: ``source`` is ``segmenter`` (then ``path`` is its
    ``model.pt`` and ``checksum`` that file's sha256) or ``ground_truth`` (the simulator labels)."""

    source: str
    path: Path | None = None
    checksum: str | None = None


def critical_probabilities(data: ShardedDataset, segmenter_path: Path, device: torch.device,
                           batch_size: int = 32, interval_s: float = 60.0) -> tuple[np.ndarray, np.ndarray | None]:
    """The segmenter's critical probability of every point of every sample, ``(samples, N) float16``
    indexed by global sample index (both splits), and with its role head each point's role
    ``(samples, N) uint8`` (else None). A progress line every ``interval_s`` seconds and at the end."""
    model = load_segmenter(segmenter_path, device)
    ds = SplitDataset(data, None, keys=("points",))
    out = np.zeros((len(data), data.info.n_points), dtype=np.float16)
    roles = np.zeros((len(data), data.info.n_points), dtype=np.uint8) if model.config.roles else None
    progress, done = Progress("policy: the segmenter's pass", len(ds), 0, interval_s, unit="sample"), 0
    for batch in eval_batches(ds, batch_size):
        probs, role = model.predict(batch["points"].to(device))
        out[batch["index"].numpy()] = probs.cpu().numpy().astype(np.float16)
        if roles is not None:
            roles[batch["index"].numpy()] = role.cpu().numpy()
        done += len(batch["index"])
        progress.update(done, force=done == len(ds))
    log.info(f"policy: segmenter probabilities of {len(ds)} samples computed (mean {float(out.mean()):.3f})")
    return out, roles


def _save_array(path: Path, array: np.ndarray) -> None:
    """``array`` as ``path`` (.npy), written crash-safe."""
    buf = io.BytesIO()
    np.save(buf, array)
    atomic_write_bytes(path, buf.getvalue())


def rotation_error_deg(rot6: np.ndarray, true6: np.ndarray) -> np.ndarray:
    """The angle between rotations given as ``R[:3, :2]`` row-major ``(B, 6)`` each (a prediction
    made orthonormal as ``StateLayout.ee_matrix`` does, ``rot6_matrices``): ``(B,)`` degrees."""
    cos = (np.einsum("bij,bij->b", rot6_matrices(rot6), rot6_matrices(true6)) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def delta_limits(data: ShardedDataset, batch_size: int = 256) -> dict[str, list]:
    """``{"min", "max"}`` of ``anchors - state`` per horizon slot, ``(H, D)`` nested lists, over
    every sample of both splits (as the dataset's own statistics are)."""
    ds = SplitDataset(data, None, keys=("state", "anchors"))
    lo = hi = None
    for batch in eval_batches(ds, batch_size):
        d = (batch["anchors"] - batch["state"][:, None, :]).double()
        blo, bhi = d.min(dim=0).values, d.max(dim=0).values
        lo = blo if lo is None else torch.minimum(lo, blo)
        hi = bhi if hi is None else torch.maximum(hi, bhi)
    if lo is None:
        raise ValueError("dataset: no samples to fit the relative-target normalizer on")
    return {"min": lo.tolist(), "max": hi.tolist()}


class PolicyJob(TrainingJob):
    """The policy's training on one dataset (see ``TrainingJob``)."""

    name = KIND

    def __init__(self, data: ShardedDataset, config: TrainingConfig, device: torch.device,
                 channel: CriticalChannel, probabilities: np.ndarray | None = None, roles: np.ndarray | None = None) -> None:
        self.cfg, self.device, self.data, self.channel = config.policy, device, data, channel
        self.seed, self.loop = config.seed, config.loop
        if channel.source == "segmenter" and probabilities is None:
            raise ValueError("policy: the segmenter channel needs the precomputed probabilities")
        objects = self.cfg.model.objects
        if objects is not None and objects.source == "roles" and channel.source == "segmenter" and roles is None:
            raise ValueError(f"policy.model.objects.source: 'roles', but the segmenter {channel.path} has no role head; "
                             "train it with segmenter.model.roles set (or label_channel: ground_truth)")
        self.probabilities = None if probabilities is None else torch.from_numpy(probabilities)
        self.roles = None if roles is None else torch.from_numpy(roles)
        self.task_lut = torch.tensor(model_task_ids(data.tasks), dtype=torch.long)
        if int(self.task_lut.max()) >= self.cfg.model.num_tasks:
            raise ValueError(f"policy.model.num_tasks: {self.cfg.model.num_tasks} encoders, but the dataset's tasks "
                             f"{data.tasks} need ids up to {int(self.task_lut.max())}")
        self._delta_stats: dict[str, list] | None = None
        self._decisions: list[int] | None = None
        self.train_ds = SplitDataset(data, "train", keys=POLICY_KEYS)
        self.val_ds = SplitDataset(data, "validation", keys=POLICY_KEYS)
        optim = self.cfg.optim
        self.steps_per_epoch = batches_per_epoch(len(self.train_ds), optim.batch_size)
        self.total_steps = optim.total_steps(len(self.train_ds))
        self.generator = seed_everything(self.seed)
        self.model = AnchorDiffusionPolicy(self.cfg.model, mixed_precision=config.mixed_precision)
        self.model.set_normalizers(self.normalizer_stats())
        self.model.to(device)
        if objects is not None and objects.fits_choices:
            self.fit_choices()
        self.model.train()
        self.ema = ExponentialMovingAverage(self.model, self.cfg.ema)
        self.params = list(self.model.parameters())
        self.optimizer = make_optimizer(self.params, optim)
        self.schedule = make_lr_schedule(self.optimizer, optim, self.total_steps)
        self.scaler = torch.amp.GradScaler("cuda") if needs_grad_scaler(device, config.mixed_precision) else None

    def fit_choices(self) -> None:
        """Fit the policy's per-choice offsets and yaws (``AnchorDiffusionPolicy.fit_choices``) on up to
        ``FIT_SAMPLES`` training samples spread evenly over the split, and log each fitted yaw."""
        picks = np.unique(np.linspace(0, len(self.train_ds) - 1, min(len(self.train_ds), FIT_SAMPLES)).astype(np.int64))
        batch = self.cfg.optim.batch_size * 4
        batches = (self.observation(collate_samples(self.train_ds.__getitems__(picks[i:i + batch].tolist())))
                   for i in range(0, len(picks), batch))
        self.model.eval()
        rows = self.model.fit_choices(batches)
        names = {m: t for t, m in zip(self.data.tasks, self.task_lut.tolist())}
        log.info(f"policy: per-choice offsets fitted on {len(picks)} samples; yaw anchored for {len(rows)} (task, choice, arm)")
        for r in rows:
            log.info(f"  {names.get(r['task'], r['task'])} choice {r['choice']} {r['arm']}: {r['anchors']} anchors, "
                     f"{'heading' if r['kind'] == 'held' else 'yaw offset'} {r['offset_deg']:+.1f} deg, "
                     f"concentration {r['concentration']:.3f}")

    def normalizer_stats(self) -> dict[str, dict[str, list]]:
        """Min/max of state, anchors and the 11 point channels from the dataset statistics, and for
        relative targets of anchors minus state per horizon slot ``(H, D)`` over every sample."""
        out = {k: stats_limits(self.data.stats, k) for k in ("state", "anchors", "points")}
        if self.cfg.model.target == "relative":
            if self._delta_stats is None:
                self._delta_stats = delta_limits(self.data)
            out["delta"] = self._delta_stats
        return out

    def observation(self, batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """A loader batch -> the policy's batch on the device: ``points (B, N, 12)`` (features +
        critical probability), ``roles (B, N)`` (each point's role: the segmenter's, or the label),
        ``state (B, 32)``, ``task_id (B,)`` model ids, ``anchors (B, H, 32)``."""
        if self.probabilities is not None:
            prob = self.probabilities[batch["index"]].float()
            roles = self.roles[batch["index"]] if self.roles is not None else (prob > 0.5).to(torch.uint8)
        else:
            prob = (batch["labels"] > 0).float()  # any role is critical
            roles = batch["labels"]
        points = append_critical_probability(batch["points"], prob)
        out = {"points": points, "roles": roles, "state": batch["state"], "anchors": batch["anchors"],
               "task_id": self.task_lut[batch["task_id"]]}
        return to_device(out, self.device)

    def batches(self, start_step: int) -> Iterator[dict[str, torch.Tensor]]:
        return train_batches(self.train_ds, self.cfg.optim.batch_size, self.seed, start_step, self.loop.loader_workers,
                             pin_memory=self.device.type == "cuda")

    def train_step(self, batch: Mapping[str, torch.Tensor]) -> dict[str, float]:
        loss = self.model.compute_loss(self.observation(batch), generator=self.generator)
        optimizer_step(loss, self.optimizer, self.schedule, self.scaler, self.params, self.cfg.optim.grad_clip_norm)
        decay = self.ema.step(self.model)
        return {"loss": float(loss.detach()), "lr": self.schedule.get_last_lr()[0], "ema_decay": decay}

    @torch.no_grad()
    def evaluate(self) -> dict[str, float]:
        """With the EMA weights over the validation split: ``loss`` (diffusion MSE over every sample,
        noise drawn from a fixed seed) and ``anchor_mse`` (DDIM samples vs. true anchors, normalized
        units, over ``val_predict_samples`` samples spread evenly over the split, so every
        validation episode counts); ``{}`` when the split is empty."""
        if len(self.val_ds) == 0:
            return {}
        model = self.ema.averaged_model
        gen = torch.Generator().manual_seed(VAL_NOISE_SEED)
        total, n = 0.0, 0
        for batch in eval_batches(self.val_ds, self.cfg.optim.batch_size):
            obs = self.observation(batch)
            total += float(model.compute_loss(obs, generator=gen)) * len(obs["state"])
            n += len(obs["state"])
        out = {"loss": total / n}
        picks = self.predict_indices()
        if len(picks):
            err, norm, size = 0.0, model.anchor_normalizer, self.cfg.optim.batch_size
            for i in range(0, len(picks), size):
                obs = self.observation(collate_samples(self.val_ds.__getitems__(picks[i:i + size])))
                pred = model.predict(obs, generator=gen)
                err += float(((norm(pred) - norm(obs["anchors"])) ** 2).mean()) * len(pred)
            out["anchor_mse"] = err / len(picks)
        out.update(self.first_anchor_errors(model, gen))
        return out

    @torch.no_grad()
    def first_anchor_errors(self, model: AnchorDiffusionPolicy, gen: torch.Generator) -> dict[str, float]:
        """The error that decides a grasp: the first predicted anchor against the true one at the
        validation split's decision states (``rest`` frames: the robot at rest at an anchor, as in
        closed loop; expert frames when the plan has none), per task and over all of them:
        ``first_cm[/task]`` the gripper position error (mean over samples of the worse arm),
        centimetres; ``first_deg[/task]`` the gripper rotation error (the angle between the predicted
        and the true rotation, mean over samples of the worse arm), degrees; ``first_rad[/task]``
        the mean absolute arm-joint error, radians per joint; with
        anchored offsets, ``first_gate[/task]`` the share whose first gates choose the labelled
        anchor's object (``AnchorDiffusionPolicy.first_gate_hits``)."""
        picks = self.decision_indices()
        if not picks:
            return {}
        layout = self.model.layout
        xyz = [np.arange(layout.dim)[layout.ee_xyz(a)] for a in ARMS]
        joints = np.concatenate([np.arange(layout.dim)[layout.qpos(a)] for a in ARMS])
        cm, deg, rad, task, gate = [], [], [], [], []
        size = self.cfg.optim.batch_size
        for i in range(0, len(picks), size):
            obs = self.observation(collate_samples(self.val_ds.__getitems__(picks[i:i + size])))
            pred = model.predict(obs, generator=gen)[:, 0].cpu().numpy()
            true = obs["anchors"][:, 0].cpu().numpy()
            cm.append(100 * np.max([np.linalg.norm(pred[:, k] - true[:, k], axis=1) for k in xyz], axis=0))
            deg.append(np.max([rotation_error_deg(pred[:, layout.ee_rot6(a)], true[:, layout.ee_rot6(a)]) for a in ARMS], axis=0))
            rad.append(np.abs(pred[:, joints] - true[:, joints]).mean(axis=1))
            task.append(obs["task_id"].cpu().numpy())
            hits = model.first_gate_hits(obs)
            if hits is not None:
                gate.append(hits.cpu().numpy())
        cm_all, rad_all, task_all = np.concatenate(cm), np.concatenate(rad), np.concatenate(task)
        metrics = {"first_cm": cm_all, "first_deg": np.concatenate(deg), "first_rad": rad_all}
        if gate:
            metrics["first_gate"] = np.concatenate(gate).astype(np.float64)
        out = {name: float(values.mean()) for name, values in metrics.items()}
        for k in np.unique(task_all).tolist():
            sel = task_all == k
            out.update({f"{name}/{TASK_NAMES[k]}": float(values[sel].mean()) for name, values in metrics.items()})
        return out

    def decision_indices(self) -> list[int]:
        """Positions in the validation split of its decision states (see ``first_anchor_errors``),
        up to ``val_decision_samples``, evenly spaced; read once per job."""
        if self._decisions is None:
            self._decisions = self._find_decisions()
        return self._decisions

    def _find_decisions(self) -> list[int]:
        kinds = np.array([self.data.sample(int(i), ())["kind"] for i in self.val_ds.samples], dtype=np.int64)
        code = FRAME_KINDS.index("rest") if (kinds == FRAME_KINDS.index("rest")).any() else FRAME_KINDS.index("expert")
        pos = np.nonzero(kinds == code)[0]
        k = min(self.cfg.val_decision_samples, len(pos))
        return sorted({int(pos[int(round(x))]) for x in np.linspace(0, len(pos) - 1, k)}) if k else []

    def predict_indices(self) -> list[int]:
        """Positions in the validation split of the samples ``anchor_mse`` is measured on: up to
        ``val_predict_samples``, evenly spaced."""
        k = min(self.cfg.val_predict_samples, len(self.val_ds))
        return sorted({int(round(x)) for x in np.linspace(0, len(self.val_ds) - 1, k)}) if k else []

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "ema": self.ema.state_dict(), "generator": self.generator.get_state()}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        super().load_state_dict(state)
        self.ema.load_state_dict(state["ema"])
        self.generator.set_state(state["generator"])

    def export(self) -> dict[str, Any]:
        cpu = lambda sd: {k: v.detach().cpu() for k, v in sd.items()}  # noqa: E731
        return {
            "kind": KIND,
            "config": self.cfg.model.model_dump(mode="json"),
            "training": self.cfg.model_dump(mode="json"),
            "mixed_precision": self.model.mixed_precision,
            "state_dict": cpu(self.model.state_dict()),
            "ema_state_dict": cpu(self.ema.averaged_model.state_dict()),
            "normalizers": self.normalizer_stats(),
            "tasks": list(TASK_NAMES),
            "dataset_tasks": list(self.data.tasks),
            "critical_channel": {"source": self.channel.source, "segmenter_checksum": self.channel.checksum},
        }


def train_policy(data: ShardedDataset, config: TrainingConfig, out_dir: Path, device: torch.device,
                 channel: CriticalChannel = CriticalChannel("ground_truth"), fingerprint: str = "", stop_at: int | None = None) -> TrainResult:
    """Train (or resume) the policy on ``data`` into ``out_dir`` (see ``run_training``), the 12th
    point channel from ``channel``."""
    out_dir = Path(out_dir)
    probabilities = roles = None
    if channel.source == "segmenter":
        if channel.path is None or channel.checksum is None:
            raise ValueError("policy: the segmenter channel needs the segmenter's model.pt and its checksum")
        tag = channel.checksum[:12]
        prob_file, role_file = out_dir / f"critical_prob-{tag}.npy", out_dir / f"roles-{tag}.npy"
        if not prob_file.is_file():  # written last: where it is, the roles (with a role head) are too
            made, role = critical_probabilities(data, channel.path, device, interval_s=config.loop.log_interval_s)
            if role is not None:
                _save_array(role_file, role)
            _save_array(prob_file, made)
        probabilities = np.load(prob_file)
        roles = np.load(role_file) if role_file.is_file() else None
    job = PolicyJob(data, config, device, channel, probabilities, roles)
    log.info(f"policy: {len(job.train_ds)} train / {len(job.val_ds)} validation samples, tasks {data.tasks} -> encoders "
        f"{job.task_lut.tolist()}, critical channel from {channel.source}, {job.total_steps} steps of "
        f"{config.policy.optim.batch_size} on {device}")
    return run_training(job, out_dir, config.loop, fingerprint, stop_at)


def load_policy(path: Path, device: torch.device | str = "cpu", ema: bool = True) -> AnchorDiffusionPolicy:
    """The trained policy of a ``model.pt`` in eval mode on ``device``: the EMA weights (what
    evaluation uses) unless ``ema=False``; normalizers included."""
    ckpt = load_checkpoint(path)
    if ckpt.get("kind") != KIND:
        raise ValueError(f"{path}: not a policy checkpoint (kind {ckpt.get('kind')!r})")
    model = AnchorDiffusionPolicy(PolicyConfig.model_validate(ckpt["config"]), mixed_precision=bool(ckpt["mixed_precision"]))
    model.load_state_dict(ckpt["ema_state_dict" if ema else "state_dict"])
    return model.to(device).eval()
