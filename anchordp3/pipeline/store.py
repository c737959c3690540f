"""A stage's manifest on disk: one SQLite file, ``records.sqlite``, with its totals and one row per item.

Layout: a ``meta`` table (stage, fingerprint, planned, complete, and the running totals done /
failed / seconds) and an ``items`` table (item id, status, seconds, ``stops``: 1 when the item is
done and its typed payload stops the episode there (``Payload.continues`` false: a rollout whose
expert failed), and the ``ItemRecord`` as JSON). A writer given its stage's payload model fills
``stops``, so the stopped items of a million are found by one indexed query, not by parsing every
record (``read_stopped``, the runner's resume).
Every write is a transaction committed with ``synchronous=FULL`` in WAL mode: a record is on disk
once ``record`` (or ``flush`` after ``record(..., durable=False)``) returns, a crash at any instant
leaves the last committed state, and readers (``anchordp3 status`` while a run goes on) never
block the writer. The totals live in ``meta`` and are updated in the same transaction as the
records, so ``read_summary`` answers from a few rows however large the stage, and the writer's
cost per record does not grow with the run.

The writer keeps only each item's status in memory (``ManifestStore.items`` is a lazy view that
reads a record from the file when asked). Folders written before this format (``manifest.json``
with every record inline, plus ``journal.jsonl``) are read as they are, and migrated into
``records.sqlite`` the first time they are opened for writing.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

from pydantic import ValidationError

from anchordp3.schemas.manifest import Fingerprint, ItemRecord, StageCounts, StageManifest
from anchordp3.schemas.records import Payload
from anchordp3.stages.files import TMP_MARK

RECORDS = "records.sqlite"
MANIFEST = "manifest.json"  # the earlier format (read, and migrated on the first write)
JOURNAL = "journal.jsonl"   # the earlier format's journal
STORE_FILES = (RECORDS, MANIFEST, JOURNAL)
_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS items (item TEXT PRIMARY KEY, status TEXT NOT NULL, seconds REAL NOT NULL, record TEXT NOT NULL,
                                  stops INTEGER NOT NULL DEFAULT 0);
CREATE INDEX IF NOT EXISTS items_stops ON items (stops) WHERE stops = 1;
"""


class StaleStageError(ValueError):
    """A stage's existing outputs were made with a different fingerprint."""


def has_manifest(stage_dir: Path) -> bool:
    """Whether ``stage_dir`` holds a stage manifest (either format)."""
    return any((Path(stage_dir) / f).is_file() for f in STORE_FILES)


# ---------------------------------------------------------------------------------- reading
def read_summary(stage_dir: Path) -> StageManifest | None:
    """The stage's fingerprint, totals and completeness without its records (``items`` empty);
    None when the stage never ran. Costs a few rows of a file however many items it holds."""
    stage_dir = Path(stage_dir)
    if (stage_dir / RECORDS).is_file():
        with _reader(stage_dir / RECORDS) as db:
            return _summary(db, stage_dir / RECORDS)
    m = _read_legacy(stage_dir)
    if m is not None:
        m.items = {}
    return m


def read_manifest(stage_dir: Path) -> StageManifest | None:
    """The stage's manifest with every record (sorted by item id); None when the stage never ran."""
    stage_dir = Path(stage_dir)
    if (stage_dir / RECORDS).is_file():
        path = stage_dir / RECORDS
        with _reader(path) as db:
            m = _summary(db, path)
            m.items = {item: _parse(rec, path) for item, rec in db.execute("SELECT item, record FROM items ORDER BY item")}
        return m
    return _read_legacy(stage_dir)


