"""A stage's manifest on disk: ``manifest.json`` plus an append-only journal of item records.

Each finished item appends one JSON line to ``journal.jsonl`` and fsyncs it, after its output is
durable; so a crash at any instant leaves at worst an orphan output (redone on resume, same
bytes) and at worst a torn last journal line (ignored on load). ``compact()`` folds the journal
into ``manifest.json`` (written atomically) and empties the journal.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from pydantic import ValidationError

from anchordp3.schemas.manifest import Fingerprint, ItemRecord, StageCounts, StageManifest
from anchordp3.stages.files import atomic_write_bytes

MANIFEST = "manifest.json"
JOURNAL = "journal.jsonl"


class StaleStageError(ValueError):
    """A stage's existing outputs were made with a different fingerprint."""


def read_manifest(stage_dir: Path) -> StageManifest | None:
    """The stage's manifest with the journal folded in; None when the stage never ran."""
    stage_dir = Path(stage_dir)
    path = stage_dir / MANIFEST
    manifest = None
    if path.is_file():
        try:
            manifest = StageManifest.model_validate_json(path.read_bytes())
        except ValidationError as e:
            err = e.errors()[0]
            raise ValueError(f"{path}: not a stage manifest ({'.'.join(map(str, err['loc']))}: {err['msg']})") from None
        except ValueError as e:
            raise ValueError(f"{path}: not a stage manifest ({str(e).splitlines()[0]})") from None
    journal = stage_dir / JOURNAL
    if journal.is_file():
        lines = journal.read_bytes().split(b"\n")
        if manifest is None:
            head = _journal_head(journal, lines[0])
            manifest = StageManifest(stage=head["stage"], fingerprint=Fingerprint.model_validate(head["fingerprint"]))
        for line in lines[1:]:
            try:
                rec = ItemRecord.model_validate_json(line)
            except ValueError:
                continue  # a torn last line (crash mid-append) or blank
            manifest.items[rec.item] = rec
    if manifest is not None:
        manifest.items = dict(sorted(manifest.items.items()))
        _recount(manifest)
    return manifest


def _journal_head(path: Path, line: bytes) -> dict:
    try:
        head = json.loads(line)
        Fingerprint.model_validate(head["fingerprint"])
        return head
    except (ValueError, KeyError, TypeError):
        raise ValueError(f"{path}: not a stage journal (bad first line)") from None


def _recount(m: StageManifest) -> None:
    recs = m.items.values()
    m.counts = StageCounts(planned=max(m.counts.planned, len(m.items)), done=sum(r.status == "done" for r in recs),
                           failed=sum(r.status == "failed" for r in recs), seconds=sum(r.seconds for r in recs))


class ManifestStore:
    """The manifest of one stage of one run, opened for writing.

    fingerprint: what the outputs about to be written depend on. Opening a stage whose stored
    fingerprint differs raises ``StaleStageError`` unless ``reset`` (then its folder is emptied) or
    ``adopt`` (the records are kept and the manifest takes ``fingerprint``, durably, at once)."""

    def __init__(self, stage_dir: Path, stage: str, fingerprint: Fingerprint, reset: bool = False, adopt: bool = False):
        self.dir, self.stage, self.fingerprint = Path(stage_dir), stage, fingerprint
        existing = read_manifest(self.dir) if self.dir.exists() else None
        adopted = False
        if existing is not None and existing.fingerprint != fingerprint:
            if not (reset or adopt):
                raise StaleStageError(f"stage {stage}: its outputs were made with a different config or code version")
            if reset:
                existing = None
            else:
                existing.fingerprint, adopted = fingerprint, True
        if reset and self.dir.exists():
            shutil.rmtree(self.dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.manifest = existing or StageManifest(stage=stage, fingerprint=fingerprint)
        self._journal = None
        if adopted:
            self.compact(existing.counts.planned, existing.complete)

    @property
    def items(self) -> dict[str, ItemRecord]:
        """Records so far, by item id."""
        return self.manifest.items

    def done(self, item: str) -> bool:
        """Whether ``item`` has a durable output."""
        r = self.manifest.items.get(item)
        return r is not None and r.status == "done"

    def record(self, rec: ItemRecord) -> None:
        """Append ``rec`` durably (call only after the item's output is durable)."""
        if self._journal is None:
            path = self.dir / JOURNAL
            fresh = not path.exists() or path.stat().st_size == 0
            self._journal = open(path, "ab")
            if fresh:
                head = {"stage": self.stage, "fingerprint": self.fingerprint.model_dump(mode="json")}
                self._journal.write(json.dumps(head).encode() + b"\n")
        self._journal.write(rec.model_dump_json().encode() + b"\n")
        self._journal.flush()
        os.fsync(self._journal.fileno())
        self.manifest.items[rec.item] = rec

    def forget(self, items: list[str]) -> None:
        """Drop the records of ``items`` (they will be redone), durably."""
        for i in items:
            self.manifest.items.pop(i, None)
        self.compact(self.manifest.counts.planned, False)

    def compact(self, planned: int, complete: bool) -> StageManifest:
        """Write ``manifest.json`` with every record and empty the journal."""
        m = self.manifest
        m.items = dict(sorted(m.items.items()))
        m.counts.planned = planned
        _recount(m)
        m.counts.planned = planned
        m.complete = complete
        atomic_write_bytes(self.dir / MANIFEST, m.model_dump_json(indent=1).encode())
        if self._journal is not None:
            self._journal.close()
            self._journal = None
        (self.dir / JOURNAL).unlink(missing_ok=True)
        return m

    def close(self) -> None:
        if self._journal is not None:
            self._journal.close()
            self._journal = None
