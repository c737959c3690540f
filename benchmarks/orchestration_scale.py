"""The orchestration core at scale: the real runner and manifest store driving synthetic no-op stages.

    python benchmarks/orchestration_scale.py [--episodes 100000] [--records 1000000]

1. **Driver cost per item-stage.** ``pipeline.noop.noop_graph()`` (four episode stages that do no
   work, one every tenth episode stopped after the first, then groups of 16 and a finishing item)
   runs through ``run_pipeline`` on a local Ray over ``--episodes`` episodes. The driver's own CPU
   time (``time.process_time``: the loop, the records, their commits; not the actors' work),
   divided by the item-stages it recorded, is ``driver_ms_per_item``; ``peak_rss_mb`` is the
   driver's peak resident memory. Beside it, the same count of records written one commit each
   (how every record was made durable before batching) shows what the batched commits save.
2. **Status of a large manifest.** A stage manifest of ``--records`` records is written through
   ``ManifestStore``; then, in a fresh process, ``read_summary`` (what ``anchordp3 status`` reads)
   answers: ``status_s`` (imports included) and that process's own peak memory (``VmHWM``:
   ``ru_maxrss`` would carry the parent's peak over the fork). The reference beside it is the earlier
   format (one ``manifest.json`` with every record inline) of the same records, read by the same
   function, at a tenth of the size (a million would take minutes and gigabytes).

Last line: ``RESULT episodes=N driver_ms_per_item=X peak_rss_mb=Y status_s=Z status_rss_mb=M records=R``.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from anchordp3.pipeline.noop import noop_graph  # noqa: E402
from anchordp3 import logs  # noqa: E402
from anchordp3.pipeline.runner import RunOptions, ensure_ray, run_pipeline  # noqa: E402
from anchordp3.pipeline.store import MANIFEST, ManifestStore, read_summary  # noqa: E402
from anchordp3.schemas.manifest import Fingerprint, ItemRecord, StageManifest  # noqa: E402
from anchordp3.schemas.run import RunConfig  # noqa: E402
from anchordp3.viz.table import text_table  # noqa: E402

FP = Fingerprint(code_version="bench", code_hash="0" * 64, config_hash="0" * 64)
TASKS = ["place_mouse", "place_stapler", "place_bell", "stack_blocks_three"]
_STATUS_PROBE = """
import json, sys, time
t0 = time.perf_counter()
from anchordp3.pipeline.store import read_summary
m = read_summary(sys.argv[1])
seconds = time.perf_counter() - t0
hwm = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:"))  # this process's own peak, kB
print(json.dumps({"seconds": seconds, "done": m.counts.done, "rss_mb": hwm / 1024}))
"""


def driver_run(episodes: int, workdir: Path) -> dict:
    """Run the no-op graph over ``episodes`` episodes; the driver's CPU seconds and records."""
    per_task = -(-episodes // len(TASKS))
    cfg = RunConfig(name="scale", tasks=TASKS, seeds=f"0-{per_task - 1}", execution={"in_flight_per_worker": 64})
    graph = noop_graph()
    ensure_ray(None, cfg, graph)  # Ray's start is not the driver's per-item cost
    t_cpu, t_wall = time.process_time(), time.perf_counter()
    counts = run_pipeline(cfg, workdir / "run", RunOptions(progress_interval=30), graph=graph)
    cpu, wall = time.process_time() - t_cpu, time.perf_counter() - t_wall
    item_stages = sum(c["done"] + c["failed"] for c in counts.values())
    return {"episodes": per_task * len(TASKS), "item_stages": item_stages, "cpu_s": cpu, "wall_s": wall,
            "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def one_commit_each(n: int, workdir: Path) -> float:
    """Seconds per record when every record is its own transaction (the reference)."""
    store = ManifestStore(workdir / "unbatched", "noop0", FP)
    t0 = time.perf_counter()
    for i in range(n):
        store.record(ItemRecord(item=f"x/{i:07d}", status="done", output=None, seconds=0.001, info={"seed": i}))
    dt = time.perf_counter() - t0
    store.close()
    return dt / n


def big_manifest(records: int, d: Path) -> float:
    """Write a stage manifest of ``records`` records through the store; seconds taken."""
    store = ManifestStore(d, "rollout", FP)
    t0 = time.perf_counter()
    batch = []
    for i in range(records):
        batch.append(ItemRecord(item=f"place_mouse/{i:09d}", status="done", output=f"place_mouse/{i:09d}.npz",
                                checksum="%064x" % i, seconds=1.0, info={"seed": i, "kept": True}))
        if len(batch) == 10000:
            store.record_many(batch)
            batch = []
    store.record_many(batch)
    store.finish(records, True)
    store.close()
    return time.perf_counter() - t0


def legacy_manifest(records: int, d: Path) -> None:
    """The same records in the earlier format: one JSON file with every record inline."""
    d.mkdir(parents=True)
    items = {f"place_mouse/{i:09d}": ItemRecord(item=f"place_mouse/{i:09d}", status="done", output=f"place_mouse/{i:09d}.npz",
                                                checksum="%064x" % i, seconds=1.0, info={"seed": i, "kept": True})
             for i in range(records)}
    (d / MANIFEST).write_text(StageManifest(stage="rollout", fingerprint=FP, complete=True, items=items).model_dump_json())


def probe_status(d: Path) -> dict:
    """``read_summary(d)`` in a fresh interpreter: seconds (imports excluded) and peak memory."""
    out = subprocess.run([sys.executable, "-c", _STATUS_PROBE, str(d)], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=100_000, help="episodes of the no-op run")
    parser.add_argument("--records", type=int, default=1_000_000, help="records of the large manifest")
    args = parser.parse_args()
    logs.console()  # progress lines on stderr
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        run = driver_run(args.episodes, work)
        ms_batched = 1e3 * run["cpu_s"] / max(run["item_stages"], 1)
        ms_single = 1e3 * one_commit_each(2000, work)
        write_s = big_manifest(args.records, work / "big")
        ours = probe_status(work / "big")
        assert ours["done"] == args.records and read_summary(work / "big").counts.done == args.records
        legacy_n = max(args.records // 10, 1)
        legacy_manifest(legacy_n, work / "legacy")
        ref = probe_status(work / "legacy")
    print(text_table(["measure", "ours", "reference"], [
        ["driver CPU per item-stage (ms)", f"{ms_batched:.3f}", f"{ms_single:.3f} per record with one commit each (the record alone)"],
        ["no-op run: episodes / item-stages / wall s", f"{run['episodes']} / {run['item_stages']} / {run['wall_s']:.0f}", "-"],
        ["driver peak memory (MB)", f"{run['rss_mb']:.0f}", "-"],
        [f"status of {args.records} records (s)", f"{ours['seconds']:.3f}", f"{ref['seconds']:.2f} for {legacy_n} records as one JSON"],
        ["status process peak memory (MB)", f"{ours['rss_mb']:.0f}", f"{ref['rss_mb']:.0f} (JSON, {legacy_n} records)"],
        [f"writing {args.records} records (s)", f"{write_s:.1f}", "-"],
    ]))
    print(f"RESULT episodes={run['episodes']} driver_ms_per_item={ms_batched:.4f} peak_rss_mb={run['rss_mb']:.0f} "
          f"status_s={ours['seconds']:.4f} status_rss_mb={ours['rss_mb']:.0f} records={args.records}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
