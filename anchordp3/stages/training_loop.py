"""The training loop the three models share: resumable checkpoints, metrics, progress, curves.

A model's training is a ``TrainingJob`` (batches, one optimizer step, evaluation, resumable state,
export); ``run_training(job, out_dir, ...)`` drives it and writes into ``out_dir``:

- ``checkpoints/last.pt``: everything to resume (weights, optimizer, schedule, EMA, RNG states,
  step); written every ``checkpoint_every`` steps, on Ctrl-C and at ``stop_at``; removed once the
  final model is written.
- ``model.pt``: everything to run the trained model (``job.export()``), written at the end.
- ``metrics.csv``: long format ``step, split, metric, value, elapsed_s`` (train rows every step,
  validation rows at every evaluation); on resume the rows after the checkpoint are dropped.
- ``tensorboard/``: the same scalars as TensorBoard events (``train/loss``, ``val/iou``, ...).
- ``loss.png``: training loss (raw and smoothed) and validation loss against the step, beside the
  validation metrics that settings are chosen by (IoU, accuracy, first-anchor error, ...), each
  evaluation's value written at its point.

Batches come from ``epoch_batches``: epoch ``e`` is a permutation drawn from ``(seed, e)`` alone,
so a run resumed at step ``k`` sees exactly the batches an uninterrupted run sees after step ``k``
and, with the RNG states restored, ends with the same weights (on the same device and threads).
Knows nothing of Ray or manifests.
"""

from __future__ import annotations

import contextlib
import csv
import io
import logging
import math
import signal
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import DataLoader

from anchordp3.dataset.files import file_sha256
from anchordp3.dataset.torch_data import SplitDataset, collate_samples, make_loader
from anchordp3.schemas.training import LoopConfig
from anchordp3.stages.files import atomic_write_bytes

log = logging.getLogger(__name__)

CHECKPOINT_DIR = "checkpoints"
LAST_CHECKPOINT = "last.pt"
MODEL_FILE = "model.pt"
METRICS_FILE = "metrics.csv"
TENSORBOARD_DIR = "tensorboard"
LOSS_PLOT = "loss.png"
METRICS_COLUMNS = ("step", "split", "metric", "value", "elapsed_s")



# ------------------------------------------------------------------------------------ checkpoints
def save_checkpoint(path: Path, payload: Mapping[str, Any]) -> str:
    """Write ``payload`` (tensors, numbers, strings, lists, dicts) with ``torch.save``, atomically
    (temporary name, fsync, rename). Returns the file's sha256."""
    buf = io.BytesIO()
    torch.save(dict(payload), buf)
    atomic_write_bytes(Path(path), buf.getvalue())
    return file_sha256(Path(path))


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by ``save_checkpoint`` (tensors only, no pickled code); a clear
    error names the file when it is missing or not a checkpoint."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such checkpoint")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch raises several types for truncated or foreign files
        raise ValueError(f"{path}: not a readable checkpoint ({type(e).__name__})") from None


def rng_state() -> dict[str, Any]:
    """The global torch RNG states (CPU and every CUDA device): dropout and init draw from them."""
    state = {"cpu": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any]) -> None:
    """Restore what ``rng_state`` returned (the CUDA part only where CUDA is present)."""
    torch.set_rng_state(state["cpu"].cpu())
    if "cuda" in state and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


