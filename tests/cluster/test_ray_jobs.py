"""Ray Jobs for real: ``ray start --head`` with its dashboard on 127.0.0.1 (the Jobs API lives
there; it needs ``ray[default]``), then ``examples/ray_job_submit.sh`` submits the tiny config.
The job is stopped mid-run (its driver killed), submitted again it resumes to the local run's
bytes, and a third submission redoes nothing.

Marked ``cluster``: ``pytest -m cluster``."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import pytest

from anchordp3.pipeline.report import dataset_content_hash
from anchordp3.pipeline.store import read_manifest
from anchordp3.pipeline.work import DATA_STAGES, stage_dir
from tests.cluster.helpers import BIN, LOOPBACK_ENV, REPO, free_port, kill_pids, own_token, pids_using, records_so_far, short_tmp

pytestmark = pytest.mark.cluster


@pytest.fixture(scope="module")
def head():
    """A one-node Ray cluster (3 logical CPUs) with its dashboard, every port on 127.0.0.1, in a
    folder of its own; yields the dashboard's address. Stopped by its processes' ids (``ray stop``
    would stop every Ray on the machine)."""
    d = short_tmp("adp3-jobs-")
    env = {**LOOPBACK_ENV, **own_token(d), "PATH": f"{BIN}:{os.environ['PATH']}"}
    dash = free_port()
    cmd = [str(BIN / "ray"), "start", "--head", "--node-ip-address=127.0.0.1", f"--port={free_port()}",
           "--include-dashboard=true", "--dashboard-host=127.0.0.1", f"--dashboard-port={dash}",
           f"--dashboard-agent-listen-port={free_port()}", "--num-cpus=3", f"--temp-dir={d}/ray", "--disable-usage-stats"]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    try:
        assert res.returncode == 0, res.stderr[-3000:]
        yield f"http://127.0.0.1:{dash}", env
    finally:
        kill_pids(pids_using(str(d)))
        shutil.rmtree(d, ignore_errors=True)


def _submit(head, name: str, config, run_dir) -> subprocess.Popen:
    address, env = head
    return subprocess.Popen(["bash", str(REPO / "examples" / "ray_job_submit.sh"), name, str(config)],
                            env={**env, "RAY_ADDRESS": address, "RUN_DIR": str(run_dir)},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)


STOP = """
import sys
from ray.job_submission import JobStatus, JobSubmissionClient
client = JobSubmissionClient(sys.argv[1])
running = [j.submission_id for j in client.list_jobs()
           if (j.submission_id or "").startswith(sys.argv[2]) and j.status == JobStatus.RUNNING]
assert len(running) == 1, running
client.stop_job(running[0])
"""


def _stop_running_job(head, name: str) -> None:
    """Stop the running job of ``name`` (its driver is killed), as ``ray job stop`` does; in a
    process with the head's environment (its token)."""
    address, env = head
    subprocess.run([sys.executable, "-c", STOP, address, f"anchordp3-{name}-"], env=env, check=True, timeout=120)


def test_a_job_stopped_mid_run_then_submitted_again_resumes_to_the_local_bytes(head, config_file, local_hash, tmp_path):
    run = tmp_path / "run"
    first = _submit(head, "jobs-tiny", config_file, run)
    deadline = time.monotonic() + 600
    while records_so_far(run) < 6 and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.5)
    assert first.poll() is None, f"the job ended before it could be stopped:\n{first.stdout.read()[-3000:]}"
    _stop_running_job(head, "jobs-tiny")
    first.wait(timeout=120)
    done_before = records_so_far(run)
    assert done_before >= 6 and not read_manifest(stage_dir(run, "write")).complete

    time.sleep(1.1)  # submission ids carry the second
    again = _submit(head, "jobs-tiny", config_file, run)
    out = again.communicate(timeout=1200)[0]
    assert again.returncode == 0 and "succeeded" in out, out[-3000:]
    print(f"stopped with {done_before} records; resumed: {dataset_content_hash(run)} (local run: {local_hash})")
    assert records_so_far(run) >= done_before and dataset_content_hash(run) == local_hash
    records = {s: read_manifest(stage_dir(run, s)).items for s in DATA_STAGES}

    time.sleep(1.1)
    third = _submit(head, "jobs-tiny", config_file, run)
    out = third.communicate(timeout=600)[0]
    assert third.returncode == 0 and "succeeded" in out, out[-3000:]
    assert {s: read_manifest(stage_dir(run, s)).items for s in DATA_STAGES} == records  # nothing redone
    assert dataset_content_hash(run) == local_hash
