"""The manifest store: records durable per transaction, totals kept with them, the earlier JSON
format read and migrated, corrupt files named, stale fingerprints refused."""

from __future__ import annotations

import json
import sqlite3

import pytest

from anchordp3.pipeline.store import (
    JOURNAL, MANIFEST, RECORDS, ManifestStore, StaleStageError, has_manifest, read_manifest, read_stopped, read_summary,
)
from anchordp3.pipeline.noop import NoopFirstInfo
from anchordp3.schemas.manifest import Fingerprint, ItemRecord, StageManifest

FP = Fingerprint(code_version="1", code_hash="c", config_hash="a")


def _rec(i: int, status: str = "done", seconds: float = 1.0) -> ItemRecord:
    return ItemRecord(item=f"t/{i:06d}", status=status, output=f"o{i}" if status == "done" else None, seconds=seconds,
                      reason=None if status == "done" else "Boom", info={"n": i})


def test_records_and_totals_survive_reopening(tmp_path):
    store = ManifestStore(tmp_path / "s", "rollout", FP)
    store.record_many([_rec(i) for i in range(5)] + [_rec(5, "failed")])
    store.finish(8, False)
    store.close()
    again = ManifestStore(tmp_path / "s", "rollout", FP)
    assert again.done("t/000003") and not again.done("t/000005") and again.items["t/000004"].info == {"n": 4}
    c = read_summary(tmp_path / "s").counts
    assert (c.done, c.failed, c.planned, c.seconds) == (5, 1, 8, 6.0)
    again.record(_rec(5))  # a retried item replaces its failed record
    c = read_summary(tmp_path / "s").counts
    assert (c.done, c.failed, c.seconds) == (6, 0, 6.0)
    again.forget(["t/000000", "t/000001"])
    m = read_manifest(tmp_path / "s")
    assert sorted(m.items) == [f"t/{i:06d}" for i in range(2, 6)] and m.counts.done == 4 and not m.complete
    again.close()


def test_a_record_added_without_commit_is_invisible_until_flush(tmp_path):
    store = ManifestStore(tmp_path / "s", "render", FP)
    store.record(_rec(0))
    store.record(_rec(1), durable=False)
    assert sorted(read_manifest(tmp_path / "s").items) == ["t/000000"]  # what a crash now would leave
    store.flush()
    assert sorted(read_manifest(tmp_path / "s").items) == ["t/000000", "t/000001"]
    assert read_summary(tmp_path / "s").counts.done == 2 and read_summary(tmp_path / "s").items == {}
    store.close()


def test_the_summary_comes_from_the_totals_not_the_records(tmp_path):
    store = ManifestStore(tmp_path / "s", "features", FP)
    store.record_many(_rec(i, seconds=0.5) for i in range(20000))
    store.finish(20000, True)
    store.close()
    with sqlite3.connect(tmp_path / "s" / RECORDS) as db:  # records removed behind the store's back:
        db.execute("DELETE FROM items")                      # the summary does not read them
    s = read_summary(tmp_path / "s")
    assert (s.counts.done, s.counts.seconds, s.complete) == (20000, 10000.0, True)
    assert read_manifest(tmp_path / "s").items == {}


def test_a_folder_of_the_earlier_json_format_is_read_then_migrated_on_first_write(tmp_path):
    d = tmp_path / "s"
    d.mkdir()
    old = StageManifest(stage="anchors", fingerprint=FP, complete=False, items={r.item: r for r in (_rec(0), _rec(1))})
    (d / MANIFEST).write_text(old.model_dump_json())
    head = json.dumps({"stage": "anchors", "fingerprint": FP.model_dump(mode="json")})
    (d / JOURNAL).write_text(head + "\n" + _rec(2, "failed").model_dump_json() + "\n{\"torn")
    before = read_manifest(d)
    assert sorted(before.items) == ["t/000000", "t/000001", "t/000002"] and before.counts.failed == 1
    store = ManifestStore(d, "anchors", FP)
    store.record(_rec(3))
    store.close()
    assert not (d / MANIFEST).exists() and not (d / JOURNAL).exists() and (d / RECORDS).is_file()
    after = read_manifest(d)
    assert {k: v for k, v in after.items.items() if k != "t/000003"} == before.items
    assert (after.counts.done, after.counts.failed) == (3, 1)


def test_a_corrupt_records_file_is_named(tmp_path):
    d = tmp_path / "s"
    d.mkdir()
    (d / RECORDS).write_bytes(b"\x93not sqlite at all" * 50)
    assert has_manifest(d)
    with pytest.raises(ValueError, match=str(d / RECORDS)):
        read_summary(d)
    with pytest.raises(ValueError, match=str(d / RECORDS)):
        read_manifest(d)


def test_a_changed_fingerprint_is_refused_unless_reset_or_adopted(tmp_path):
    d = tmp_path / "s"
    store = ManifestStore(d, "write", FP)
    store.record(_rec(0))
    store.close()
    new = FP.model_copy(update={"code_hash": "d"})
    with pytest.raises(StaleStageError):
        ManifestStore(d, "write", new)
    kept = ManifestStore(d, "write", new, adopt=True)
    assert kept.done("t/000000")
    kept.close()
    assert read_summary(d).fingerprint == new
    fresh = ManifestStore(d, "write", FP, reset=True)
    assert len(fresh.items) == 0
    fresh.close()


def _stop_rec(i: int) -> ItemRecord:
    return ItemRecord(item=f"t/{i:06d}", status="done", output=None, seconds=0.1,
                      info=NoopFirstInfo(seed=i, kept=i % 3 != 0).model_dump(mode="json"))


def test_items_that_stop_their_episode_are_found_without_parsing_every_record(tmp_path):
    store = ManifestStore(tmp_path / "s", "rollout", FP, payload=NoopFirstInfo)
    store.record_many([_stop_rec(i) for i in range(10)] + [_rec(10, "failed")])
    assert store.stopped() == {"t/000000", "t/000003", "t/000006", "t/000009"}
    store.close()
    with sqlite3.connect(tmp_path / "s" / RECORDS) as db:  # the records' JSON blanked: the query does not read it
        db.execute("UPDATE items SET record = '{}' WHERE stops = 0")
    assert [r.item for r in read_stopped(tmp_path / "s", NoopFirstInfo)] == ["t/000000", "t/000003", "t/000006", "t/000009"]


def test_a_file_from_before_the_stops_column_gets_it_filled_from_its_records(tmp_path):
    store = ManifestStore(tmp_path / "s", "rollout", FP, payload=NoopFirstInfo)
    store.record_many([_stop_rec(i) for i in range(7)])
    store.close()
    with sqlite3.connect(tmp_path / "s" / RECORDS) as db:  # the layout of the first SQLite store
        db.executescript("DROP INDEX items_stops; ALTER TABLE items DROP COLUMN stops;")
    assert [r.item for r in read_stopped(tmp_path / "s", NoopFirstInfo)] == ["t/000000", "t/000003", "t/000006"]  # read by parsing
    again = ManifestStore(tmp_path / "s", "rollout", FP, payload=NoopFirstInfo)  # a writer adds and fills the column
    assert again.stopped() == {"t/000000", "t/000003", "t/000006"}
    again.close()
