"""Ship a run's trained models as a self-contained models folder, the form ``anchordp3 eval
--models DIR`` (and ``--models pretrained``, the package's own) loads.

The folder holds, per model, ``model.pt`` (the policy with its EMA weights only, the classifier
with only the tensors that differ from the encoder its package ships, large weights in float16),
``manifest.json`` (its manifest as JSON, every record inline) and ``training.yaml``; beside them
``run_config.yaml`` (the data config the models were trained on:
world, features and plan of the evaluation) and ``SHIPPED.md`` (where they came from, with the
command that made them and their sizes). Written to a temporary folder and renamed, so a
half-shipped folder never replaces a good one.
"""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import torch

from anchordp3.pipeline.evaluation import PRETRAINED_DIR, RUN_CONFIG_FILE
from anchordp3.pipeline.store import MANIFEST, read_manifest
from anchordp3.pipeline.training import TRAINING_FILE, model_dir, trained_model
from anchordp3.schemas.run import load_run_config
from anchordp3.schemas.training import MODELS, DiffusionSchedulerConfig
from anchordp3.stages.files import atomic_write_bytes
from anchordp3.stages.training_loop import load_checkpoint

SHIPPED_FILE = "SHIPPED.md"


HALF_MIN_NUMEL = 1024  # float tensors at least this large are stored in float16 when shipping


def half_weights(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``state`` with every large float32 tensor (weights, not normaliser limits) in float16.
    ``load_state_dict`` copies them back into the float32 parameters: about 3 decimal digits per
    weight, half the bytes."""
    return {k: v.half() if v.dtype == torch.float32 and v.numel() >= HALF_MIN_NUMEL else v for k, v in state.items()}


def slim_checkpoint(name: str, path: Path, ddim_steps: int | None = None) -> tuple[bytes, dict]:
    """``model.pt`` bytes of model ``name`` without what evaluation never reads (the policy's raw
    (non-EMA) weights are its EMA ones, and large weights are stored in float16), and the model's
    config as shipped. ``ddim_steps``: the policy's DDIM steps per decision (its config's
    ``scheduler.num_inference_steps``; None keeps the ones it was trained and validated with)."""
    ckpt = load_checkpoint(path)
    if name == "policy" and ddim_steps is not None:
        ckpt["config"]["scheduler"]["num_inference_steps"] = ddim_steps
    if "weights_dir" in ckpt:  # checkpoints of older code recorded the resolved (machine) path
        ckpt["weights_dir"] = ckpt.get("config", {}).get("weights_dir")
    for key in ("state_dict", "ema_state_dict"):
        if key in ckpt:
            ckpt[key] = half_weights(ckpt[key])
    if name == "policy":
        ckpt["state_dict"] = ckpt["ema_state_dict"]  # the same tensors: stored once
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    return buf.getvalue(), ckpt.get("config", {})


def shipped_folder(path: Path) -> bool:
    """Whether ``path`` is a shipped models folder (``MODEL/model.pt`` and ``run_config.yaml``), not a run."""
    return (Path(path) / RUN_CONFIG_FILE).is_file() and all((Path(path) / m / "model.pt").is_file() for m in MODELS)


def _source(src: Path, name: str, shipped: bool) -> tuple[Path, Path]:
    """``(model.pt, folder of its manifest and training config)`` of model ``name`` in a run or
    (``shipped``) a shipped models folder; FileNotFoundError naming a model the run has not trained."""
    if shipped:
        return src / name / "model.pt", src / name
    found = trained_model(src, name)
    if found is None:
        raise FileNotFoundError(f"{model_dir(src, name)}: no trained {name}; run `anchordp3 train all --run-dir {src}`")
    return found[0], model_dir(src, name)


def ship_models(run_dir: Path, dest: Path | None = None, command: str = "", ddim_steps: int | None = None) -> str:
    """Copy the three trained models of a run, or of a shipped models folder (to ship them again,
    e.g. with other DDIM steps), into ``dest`` (default: the package's ``pretrained/``); returns a
    one-line summary. ``ddim_steps``: the shipped policy's DDIM steps per decision (None: its own).
    Raises FileNotFoundError naming a model that is not trained."""
    run_dir, dest = Path(run_dir), Path(dest) if dest is not None else PRETRAINED_DIR
    tmp = dest.with_name(f".{dest.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shipped = shipped_folder(run_dir)
    sizes, configs = {}, {}
    for name in MODELS:
        model_pt, folder = _source(run_dir, name, shipped)
        blob, configs[name] = slim_checkpoint(name, model_pt, ddim_steps)
        atomic_write_bytes(tmp / name / "model.pt", blob)
        manifest = read_manifest(folder)  # shipped as JSON, every record inline (a format read_manifest reads)
        atomic_write_bytes(tmp / name / MANIFEST, manifest.model_dump_json(indent=1).encode())
        if (folder / TRAINING_FILE).is_file():
            atomic_write_bytes(tmp / name / TRAINING_FILE, (folder / TRAINING_FILE).read_bytes())
        sizes[name] = len(blob)
    run_config = run_dir / RUN_CONFIG_FILE if shipped else run_dir / "config.yaml"
    atomic_write_bytes(tmp / RUN_CONFIG_FILE, run_config.read_bytes())
    total = sum(sizes.values())
    sampling = DiffusionSchedulerConfig.model_validate(configs["policy"]["scheduler"])  # defaults for older checkpoints
    steps = sampling.num_inference_steps
    origin = f"From the {'models folder' if shipped else 'run'} `{run_dir.name}`"
    tasks = load_run_config(run_config).tasks
    lines = ["# Shipped models", "", origin + (f", made by `{command}`." if command else "."), "",
             f"Tasks ({len(tasks)}): {', '.join(tasks)}.", "",
             "| model | model.pt MB |", "|---|---|"] + [f"| {k} | {v / 1e6:.2f} |" for k, v in sizes.items()] + \
            ["", f"In all {total / 1e6:.2f} MB. `run_config.yaml` is the data config they were trained on. "
             f"The policy decides with {steps} DDIM steps.", ""]
    atomic_write_bytes(tmp / SHIPPED_FILE, "\n".join(lines).encode())
    if dest.exists():
        old = dest.with_name(f".{dest.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        dest.rename(old)
        tmp.rename(dest)
        shutil.rmtree(old)
    else:
        tmp.rename(dest)
    return f"shipped {', '.join(MODELS)} ({total / 1e6:.1f} MB) from {run_dir} to {dest}"
