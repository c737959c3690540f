"""Checking a run directory's outputs against its manifests, and repairing what is broken.

Every done item's output is re-hashed and compared with the checksum its record holds (files by
``file_sha256``, shard folders by ``tree_checksum``); the ``dataset`` item also covers the tables
that ``dataset.json`` lists. Repair forgets exactly the broken items' records (so the manifest no
longer claims them), removes the broken outputs, and resumes the run, which redoes exactly those
items: outputs are deterministic, so the healed run holds the same bytes as before.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from anchordp3.dataset.files import file_sha256, tree_checksum
from anchordp3.pipeline.inspect import check_run_dir, product_folders, run_config, run_status
from anchordp3.pipeline.lock import RunLock
from anchordp3.pipeline.graph import CONFIG_FILE
from anchordp3.pipeline.runner import RunOptions, run_pipeline
from anchordp3.pipeline.store import ManifestStore, read_manifest, read_summary
from anchordp3.pipeline.work import DATA_GRAPH, DATA_STAGES, INDEX_ITEM, stage_dir
from anchordp3.schemas.dataset import DatasetInfo
from anchordp3.schemas.manifest import ItemRecord

log = logging.getLogger(__name__)


class Problem(BaseModel):
    """One missing or corrupt output of a done item."""

    model_config = ConfigDict(extra="forbid")

    stage: str = Field(description="Stage whose manifest records the item.")
    item: str = Field(description="Item id.")
    path: str = Field(description="The output file or folder.")
    kind: Literal["missing", "corrupt"] = Field(description="Absent, or present with other content.")
    detail: str = Field(default="", description="What differs.")

    def line(self) -> str:
        """One line for a terminal."""
        return f"{self.kind}: {self.path} ({self.stage} {self.item}{'; ' + self.detail if self.detail else ''})"


class RunVerifyReport(BaseModel):
    """Outcome of verifying a run directory."""

    model_config = ConfigDict(extra="forbid")

    run_dir: str = Field(description="The run directory.")
    checked: int = Field(ge=0, description="Outputs re-hashed.")
    problems: list[Problem] = Field(default_factory=list, description="Missing or corrupt outputs.")

    @property
    def ok(self) -> bool:
        """Nothing missing or corrupt."""
        return not self.problems

    def text(self) -> str:
        """Problem lines and a summary line."""
        lines = [p.line() for p in self.problems]
        if self.ok:
            lines.append(f"verified {self.checked} outputs in {self.run_dir}: all good")
        else:
            data = len(data_problems(self.problems))
            redo = ["`anchordp3 verify --repair` redoes the data's"] if data else []
            if data < len(self.problems):
                redo.append("`anchordp3 train NAME --force` a model's, `anchordp3 eval --force` an evaluation's")
            lines.append(f"{len(self.problems)} of {self.checked} outputs in {self.run_dir} are missing or corrupt; "
                         + "; ".join(redo))
        return "\n".join(lines)


def check_output(path: Path, checksum: str) -> tuple[str, str] | None:
    """``(kind, detail)`` when ``path`` (a file, or a folder hashed by ``tree_checksum``) is
    missing or its content differs from ``checksum``; None when it is intact."""
    if path.is_dir():
        got = tree_checksum(path)[0]
    elif path.is_file():
        got = file_sha256(path)
    else:
        return "missing", ""
    if got != checksum:
        return "corrupt", f"sha256 {got[:12]}… != recorded {checksum[:12]}…"
    return None


def _check_item(run_dir: Path, stage: str, rec: ItemRecord) -> tuple[int, list[Problem]]:
    """Outputs checked and problems of one done item."""
    root = stage_dir(run_dir, stage)
    path = root / rec.output
    bad = check_output(path, rec.checksum) if rec.checksum else None
    if bad:
        return 1, [Problem(stage=stage, item=rec.item, path=str(path), kind=bad[0], detail=bad[1])]
    if stage != "write" or rec.item != INDEX_ITEM:
        return 1, []
    # the index item's output is dataset.json; the tables it lists are part of the item too
    info = DatasetInfo.model_validate_json(path.read_bytes())
    problems = [Problem(stage=stage, item=rec.item, path=str(root / name), kind=b[0], detail=b[1])
                for name, sha in sorted(info.files.items()) if (b := check_output(root / name, sha))]
    return 1 + len(info.files), problems


def verify_run(run_dir: Path) -> RunVerifyReport:
    """Re-hash the output of every done item of every data stage of ``run_dir``, and of its
    trained models and evaluations (``inspect.product_folders``)."""
    run_dir = check_run_dir(run_dir)
    manifests = {s: read_manifest(d) if (d := stage_dir(run_dir, s)).is_dir() else None for s in DATA_STAGES}
    if all(m is None for m in manifests.values()):
        raise ValueError(f"{run_dir}: no stage has run here (no stage manifest): nothing to verify")
    checked, problems = 0, []
    for s, m in manifests.items():
        if m is None:
            continue
        for rec in m.items.values():
            if rec.status != "done" or rec.output is None:
                continue
            n, ps = _check_item(run_dir, s, rec)
            checked += n
            problems += ps
    for label, d in product_folders(run_dir):
        for rec in read_manifest(d).items.values():
            if rec.status == "done" and rec.output is not None and rec.checksum:
                checked += 1
                if bad := check_output(d / rec.output, rec.checksum):
                    problems.append(Problem(stage=label, item=rec.item, path=str(d / rec.output), kind=bad[0], detail=bad[1]))
    return RunVerifyReport(run_dir=str(run_dir), checked=checked, problems=problems)


def data_problems(problems: list[Problem]) -> list[Problem]:
    """The problems of the data stages (what ``--repair`` redoes; a model or an evaluation is
    redone by ``train --force`` or ``eval --force``)."""
    return [p for p in problems if p.stage in DATA_STAGES]


def items_to_redo(problems: list[Problem]) -> dict[str, list[str]]:
    """Stage → items whose records must go: the broken ones, and the ``dataset`` index item
    when a shard is broken (the index and statistics are rebuilt from the shards)."""
    out: dict[str, list[str]] = {}
    for p in problems:
        out.setdefault(p.stage, [])
        if p.item not in out[p.stage]:
            out[p.stage].append(p.item)
    if "write" in out and any(i != INDEX_ITEM for i in out["write"]) and INDEX_ITEM not in out["write"]:
        out["write"].append(INDEX_ITEM)
    return out


def forget_broken(run_dir: Path, problems: list[Problem]) -> dict[str, list[str]]:
    """Drop the records of the broken items durably, then remove their broken outputs.

    Holds the run lock, so it refuses while a run is going on. Returns stage → items forgotten."""
    run_dir = Path(run_dir)
    redo = items_to_redo(problems)
    with RunLock(run_dir):
        for s, items in redo.items():
            d = stage_dir(run_dir, s)
            m = read_summary(d)
            store = ManifestStore(d, s, m.fingerprint, payload=DATA_GRAPH[s].stop_payload)
            try:
                store.forget(items)
            finally:
                store.close()
        for p in problems:  # records first, outputs second: a crash in between leaves orphans, never dangling records
            path = Path(p.path)
            if path.is_dir():
                shutil.rmtree(path)
            elif path.exists():
                path.unlink()
    return redo


def repair_run(run_dir: Path, address: str | None = None) -> tuple[RunVerifyReport, RunVerifyReport]:
    """Verify ``run_dir``; when something is broken, forget those items and resume the run so
    exactly they are redone; verify again. Returns the reports before and after."""
    before = verify_run(run_dir)
    if not data_problems(before.problems):
        return before, before
    cfg = run_config(run_dir)
    if cfg is None:
        raise FileNotFoundError(f"{Path(run_dir) / CONFIG_FILE}: no such file; cannot resume the run to repair it")
    stale = [st.stage for st in run_status(run_dir) if st.stale]
    if stale:
        raise ValueError(f"{run_dir}: stage(s) {', '.join(stale)} were made with another config or code version than "
                         f"its {CONFIG_FILE}; repairing would mix outputs (rerun with --force instead)")
    redo = forget_broken(run_dir, data_problems(before.problems))
    log.info("redoing " + "; ".join(f"{s}: {', '.join(items)}" for s, items in redo.items()))
    run_pipeline(cfg, Path(run_dir), RunOptions(address=address))
    return before, verify_run(run_dir)
