"""Training the three models of a run: ``<run>/models/<name>/`` with a manifest each.

Each model is a train stage of the graph (``products.GRAPH``: ``train-segmenter``,
``train-classifier``, ``train-policy``), run by the runner in the driver, in that order, once
the dataset (``<run>/dataset``) is complete; ``train_item`` is a stage's one item.
``train_models(run_dir, ["segmenter", "classifier", "policy"], config)`` runs them with
``config`` as the run config's ``training`` section. Each model folder holds ``model.pt``,
``metrics.csv``, ``tensorboard/``, ``loss.png``, ``training.yaml`` (the resolved config) and a
manifest (``records.sqlite``, stage ``train-<name>``) with one item, the model: final
validation metrics, steps, wall time, and the checkpoint's path and sha256.

Fingerprint of a model = code version + hash of what its weights depend on (seed, mixed
precision and the model's section of ``TrainingConfig``; not the device or the loop settings) +
upstream: the ``dataset.json`` checksum (segmenter, policy) and, for the policy, the segmenter
checkpoint it took its 12th channel from. A model whose fingerprint changed is refused (one-line
error, before any model trains) unless ``force``; one that is done with the same fingerprint is
skipped; an interrupted one resumes from its checkpoint. The classifier learns from the
instruction bank, not from the dataset, so a new dataset does not invalidate it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import yaml

import anchordp3
from anchordp3.dataset.files import file_sha256
from anchordp3.dataset.reader import ShardedDataset, open_dataset
from anchordp3.models.device import pick_device
from anchordp3.pipeline.codehash import code_hash
from anchordp3.pipeline.store import read_manifest
from anchordp3.pipeline.graph import BatchContext, BatchItem, StageOutput
from anchordp3.pipeline.work import stage_dir
from anchordp3.schemas.dataset import INFO_FILE
from anchordp3.schemas.manifest import Fingerprint, ItemRecord
from anchordp3.schemas.records import ModelInfo
from anchordp3.schemas.run import RunConfig, config_hash, load_run_config
from anchordp3.schemas.sections import overlay
from anchordp3.schemas.yaml_files import read_yaml_mapping, validate_mapping
from anchordp3.schemas.training import MODELS, TrainingConfig, training_preset
from anchordp3.stages.files import atomic_write_bytes
from anchordp3.stages.training_loop import MODEL_FILE, format_metrics, format_seconds

log = logging.getLogger(__name__)

MODELS_DIR = "models"
CONFIG_FILE = "config.yaml"
TRAINING_FILE = "training.yaml"



def model_dir(run_dir: Path, name: str) -> Path:
    """``<run>/models/<name>``."""
    return Path(run_dir) / MODELS_DIR / name


def stage_name(name: str) -> str:
    """The manifest's stage name of model ``name``: ``train-<name>``."""
    return f"train-{name}"


# ------------------------------------------------------------------------------------------ config
def load_training_config(path: Path | None = None, preset: str = "cpu", steps: int | None = None,
                         device: str | None = None) -> TrainingConfig:
    """The training config: preset ``cpu`` or ``report``, overlaid with the YAML file ``path`` (any
    subset of ``TrainingConfig``'s fields, nested), then ``steps`` (every model's
    ``optim.steps``) and ``device``. Errors name the file and the field."""
    data: dict[str, Any] = training_preset(preset).model_dump(mode="json")
    if path is not None:
        data = overlay(data, read_yaml_mapping(path, "training config"))
    if steps is not None:
        for name in MODELS:
            data[name]["optim"]["steps"] = steps
    if device is not None:
        data["device"] = device
    return validate_mapping(TrainingConfig, data, path)


def model_config_part(cfg: TrainingConfig, name: str) -> dict:
    """What model ``name``'s weights depend on: seed, mixed precision, its config section."""
    return {"seed": cfg.seed, "mixed_precision": cfg.mixed_precision, name: getattr(cfg, name).model_dump(mode="json")}


def fingerprint(cfg: TrainingConfig, name: str, upstream: dict[str, str]) -> Fingerprint:
    """Model ``name``'s fingerprint (see the module doc)."""
    return Fingerprint(code_version=anchordp3.__version__, code_hash=code_hash([f"anchordp3.stages.train_{name}"]),
                       config_hash=config_hash(model_config_part(cfg, name)), upstream=dict(upstream))


