"""Short human summaries of a run directory."""

from __future__ import annotations

from pathlib import Path

from anchordp3.pipeline.store import STORE_FILES, read_manifest
from anchordp3.pipeline.work import DATA_STAGES, stage_dir
from anchordp3.viz.table import text_table


def data_summary(run_dir: Path) -> str:
    """One row per data stage (done, failed, planned, compute seconds) and where the dataset is."""
    rows = []
    for s in DATA_STAGES:
        d = stage_dir(run_dir, s)
        m = read_manifest(d) if d.exists() else None
        if m is None:
            rows.append([s, "-", "-", "-", "-", "not run"])
            continue
        c = m.counts
        rows.append([s, c.done, c.failed, c.planned, f"{c.seconds:.1f}", "complete" if m.complete else "incomplete"])
    out = text_table(["stage", "done", "failed", "planned", "compute s", "state"], rows)
    ds = stage_dir(run_dir, "write")
    if (ds / "dataset.json").is_file():
        from anchordp3.dataset.reader import open_dataset

        d = open_dataset(ds)
        out += f"\n\ndataset: {ds} ({len(d)} samples, {len(d.episodes())} episodes, tasks: {', '.join(d.tasks)})"
        d.close()
    return out


def dataset_content_hash(run_dir: Path) -> str:
    """sha256 over the dataset's files (names and bytes), leaving out the write stage's own
    bookkeeping (its manifest, in either format, with SQLite's side files) and leftovers of
    interrupted writes (dot-files)."""
    import hashlib

    from anchordp3.dataset.files import file_sha256, tree_files

    root = stage_dir(run_dir, "write")
    h = hashlib.sha256()
    for rel in tree_files(root):
        if rel.startswith(STORE_FILES) or any(part.startswith(".") for part in rel.split("/")):
            continue
        h.update(rel.encode() + b"\0" + file_sha256(root / rel).encode())
    return h.hexdigest()
