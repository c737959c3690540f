"""The run directory's disk fills up mid-run (a small tmpfs): the run stops with one line naming
the path (exit 2), nothing half-written is recorded as done (``verify`` finds every done output
whole), and once space is freed the same command resumes to the local run's bytes.

Needs root to mount a tmpfs (skipped otherwise). Marked ``cluster``: ``pytest -m cluster``."""

from __future__ import annotations

import subprocess

import pytest

from anchordp3.pipeline.report import dataset_content_hash
from anchordp3.pipeline.store import count_records
from anchordp3.pipeline.work import DATA_STAGES, stage_dir
from tests.cluster.helpers import LOOPBACK_ENV, cli, records_so_far, short_tmp

pytestmark = pytest.mark.cluster

FULL_AT = "3m"  # the tiny run needs more than this at its peak (checked below), far less than FREED
FREED = "256m"


@pytest.fixture
def small_disk():
    """A tmpfs of ``FULL_AT``; unmounted at the end."""
    d = short_tmp("adp3-disk-")
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={FULL_AT}", "tmpfs", str(d)], capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {res.stderr.strip()}")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], check=False)
        d.rmdir()


def test_a_full_disk_stops_the_run_in_one_line_and_it_resumes_once_space_is_freed(small_disk, config_file, local_hash):
    run = small_disk / "run"
    res = subprocess.run(cli("-q", "run", str(config_file), "--run-dir", str(run)), capture_output=True, text=True, timeout=900, env=LOOPBACK_ENV)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2, res.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(small_disk) in lines[0], res.stderr[-3000:]
    assert "no space left on device" in lines[0]
    print(f"full: {lines[0]}")  # shown by `pytest -rA`: the closing note of a drill quotes it
    recorded = records_so_far(run)
    verify = subprocess.run(cli("verify", str(run)), capture_output=True, text=True, timeout=300)
    assert verify.returncode == 0, verify.stdout + verify.stderr  # every output recorded done is whole

    subprocess.run(["mount", "-o", f"remount,size={FREED}", str(small_disk)], check=True)
    again = subprocess.run(cli("-q", "run", str(config_file), "--run-dir", str(run)), capture_output=True, text=True, timeout=900, env=LOOPBACK_ENV)
    assert again.returncode == 0, again.stderr[-3000:]
    assert sum(count_records(stage_dir(run, s)) for s in DATA_STAGES) >= recorded
    print(f"resumed: {dataset_content_hash(run)} (local run: {local_hash}); {recorded} records before the resume")
    assert dataset_content_hash(run) == local_hash
    assert not [p for p in run.rglob(".*.tmp-*")]  # no leftovers of the interrupted writes