# ------------------------------------------------------------------------------------------ status
@dataclass
class ModelStatus:
    """A model folder's state: ``done`` (model.pt recorded), ``partial`` (a resumable checkpoint),
    or ``absent``; with the done record when there is one."""

    name: str
    state: str
    record: ItemRecord | None = None


def model_status(run_dir: Path, name: str) -> ModelStatus:
    """Whether model ``name`` of the run is trained (reads its manifest; trains nothing)."""
    d = model_dir(run_dir, name)
    m = read_manifest(d) if d.is_dir() else None
    rec = m.items.get(name) if m is not None else None
    if rec is not None and rec.status == "done":
        return ModelStatus(name, "done", rec)
    if (d / "checkpoints" / "last.pt").is_file():
        return ModelStatus(name, "partial", rec)
    return ModelStatus(name, "absent", rec)


def trained_model(run_dir: Path, name: str) -> tuple[Path, str] | None:
    """``(model.pt path, sha256)`` of a trained model of the run, or None."""
    st = model_status(run_dir, name)
    if st.state != "done" or st.record is None or st.record.output is None:
        return None
    return model_dir(run_dir, name) / st.record.output, str(st.record.checksum)


# ---------------------------------------------------------------------------------------- training
def train_item(run_dir: Path, cfg: RunConfig, item: BatchItem) -> StageOutput | None:
    """Train model ``item.id`` of the run with ``cfg.training``, resuming its checkpoint: a train
    stage's one item, run in the driver while the runner holds its manifest. Returns the model
    file, its sha256 and ``ModelInfo``, or None when ``item.stop_at`` stopped it (resumable)."""
    return _train(Path(run_dir), item.id, cfg.training, item.stop_at)


def _train(run_dir: Path, name: str, cfg: TrainingConfig, stop_at: int | None) -> StageOutput | None:
    device = pick_device(cfg.device)
    threads = torch.get_num_threads()
    if device.type == "cpu" and cfg.loop.cpu_threads:
        torch.set_num_threads(cfg.loop.cpu_threads)
    try:
        d = model_dir(run_dir, name)
        channel = _critical_channel(run_dir, cfg) if name == "policy" else None
        digest = _fingerprint_of(run_dir, name, cfg, channel).digest()
        atomic_write_bytes(d / TRAINING_FILE, yaml.safe_dump(model_config_part(cfg, name), sort_keys=False).encode())
        data = _open_run_dataset(run_dir) if name != "classifier" else None
        try:
            if name == "segmenter":
                from anchordp3.stages.train_segmenter import train_segmenter

                result = train_segmenter(data, cfg, d, device, digest, stop_at)
            elif name == "classifier":
                from anchordp3.stages.train_classifier import train_classifier

                result = train_classifier(cfg, d, device, digest, stop_at)
            else:
                from anchordp3.stages.train_policy import train_policy

                result = train_policy(data, cfg, d, device, channel, digest, stop_at)
        finally:
            if data is not None:
                data.close()
    finally:
        torch.set_num_threads(threads)
    if not result.finished:
        return None
    log.info(f"{name}: done in {format_seconds(result.seconds)}: {format_metrics(result.metrics)} -> {result.model_path}")
    return StageOutput(MODEL_FILE, result.checksum, ModelInfo(
        metrics=result.metrics, steps=result.step, train_seconds=round(result.seconds, 2), device=str(device),
        checkpoint=str(Path(MODELS_DIR) / name / MODEL_FILE), resumed_from=result.resumed_from,
        critical_channel=channel.source if channel is not None else None))


def model_fingerprint(ctx: BatchContext, cfg: RunConfig, name: str) -> Fingerprint:
    """Model ``name``'s train stage fingerprint (``Stage.fingerprint``), from the run's files."""
    return _fingerprint_of(ctx.run_dir, name, cfg.training)


def check_train_stages(ctx: BatchContext, cfg: RunConfig) -> None:
    """What training the models of this call's train stages would refuse only later, refused
    before anything runs (the train stages' one ``check``): a dataset of other tasks than the run
    config's, and ``_preflight``'s refusals."""
    names = [n for n in MODELS if stage_name(n) in ctx.stages]
    run_dir = Path(ctx.run_dir)
    if any(n != "classifier" for n in names) and (stage_dir(run_dir, "write") / INFO_FILE).is_file():
        run_cfg = load_run_config(run_dir / CONFIG_FILE)
        data = open_dataset(stage_dir(run_dir, "write"))
        try:
            missing = sorted(set(data.tasks) - set(run_cfg.tasks))
        finally:
            data.close()
        if missing:
            raise ValueError(f"{stage_dir(run_dir, 'write')}: dataset tasks {missing} are not in the run config's tasks")
    _preflight(run_dir, names, cfg.training, ctx)