def read_records(stage_dir: Path, status: str | None = None, slowest: bool = False, limit: int = 0) -> list[ItemRecord]:
    """Some of a stage's records without reading the rest: those of one ``status`` (None: any),
    sorted by item id or, ``slowest``, by seconds (most first), at most ``limit`` (0: all)."""
    stage_dir = Path(stage_dir)
    if not (stage_dir / RECORDS).is_file():
        m = _read_legacy(stage_dir)
        recs = [r for r in (m.items.values() if m else []) if status is None or r.status == status]
        recs = sorted(recs, key=lambda r: -r.seconds) if slowest else recs
        return recs[:limit] if limit > 0 else recs
    sql = "SELECT record FROM items" + (" WHERE status = ?" if status else "") + (" ORDER BY seconds DESC, item" if slowest else " ORDER BY item")
    sql += f" LIMIT {int(limit)}" if limit > 0 else ""
    with _reader(stage_dir / RECORDS) as db:
        return [_parse(text, stage_dir / RECORDS) for (text,) in db.execute(sql, (status,) if status else ())]


def read_stopped(stage_dir: Path, payload: type[Payload]) -> list[ItemRecord]:
    """The records of items done whose ``payload`` stops the episode (``continues`` false), by item
    id: one indexed query (a folder of the earlier formats: every record parsed)."""
    stage_dir = Path(stage_dir)
    if (stage_dir / RECORDS).is_file():
        with _reader(stage_dir / RECORDS) as db:
            if _has_stops(db):
                rows = db.execute("SELECT record FROM items WHERE stops = 1 ORDER BY item")
                return [_parse(text, stage_dir / RECORDS) for (text,) in rows]
    return [r for r in read_records(stage_dir, status="done") if _stops(r, payload)]


def _stops(rec: ItemRecord, payload: type[Payload] | None) -> bool:
    """Whether ``rec`` is done and its payload stops the episode there."""
    return payload is not None and rec.status == "done" and not rec.payload(payload).continues


def _has_stops(db: sqlite3.Connection) -> bool:
    return any(row[1] == "stops" for row in db.execute("PRAGMA table_info(items)"))


def read_record(stage_dir: Path, item: str) -> ItemRecord | None:
    """The record of one item (None when the stage has none), without reading the others."""
    stage_dir = Path(stage_dir)
    if not (stage_dir / RECORDS).is_file():
        m = _read_legacy(stage_dir)
        return m.items.get(item) if m else None
    with _reader(stage_dir / RECORDS) as db:
        row = db.execute("SELECT record FROM items WHERE item = ?", (item,)).fetchone()
    return None if row is None else _parse(row[0], stage_dir / RECORDS)


def count_records(stage_dir: Path) -> int:
    """Items recorded so far (durable), read while a run may be writing."""
    m = read_summary(stage_dir) if has_manifest(stage_dir) else None
    return 0 if m is None else m.counts.done + m.counts.failed


