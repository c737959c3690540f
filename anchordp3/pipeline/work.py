"""One item of one data stage, as a plain function (the Ray actors in ``actors.py`` call it).

Items are small dicts of IDs and paths; every output is written by the stage into the run
directory, and what comes back is a small result: output path, checksum, facts.
"""

from __future__ import annotations

import time
from pathlib import Path

from anchordp3.dataset.files import file_sha256
from anchordp3.schemas.dataset import ShardMember
from anchordp3.schemas.episode import EpisodeRecord
from anchordp3.schemas.run import RunConfig
from anchordp3.stages.anchors import load_plan, run_anchors
from anchordp3.stages.features import run_features
from anchordp3.stages.files import frames_file, plan_file
from anchordp3.stages.render import run_render
from anchordp3.stages.rollout import rollout
from anchordp3.stages.write import write_shard

STAGE_DIRS = {"rollout": "rollout", "anchors": "anchors", "render": "render", "features": "features", "write": "dataset"}


def stage_dir(run_dir: Path, stage: str) -> Path:
    """Folder of ``stage`` in a run directory."""
    return Path(run_dir) / STAGE_DIRS[stage]


def run_item(stage: str, run_dir: Path, cfg: RunConfig, item: dict) -> dict:
    """Do ``item`` of ``stage``; returns ``{output, checksum, seconds, info}``.

    Raises whatever the stage raises (the caller retries and records failures)."""
    t0 = time.perf_counter()
    out = _STAGES[stage](Path(run_dir), cfg, item)
    out["seconds"] = time.perf_counter() - t0
    return out


def _rollout(run: Path, cfg: RunConfig, item: dict) -> dict:
    d = stage_dir(run, "rollout")
    rec = rollout(item["task"], int(item["seed"]), cfg.world(), cfg.preset, d)
    checksum = file_sha256(d / rec.arrays) if rec.arrays else None
    return {"output": rec.arrays, "checksum": checksum, "info": {"kept": rec.success, "record": rec.model_dump(mode="json")}}


def _anchors(run: Path, cfg: RunConfig, item: dict) -> dict:
    d = stage_dir(run, "anchors")
    rec = EpisodeRecord.model_validate(item["record"])
    rel = run_anchors(rec, stage_dir(run, "rollout"), d, cfg.anchors)
    plan = load_plan(d / rel)
    return {"output": rel, "checksum": file_sha256(d / rel),
            "info": {"frames": len(plan), "dagger": sum(k == "dagger" for k in plan.kind), "anchors": len(plan.anchor_t)}}


def _render(run: Path, cfg: RunConfig, item: dict) -> dict:
    d = stage_dir(run, "render")
    rec = EpisodeRecord.model_validate(item["record"])
    plan = stage_dir(run, "anchors") / plan_file(rec.task, rec.seed)
    rel = run_render(rec, stage_dir(run, "rollout"), plan, d, cfg.world(), cfg.render, cfg.anchors)
    return {"output": rel, "checksum": file_sha256(d / rel), "info": {}}


def _features(run: Path, cfg: RunConfig, item: dict) -> dict:
    d = stage_dir(run, "features")
    frames = stage_dir(run, "render") / frames_file(item["task"], int(item["seed"]))
    rel = run_features(item["task"], int(item["seed"]), frames, d, cfg.features)
    return {"output": rel, "checksum": file_sha256(d / rel), "info": {}}


def _write(run: Path, cfg: RunConfig, item: dict) -> dict:
    members = [ShardMember.model_validate(m) for m in item["members"]]
    rec = write_shard(int(item["shard"]), members, stage_dir(run, "features"), stage_dir(run, "write"), cfg.write,
                      tasks=item["tasks"], failed=[tuple(x) for x in item["failed"]])
    return {"output": rec.path, "checksum": rec.checksum, "info": {"samples": rec.samples, "shard": rec.model_dump(mode="json")}}


_STAGES = {"rollout": _rollout, "anchors": _anchors, "render": _render, "features": _features, "write": _write}

# The module whose code (with all it imports) makes each stage's outputs: its fingerprint's code_hash.
STAGE_CODE = {"rollout": rollout.__module__, "anchors": run_anchors.__module__, "render": run_render.__module__,
              "features": run_features.__module__, "write": write_shard.__module__}