# ----------------------------------------------------------------------------------------- batches
def batches_per_epoch(n: int, batch_size: int) -> int:
    """``ceil(n / batch_size)`` (the last batch of an epoch may be smaller); at least 1."""
    return max(1, -(-n // batch_size))


def epoch_batches(n: int, batch_size: int, seed: int, start_step: int = 0) -> Iterator[list[int]]:
    """Endless index batches over ``range(n)``: epoch after epoch, each a fresh permutation drawn
    from ``(seed, epoch)`` only, cut into ``batches_per_epoch`` batches. Starts at global batch
    ``start_step`` without drawing the skipped ones, so resuming reproduces the order exactly."""
    if n < 1:
        raise ValueError("training split is empty: nothing to train on")
    per_epoch = batches_per_epoch(n, batch_size)
    epoch, skip = divmod(start_step, per_epoch)
    while True:
        gen = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
        perm = torch.randperm(n, generator=gen)
        for b in range(skip, per_epoch):
            yield perm[b * batch_size:(b + 1) * batch_size].tolist()
        skip, epoch = 0, epoch + 1


class StepBatchSampler(torch.utils.data.Sampler):
    """``epoch_batches`` as a DataLoader ``batch_sampler`` (endless; break out by step count)."""

    def __init__(self, n: int, batch_size: int, seed: int, start_step: int = 0) -> None:
        self.n, self.batch_size, self.seed, self.start_step = n, batch_size, seed, start_step

    def __iter__(self) -> Iterator[list[int]]:
        return epoch_batches(self.n, self.batch_size, self.seed, self.start_step)


def train_batches(ds: SplitDataset, batch_size: int, seed: int, start_step: int, workers: int = 0,
                  pin_memory: bool = False) -> Iterator[dict[str, torch.Tensor]]:
    """Endless training batches of ``ds`` (dicts of stacked tensors, see ``collate_samples``) in the
    order of ``epoch_batches(len(ds), batch_size, seed, start_step)``, read by ``workers`` processes."""
    loader = DataLoader(ds, batch_sampler=StepBatchSampler(len(ds), batch_size, seed, start_step), num_workers=workers,
                        collate_fn=collate_samples, pin_memory=pin_memory)
    return iter(loader)


def eval_batches(ds: SplitDataset, batch_size: int) -> DataLoader:
    """The samples of ``ds`` in storage order, ``batch_size`` at a time (read in this process)."""
    return make_loader(ds, batch_size, 0, shuffle=False)


def to_device(batch: Mapping[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """Every tensor of ``batch`` on ``device`` (non-blocking from pinned memory)."""
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


# ------------------------------------------------------------------------------------ optimisation
def optimizer_step(loss: torch.Tensor, optimizer: torch.optim.Optimizer, schedule, scaler: torch.amp.GradScaler | None,
                   params: list[torch.nn.Parameter], grad_clip_norm: float | None) -> None:
    """Backward ``loss`` (scaled for fp16 autocast when ``scaler``), clip the global gradient norm,
    step the optimizer and the learning-rate schedule. Gradients are cleared to None first, so a
    parameter no sample reached keeps ``grad is None`` and AdamW leaves it untouched."""
    optimizer.zero_grad(set_to_none=True)
    if scaler is not None:
        scaler.scale(loss).backward()
        scaler.unscale_(optimizer)
    else:
        loss.backward()
    if grad_clip_norm is not None:
        torch.nn.utils.clip_grad_norm_([p for p in params if p.grad is not None], grad_clip_norm)
    if scaler is not None:
        scaler.step(optimizer)
        scaler.update()
    else:
        optimizer.step()
    schedule.step()


# ---------------------------------------------------------------------------------------- the job
class TrainingJob(ABC):
    """One model's training as the loop sees it. Subclasses set ``name``, ``total_steps`` and
    ``steps_per_epoch`` and implement the methods below."""

    name: str
    total_steps: int
    steps_per_epoch: int

    @abstractmethod
    def batches(self, start_step: int) -> Iterator[Any]:
        """Endless batches for global steps ``start_step, start_step + 1, ...``."""

    @abstractmethod
    def train_step(self, batch: Any) -> dict[str, float]:
        """One optimizer step on ``batch``; returns at least ``{"loss", "lr"}``."""

    @abstractmethod
    def evaluate(self) -> dict[str, float]:
        """Metrics on the validation data (at least ``loss`` when there is any); leaves the model
        in training mode and draws nothing from the global RNG."""

    def state_dict(self) -> dict[str, Any]:
        """Everything to resume except the global RNG: weights, optimizer, schedule and grad scaler
        (``self.model``, ``self.optimizer``, ``self.schedule``, ``self.scaler``); jobs with more
        state (EMA, own generators) extend it."""
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "schedule": self.schedule.state_dict(), "scaler": self.scaler.state_dict() if self.scaler else None}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore what ``state_dict`` returned."""
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.schedule.load_state_dict(state["schedule"])
        if self.scaler is not None and state.get("scaler"):
            self.scaler.load_state_dict(state["scaler"])

    @abstractmethod
    def export(self) -> dict[str, Any]:
        """Everything to run the trained model: weights (EMA too), normalizers, config, task list."""


@dataclass
class TrainResult:
    """What one ``run_training`` call did."""

    name: str
    finished: bool                  # reached total_steps (model.pt written)
    step: int                       # optimizer steps done so far
    total_steps: int
    resumed_from: int               # step the call started at (0: fresh)
    seconds: float                  # training wall time over every call, seconds
    metrics: dict[str, float] = field(default_factory=dict)  # final validation metrics (when finished)
    model_path: Path | None = None  # model.pt when finished
    checksum: str | None = None     # its sha256


# ---------------------------------------------------------------------------------------- metrics
class MetricsLog:
    """Appends scalars to ``metrics.csv`` and TensorBoard. Opened at ``start_step``: rows and events
    after it (left by an interrupted run) are dropped, so the logs match the resumed weights."""

    def __init__(self, out_dir: Path, start_step: int) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.path = Path(out_dir) / METRICS_FILE
        rows = read_metrics(self.path) if self.path.is_file() else []
        kept = [r for r in rows if int(r["step"]) <= start_step] if start_step else []
        text = io.StringIO()
        writer = csv.writer(text)
        writer.writerow(METRICS_COLUMNS)
        for r in kept:
            writer.writerow([r[c] for c in METRICS_COLUMNS])
        atomic_write_bytes(self.path, text.getvalue().encode())
        self._file = open(self.path, "a", newline="")
        self._csv = csv.writer(self._file)
        self._tb = SummaryWriter(str(Path(out_dir) / TENSORBOARD_DIR), purge_step=start_step + 1 if start_step else None)

    def log(self, step: int, split: str, metrics: Mapping[str, float], elapsed_s: float) -> None:
        """One row per metric: ``(step, split, name, value, elapsed_s)``; TensorBoard tag ``split/name``."""
        for name, value in metrics.items():
            self._csv.writerow([step, split, name, f"{float(value):.6g}", f"{elapsed_s:.2f}"])
            self._tb.add_scalar(f"{split}/{name}", float(value), step)

    def flush(self) -> None:
        self._file.flush()
        self._tb.flush()

    def close(self) -> None:
        self._file.close()
        self._tb.close()


def read_metrics(path: Path) -> list[dict[str, str]]:
    """Rows of a ``metrics.csv`` as dicts keyed by ``METRICS_COLUMNS``."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def plot_losses(metrics_csv: Path, png: Path, title: str) -> Path:
    """``loss.png``: on the left, training loss per step (faint) and its moving average, validation
    loss at each evaluation (log scale when the losses are positive); on the right, when the job
    reports them, the other validation metrics (all tasks together) at each evaluation, the value
    written at each point so that a single evaluation reads as a number, not a dot. Uses
    matplotlib's Agg canvas (no pyplot, no display, no global backend change)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = read_metrics(metrics_csv)
    series: dict[str, tuple[list[int], list[float]]] = {}
    scores: dict[str, tuple[list[int], list[float]]] = {}  # validation metrics but the loss, all tasks together
    for r in rows:
        if r["metric"] == "loss":
            target = series.setdefault(r["split"], ([], []))
        elif r["split"] == "val" and "/" not in r["metric"]:
            target = scores.setdefault(r["metric"], ([], []))
        else:
            continue
        target[0].append(int(r["step"]))
        target[1].append(float(r["value"]))
    fig = Figure(figsize=(11.0 if scores else 6.4, max(4.0, 1.4 * len(scores))), dpi=100)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(max(1, len(scores)), 2 if scores else 1, width_ratios=[3, 2] if scores else [1])
    ax = fig.add_subplot(grid[:, 0])
    if "train" in series:
        xs, ys = series["train"]
        ax.plot(xs, ys, color="tab:blue", alpha=0.25, linewidth=0.8, label="train (per step)")
        ax.plot(xs, _moving_average(ys, max(1, len(ys) // 25)), color="tab:blue", label="train (smoothed)")
    if "val" in series:
        xs, ys = series["val"]
        ax.plot(xs, ys, "o-", color="tab:orange", label="validation")
        ax.annotate(f"{ys[-1]:.3g}", (xs[-1], ys[-1]), textcoords="offset points", xytext=(4, 6), color="tab:orange", fontsize=8)
    values = [v for _, ys in series.values() for v in ys]
    if values and min(values) > 0:
        ax.set_yscale("log")
    ax.set_xlabel("optimizer step")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if series:
        ax.legend()
    for k, (name, (xs, ys)) in enumerate(scores.items()):  # one small panel per metric, each its own scale
        axk = fig.add_subplot(grid[k, 1], sharex=ax)
        axk.plot(xs, ys, "o-", color="tab:green")
        for x, y in zip(xs, ys):
            axk.annotate(f"{y:.3g}", (x, y), textcoords="offset points", xytext=(-4, 4), ha="right", fontsize=8)
        axk.set_ylabel(name, fontsize=8)
        axk.tick_params(labelsize=7)
        axk.grid(alpha=0.3)
        if k == 0:
            axk.set_title("validation metrics (all tasks)", fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write_bytes(Path(png), buf.getvalue())
    return Path(png)


def _moving_average(ys: list[float], window: int) -> list[float]:
    """Centred moving average (no lag), the window shrinking at both ends."""
    csum = [0.0]
    for y in ys:
        csum.append(csum[-1] + y)
    half = window // 2
    out = []
    for i in range(len(ys)):
        lo, hi = max(0, i - half), min(len(ys), i + half + 1)
        out.append((csum[hi] - csum[lo]) / (hi - lo))
    return out


# --------------------------------------------------------------------------------------- progress
class Progress:
    """Progress lines ``name: step k/N (p%) | loss L | r steps/s | ETA t`` at most every
    ``interval_s`` seconds (and whenever ``force``); the rate counts this call's steps only.
    ``unit`` names what is counted (``step``: an optimizer step; ``sample``, ...); a line
    without a loss leaves it out."""

    def __init__(self, name: str, total: int, start: int, interval_s: float, unit: str = "step") -> None:
        self.name, self.total, self.start, self.interval_s, self.unit = name, total, start, interval_s, unit
        self.t0 = self.last = time.perf_counter()

    def update(self, step: int, loss: float | None = None, force: bool = False, extra: str = "") -> None:
        now = time.perf_counter()
        if not force and now - self.last < self.interval_s:
            return
        self.last = now
        done = step - self.start
        rate = done / (now - self.t0) if now > self.t0 else 0.0
        eta = format_seconds((self.total - step) / rate) if rate > 0 else "?"
        pct = 100.0 * step / max(self.total, 1)
        parts = [f"{self.name}: {self.unit} {step}/{self.total} ({pct:.0f}%)"]
        parts += [f"loss {loss:.4g}"] if loss is not None else []
        parts += [f"{rate:.2f} {self.unit}s/s", f"ETA {eta}"] + ([extra] if extra else [])
        log.info(" | ".join(parts))


class _StopRequested(Exception):
    """Ctrl-C arrived; raised between two steps, where the state is consistent."""


@contextlib.contextmanager
def _deferred_interrupt() -> Iterator[Callable[[], bool]]:
    """Within the block, Ctrl-C (SIGINT) only sets a flag, read through the yielded callable, so the
    loop stops between two optimizer steps and checkpoints a consistent state; a second Ctrl-C
    interrupts at once. Outside the main thread, a no-op (the flag stays False)."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return
    hits = []

    def handler(signum, frame):
        hits.append(signum)
        if len(hits) > 1:
            raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield lambda: bool(hits)
    finally:
        signal.signal(signal.SIGINT, previous)


def format_seconds(s: float) -> str:
    """``75.2`` -> ``1m15s``; ``3725`` -> ``1h02m``; under a minute: ``42s``."""
    if not math.isfinite(s):
        return "?"
    s = max(0, int(round(s)))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{(s % 3600) // 60:02d}m"


def format_metrics(metrics: Mapping[str, float]) -> str:
    """``{"loss": 0.1234, "iou": 0.5}`` -> ``loss 0.1234, iou 0.5``."""
    return ", ".join(f"{k} {v:.4g}" for k, v in metrics.items())


# ------------------------------------------------------------------------------------------ driver
def run_training(job: TrainingJob, out_dir: Path, loop: LoopConfig, fingerprint: str,
                 stop_at: int | None = None) -> TrainResult:
    """Train ``job`` to ``job.total_steps`` in ``out_dir``, resuming from ``checkpoints/last.pt``
    when it exists (and was written under the same ``fingerprint``).

    stop_at: stop after this many steps with a resumable checkpoint (an interruption on purpose;
    the next call continues to ``total_steps``). Ctrl-C stops after the current step with a
    checkpoint, then raises ``KeyboardInterrupt``; a second Ctrl-C stops at once (the last
    periodic checkpoint stays).
    Returns a ``TrainResult``; when ``finished``, ``model.pt``, ``loss.png`` and the final
    validation metrics exist and the resume checkpoint is gone."""
    out_dir = Path(out_dir)
    ckpt_path = out_dir / CHECKPOINT_DIR / LAST_CHECKPOINT
    total = job.total_steps
    start, elapsed = 0, 0.0
    if ckpt_path.is_file():
        state = load_checkpoint(ckpt_path)
        if state.get("fingerprint") != fingerprint:
            raise ValueError(f"{ckpt_path}: written by a different config, code or dataset; retrain with --force")
        job.load_state_dict(state["job"])
        set_rng_state(state["rng"])
        start, elapsed = int(state["step"]), float(state["elapsed_s"])
        log.info(f"{job.name}: resuming at step {start}/{total} from {ckpt_path}")
    metrics_log = MetricsLog(out_dir, start)
    eval_every = loop.eval_every or job.steps_per_epoch
    ckpt_every = loop.checkpoint_every or job.steps_per_epoch
    progress = Progress(job.name, total, start, loop.log_interval_s)
    step, loss, t_mark = start, float("nan"), time.perf_counter()

    def clock() -> float:
        nonlocal elapsed, t_mark
        now = time.perf_counter()
        elapsed, t_mark = elapsed + now - t_mark, now
        return elapsed

    def checkpoint() -> None:
        save_checkpoint(ckpt_path, {"fingerprint": fingerprint, "name": job.name, "step": step, "total_steps": total,
                                    "elapsed_s": clock(), "job": job.state_dict(), "rng": rng_state()})
        metrics_log.flush()

    try:
        batches = job.batches(start)
        with _deferred_interrupt() as interrupted:
            while step < total and (stop_at is None or step < stop_at):
                if interrupted():
                    raise _StopRequested
                metrics = job.train_step(next(batches))
                step += 1
                loss = metrics["loss"]
                if not math.isfinite(loss):
                    raise RuntimeError(f"{job.name}: loss is {loss} at step {step}; lower the learning rate or check the data")
                metrics_log.log(step, "train", metrics, clock())
                progress.update(step, loss)
                if step % eval_every == 0 and step < total:
                    val = job.evaluate()
                    metrics_log.log(step, "val", val, clock())
                    if val:
                        progress.update(step, loss, force=True, extra="val " + format_metrics(val))
                if step % ckpt_every == 0 and step < total:
                    checkpoint()
    except _StopRequested:
        checkpoint()
        metrics_log.close()
        log.info(f"{job.name}: interrupted at step {step}/{total}; checkpoint saved, run again to resume")
        raise KeyboardInterrupt from None
    except BaseException:
        metrics_log.close()
        raise
    if step < total:
        checkpoint()
        metrics_log.close()
        log.info(f"{job.name}: stopped at step {step}/{total}; checkpoint saved")
        return TrainResult(job.name, False, step, total, start, clock())
    final = job.evaluate()
    seconds = clock()
    metrics_log.log(step, "val", final, seconds)
    metrics_log.close()
    progress.update(step, loss, force=True, extra="val " + format_metrics(final) if final else "")
    model_path = out_dir / MODEL_FILE
    checksum = save_checkpoint(model_path, {**job.export(), "step": step, "metrics": final, "fingerprint": fingerprint})
    plot_losses(out_dir / METRICS_FILE, out_dir / LOSS_PLOT, f"{job.name}: {step} steps")
    ckpt_path.unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        ckpt_path.parent.rmdir()  # only when empty
    return TrainResult(job.name, True, step, total, start, seconds, final, model_path, checksum)