def _open_run_dataset(run_dir: Path) -> ShardedDataset:
    d = stage_dir(run_dir, "write")
    if not (d / INFO_FILE).is_file():
        raise ValueError(f"{d}: no complete dataset (no {INFO_FILE}); finish the data stages with `anchordp3 run` first")
    return open_dataset(d)


def _preflight(run_dir: Path, names: Sequence[str], cfg: TrainingConfig, ctx: BatchContext) -> None:
    """Refuse at once what training ``names`` would refuse only after training the models before
    it: a model trained with another config, code or data (without ``force``), a policy on top of a
    segmenter this call retrains, and a policy whose ``label_channel: auto`` finds no segmenter
    (it would train on the simulator's masks, a policy the segmenter-fed closed loop never sees)."""
    retrained: set[str] = set()
    have_data = (stage_dir(run_dir, "write") / INFO_FILE).is_file()
    for name in (n for n in MODELS if n in names):
        if name == "policy" and cfg.policy.label_channel == "auto" and "segmenter" not in names \
                and trained_model(run_dir, "segmenter") is None:
            raise ValueError(f"policy.label_channel 'auto': {model_dir(run_dir, 'segmenter')} holds no trained segmenter; "
                             "train it first (`anchordp3 train segmenter`, or `train all`), or set label_channel: "
                             "ground_truth to train on the simulator's masks")
        if name != "classifier" and not have_data:
            continue  # the data comes in this call: checked when the stage starts
        d = model_dir(run_dir, name)
        stored = read_manifest(d) if d.is_dir() else None
        if name == "policy":
            if "segmenter" in retrained and stored is not None and stored.complete and not ctx.force:
                raise ValueError(f"{d}: trained on the segmenter this call trains anew; pass --force to retrain it too")
            if "segmenter" in retrained:
                continue  # its fingerprint depends on the segmenter to come
        fp = _fingerprint_of(run_dir, name, cfg)
        changes = stored.fingerprint.changes(fp) if stored is not None else []
        if ctx.refuses(changes):
            raise _stale(d, stored.fingerprint, fp)
        if (changes and not ctx.keeps(changes)) or stored is None or not stored.complete:
            retrained.add(name)


def _fingerprint_of(run_dir: Path, name: str, cfg: TrainingConfig, channel=None) -> Fingerprint:
    """Model ``name``'s fingerprint given the run's data (and, for the policy, its label channel)."""
    upstream: dict[str, str] = {}
    if name != "classifier":
        upstream["dataset"] = file_sha256(stage_dir(run_dir, "write") / INFO_FILE)
    if name == "policy":
        channel = channel or _critical_channel(run_dir, cfg)
        upstream["segmenter"] = channel.checksum or "ground_truth"
    return fingerprint(cfg, name, upstream)


def _critical_channel(run_dir: Path, cfg: TrainingConfig):
    from anchordp3.stages.train_policy import CriticalChannel

    source = cfg.policy.label_channel
    seg = trained_model(run_dir, "segmenter") if source != "ground_truth" else None
    if source == "segmenter" and seg is None:
        raise ValueError("policy.label_channel: 'segmenter' needs a trained segmenter; run `anchordp3 train segmenter` first "
                         "(or use 'auto' / 'ground_truth')")
    if seg is None:
        return CriticalChannel("ground_truth")
    return CriticalChannel("segmenter", seg[0], seg[1])


def _stale(d: Path, old: Fingerprint, new: Fingerprint) -> ValueError:
    """The refusal of a model folder ``d`` trained under fingerprint ``old`` where ``new`` is wanted."""
    keep = ", --keep-outputs to keep it" if old.changes(new) == ["code"] else ""
    return ValueError(f"{d}: trained with a different {_what_changed(old, new)}; pass --force to retrain it{keep}, "
                      "or the settings it was trained with to keep it")


def _what_changed(old: Fingerprint, new: Fingerprint) -> str:
    words = {"code": "code", "config": "training config"}
    return " and ".join(words.get(c, c.removeprefix("upstream ")) for c in old.changes(new)) or "fingerprint"