class _reader:
    """A read-only connection (``mode=ro``; ``immutable`` where the folder cannot be written, as
    an installed package's)."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self) -> sqlite3.Connection:
        try:
            self.db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True)
            self.db.execute("SELECT 1 FROM meta LIMIT 1")
        except sqlite3.DatabaseError as e:
            try:
                self.db = sqlite3.connect(f"file:{self.path}?immutable=1", uri=True)
                self.db.execute("SELECT 1 FROM meta LIMIT 1")
            except sqlite3.DatabaseError:
                raise ValueError(f"{self.path}: not a stage manifest ({e})") from None
        return self.db

    def __exit__(self, *exc) -> None:
        self.db.close()


def _summary(db: sqlite3.Connection, path: Path) -> StageManifest:
    meta = dict(db.execute("SELECT key, value FROM meta"))
    try:
        fp = Fingerprint.model_validate_json(meta["fingerprint"])
        counts = StageCounts(planned=int(meta["planned"]), done=int(meta["done"]), failed=int(meta["failed"]),
                             seconds=float(meta["seconds"]))
        return StageManifest(stage=meta["stage"], fingerprint=fp, complete=meta["complete"] == "1", counts=counts)
    except (KeyError, ValueError) as e:
        raise ValueError(f"{path}: not a stage manifest (meta: {str(e).splitlines()[0]})") from None


def _parse(text: str | bytes, path: Path) -> ItemRecord:
    try:
        return ItemRecord.model_validate_json(text)
    except ValidationError as e:
        err = e.errors()[0]
        raise ValueError(f"{path}: a bad item record ({'.'.join(map(str, err['loc']))}: {err['msg']})") from None


def _read_legacy(stage_dir: Path) -> StageManifest | None:
    """A manifest of the earlier format: ``manifest.json`` (every record inline) and ``journal.jsonl``."""
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
        recs = manifest.items.values()
        manifest.counts = StageCounts(planned=max(manifest.counts.planned, len(manifest.items)),
                                      done=sum(r.status == "done" for r in recs), failed=sum(r.status == "failed" for r in recs),
                                      seconds=sum(r.seconds for r in recs))
    return manifest


def _journal_head(path: Path, line: bytes) -> dict:
    try:
        head = json.loads(line)
        Fingerprint.model_validate(head["fingerprint"])
        return head
    except (ValueError, KeyError, TypeError):
        raise ValueError(f"{path}: not a stage journal (bad first line)") from None


# ---------------------------------------------------------------------------------- writing
class RecordView(Mapping):
    """The records of an open store by item id: statuses from memory, each record read from the
    file only when asked for (``get``, ``[]``, ``values``)."""

    def __init__(self, store: ManifestStore):
        self._store = store

    def __getitem__(self, item: str) -> ItemRecord:
        rec = self._store.get(item)
        if rec is None:
            raise KeyError(item)
        return rec

    def get(self, item: str, default=None):
        return self._store.get(item) if item in self._store.status else default

    def __contains__(self, item) -> bool:
        return item in self._store.status

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(self._store.status))

    def __len__(self) -> int:
        return len(self._store.status)

    def values(self):
        return [r for _, r in self._store.records()]

    def items(self):
        return list(self._store.records())


class ManifestStore:
    """The manifest of one stage of one run, opened for writing (one writer at a time: the run lock).

    fingerprint: what the outputs about to be written depend on. Opening a stage whose stored
    fingerprint differs raises ``StaleStageError`` unless ``reset`` (then its folder is emptied) or
    ``adopt`` (the records are kept and the manifest takes ``fingerprint``, durably, at once).
    payload: the stage's payload model, when its items can stop an episode (fills ``stops``).
    forget: items whose records go in the same transaction that writes ``fingerprint`` (they
    will be redone: a task whose code changed)."""

    def __init__(self, stage_dir: Path, stage: str, fingerprint: Fingerprint, reset: bool = False, adopt: bool = False,
                 payload: type[Payload] | None = None, forget: Iterable[str] = ()):
        self.dir, self.stage, self.fingerprint, self.payload = Path(stage_dir), stage, fingerprint, payload
        existing = read_summary(self.dir) if self.dir.exists() else None
        if existing is not None and existing.fingerprint != fingerprint and not (reset or adopt):
            raise StaleStageError(f"stage {stage}: its outputs were made with a different config or code version")
        if reset and self.dir.exists():
            shutil.rmtree(self.dir)
            existing = None
        self.dir.mkdir(parents=True, exist_ok=True)
        if existing is not None and not (self.dir / RECORDS).is_file():
            self._migrate()
        if not (self.dir / RECORDS).is_file():  # a new manifest appears whole, its fingerprint in it
            _create_manifest(self.dir / RECORDS, _meta_rows(StageManifest(stage=stage, fingerprint=fingerprint), 0))
        self.db = sqlite3.connect(self.dir / RECORDS, isolation_level=None)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=FULL")
        self._add_stops()
        self.db.executescript(_SCHEMA)
        self.status: dict[str, str] = dict(self.db.execute("SELECT item, status FROM items"))
        self.counts = StageCounts()
        self.complete = False
        if existing is not None:
            self.counts, self.complete = existing.counts.model_copy(), existing.complete
        self._pending: dict[str, ItemRecord] = {}
        with _transaction(self.db):  # the fingerprint is on disk before any output of this writer is, and
            self._drop(forget)        # in the same step the records it no longer covers are gone
            self._put_meta(self._meta())

    # ------------------------------------------------------------------------------ reading
    @property
    def items(self) -> RecordView:
        """Records so far, by item id (lazy: read from the file when asked)."""
        return RecordView(self)

    @property
    def manifest(self) -> StageManifest:
        """Fingerprint, totals and completeness (``items`` left empty: use ``items``)."""
        return StageManifest(stage=self.stage, fingerprint=self.fingerprint, complete=self.complete, counts=self.counts.model_copy())

    def done(self, item: str) -> bool:
        """Whether ``item`` has a durable output."""
        return self.status.get(item) == "done"

    def get(self, item: str) -> ItemRecord | None:
        """The record of ``item`` (None when it has none)."""
        if item in self._pending:
            return self._pending[item]
        row = self.db.execute("SELECT record FROM items WHERE item = ?", (item,)).fetchone()
        return None if row is None else _parse(row[0], self.dir / RECORDS)

    def stopped(self) -> set[str]:
        """Items done whose payload stops the episode there (durable ones: flushes first)."""
        self.flush()
        return {item for (item,) in self.db.execute("SELECT item FROM items WHERE stops = 1")}

    def records(self) -> Iterator[tuple[str, ItemRecord]]:
        """Every ``(item, record)``, sorted by item id."""
        self.flush()
        for item, text in self.db.execute("SELECT item, record FROM items ORDER BY item").fetchall():
            yield item, _parse(text, self.dir / RECORDS)

    # ------------------------------------------------------------------------------ writing
    def record(self, rec: ItemRecord, durable: bool = True) -> None:
        """Add ``rec`` (call only after the item's output is durable). ``durable``: commit now;
        else it is committed by the next ``flush`` (several records, one transaction)."""
        self._count(self.get(rec.item) if rec.item in self.status else None, -1)
        self._count(rec, +1)
        self.status[rec.item] = rec.status
        self._pending[rec.item] = rec
        if durable:
            self.flush()

    def record_many(self, recs: Iterable[ItemRecord]) -> None:
        """Add several records in one transaction."""
        for rec in recs:
            self.record(rec, durable=False)
        self.flush()

    def flush(self) -> None:
        """Commit the records added with ``durable=False``, and the totals, in one transaction."""
        if self._pending:
            self._commit()

    def _commit(self) -> None:
        rows = [(r.item, r.status, r.seconds, r.model_dump_json(), int(_stops(r, self.payload))) for r in self._pending.values()]
        with _transaction(self.db):
            self.db.executemany("INSERT OR REPLACE INTO items VALUES (?, ?, ?, ?, ?)", rows)
            self._put_meta(self._meta())
        self._pending.clear()

    def forget(self, items: list[str]) -> None:
        """Drop the records of ``items`` (they will be redone), durably; the stage is no longer complete."""
        self.flush()
        self.complete = False
        with _transaction(self.db):
            self._drop(items)
            self._put_meta(self._meta())

    def finish(self, planned: int, complete: bool) -> StageManifest:
        """Commit what is pending with the stage's planned count and completeness; returns the summary."""
        self.counts.planned = max(planned, len(self.status))
        self.complete = complete
        self._commit()
        return self.manifest

    def close(self, commit: bool = True) -> None:
        """Commit what is pending (unless not ``commit``: it is dropped) and close the file."""
        if getattr(self, "db", None) is not None:
            try:
                if commit:
                    self.flush()
            finally:
                self.db.close()
                self.db = None

    # ------------------------------------------------------------------------------ helpers
    def _drop(self, items: Iterable[str]) -> None:
        """Delete the records of ``items`` and their counts (inside the caller's transaction); a
        stage that loses any is no longer complete."""
        gone = [i for i in items if i in self.status]
        for item in gone:
            self._count(self.get(item), -1)
            del self.status[item]
        if gone:
            self.complete = False
            self.db.executemany("DELETE FROM items WHERE item = ?", [(i,) for i in gone])

    def _count(self, rec: ItemRecord | None, sign: int) -> None:
        if rec is None:
            return
        if rec.status == "done":
            self.counts.done += sign
        else:
            self.counts.failed += sign
        self.counts.seconds = max(self.counts.seconds + sign * rec.seconds, 0.0)

    def _meta(self) -> dict[str, str]:
        return _meta_rows(self.manifest, len(self.status))

    def _put_meta(self, meta: dict[str, str]) -> None:
        self.db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", list(meta.items()))

    def _add_stops(self) -> None:
        """A file written before the ``stops`` column gets it, filled from the records (once)."""
        if not self.db.execute("SELECT 1 FROM sqlite_master WHERE name = 'items'").fetchone() or _has_stops(self.db):
            return
        with _transaction(self.db):
            self.db.execute("ALTER TABLE items ADD COLUMN stops INTEGER NOT NULL DEFAULT 0")
            if self.payload is not None:
                rows = self.db.execute("SELECT item, record FROM items WHERE status = 'done'").fetchall()
                stopped = [(item,) for item, text in rows if _stops(_parse(text, self.dir / RECORDS), self.payload)]
                self.db.executemany("UPDATE items SET stops = 1 WHERE item = ?", stopped)

    def _migrate(self) -> None:
        """Move a folder of the earlier format into ``records.sqlite`` (built under a temporary name
        and renamed, so a crash leaves either format whole), then drop the old files."""
        old = _read_legacy(self.dir)
        tmp = self.dir / (RECORDS + ".tmp")
        tmp.unlink(missing_ok=True)
        db = sqlite3.connect(tmp, isolation_level=None)
        try:
            db.executescript(_SCHEMA)
            with _transaction(db):
                db.executemany("INSERT INTO items VALUES (?, ?, ?, ?, ?)",
                               [(r.item, r.status, r.seconds, r.model_dump_json(), int(_stops(r, self.payload))) for r in old.items.values()])
                db.executemany("INSERT INTO meta VALUES (?, ?)", list(_meta_rows(old, 0).items()))
        finally:
            db.close()
        tmp.replace(self.dir / RECORDS)
        for name in (MANIFEST, JOURNAL):
            (self.dir / name).unlink(missing_ok=True)


def _create_manifest(path: Path, meta: dict[str, str]) -> None:
    """A new manifest file at ``path`` with its schema and ``meta`` rows, made under a temporary
    name and renamed into place: a reader following a run never finds it without its meta."""
    tmp = path.with_name(f".{path.name}{TMP_MARK}{os.getpid()}")
    tmp.unlink(missing_ok=True)
    db = sqlite3.connect(tmp, isolation_level=None)
    try:
        db.executescript(_SCHEMA)
        with _transaction(db):
            db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", list(meta.items()))
    finally:
        db.close()
    os.replace(tmp, path)


def _meta_rows(m: StageManifest, items: int) -> dict[str, str]:
    """The ``meta`` table of summary ``m`` (planned at least ``items``); ``_summary`` reads it back."""
    c = m.counts
    return {"stage": m.stage, "fingerprint": m.fingerprint.model_dump_json(), "planned": str(max(c.planned, items)),
            "complete": "1" if m.complete else "0", "done": str(c.done), "failed": str(c.failed), "seconds": repr(c.seconds)}


class _transaction:
    """``BEGIN IMMEDIATE`` … ``COMMIT`` (``ROLLBACK`` on error) on an autocommit connection."""

    def __init__(self, db: sqlite3.Connection):
        self.db = db

    def __enter__(self):
        self.db.execute("BEGIN IMMEDIATE")
        return self.db

    def __exit__(self, exc_type, *exc) -> None:
        self.db.execute("ROLLBACK" if exc_type else "COMMIT")
