"""A real multi-node Ray cluster on one machine: a head and two worker nodes, each its own raylet
and object store, all bound to 127.0.0.1. A run joins it with ``--address``, spreads its actors
over the nodes (each record names its node) and writes the same dataset bytes as a local run;
the node holding any stage's worker lost mid-run, the driver killed and started again, and 20
SIGKILLs of the driver at random instants each lose nothing and end with those bytes.

Marked ``cluster`` (not in the default suite): ``pytest -m cluster``."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest
import ray
from ray.cluster_utils import Cluster

from anchordp3.pipeline.report import dataset_content_hash
from anchordp3.pipeline.runner import RunOptions, run_pipeline
from anchordp3.pipeline.store import count_records, read_manifest
from anchordp3.pipeline.work import DATA_STAGES, stage_dir
from anchordp3.schemas.run import RunConfig
from tests.cluster.helpers import TINY, cli, records_so_far

pytestmark = pytest.mark.cluster

STAGES = ("rollout", "anchors", "render", "features", "write")
CFG = RunConfig.model_validate(TINY)
LOOPBACK = {"node_ip_address": "127.0.0.1"}


@pytest.fixture
def cluster():
    """A head (1 CPU) and two worker nodes (2 CPUs each), every process on 127.0.0.1."""
    if ray.is_initialized():
        ray.shutdown()
    c = Cluster(initialize_head=True, head_node_args={**LOOPBACK, "num_cpus": 1, "include_dashboard": False})
    workers = [c.add_node(**LOOPBACK, num_cpus=2) for _ in range(2)]
    c.wait_for_nodes()
    c.workers = workers
    yield c
    ray.shutdown()
    c.shutdown()


def _nodes(run: Path) -> dict[str, set[str]]:
    """Stage → the nodes that made its items (from the records)."""
    return {s: {r.node for r in read_manifest(stage_dir(run, s)).items.values() if r.node} for s in STAGES}


def test_a_run_spreads_over_the_nodes_and_writes_the_local_runs_bytes(cluster, local_hash, tmp_path):
    run_pipeline(CFG, tmp_path, RunOptions(address=cluster.address, progress_interval=60))
    nodes = _nodes(tmp_path)
    assert len(nodes["render"]) == 2 and len(set().union(*nodes.values())) == 3  # every node did some of the work
    node_ids = {n["NodeID"][:12] for n in ray.nodes() if n["Alive"]}
    assert set().union(*nodes.values()) <= node_ids
    assert all(n["NodeManagerAddress"] == "127.0.0.1" for n in ray.nodes())  # loopback only
    print(f"nodes {sorted(set().union(*nodes.values()))}; {dataset_content_hash(tmp_path)} (local run: {local_hash})")
    assert dataset_content_hash(tmp_path) == local_hash


@pytest.fixture
def three_workers():
    """A head that runs nothing (0 CPUs) and three 2-CPU worker nodes: every worker actor sits on a
    node that can be lost, and the pools (3 CPUs) still fit on the two left."""
    if ray.is_initialized():
        ray.shutdown()
    c = Cluster(initialize_head=True, head_node_args={**LOOPBACK, "num_cpus": 0, "include_dashboard": False})
    c.workers = [c.add_node(**LOOPBACK, num_cpus=2) for _ in range(3)]
    c.wait_for_nodes()
    yield c
    ray.shutdown()
    c.shutdown()


@pytest.mark.parametrize("stage", STAGES)
def test_losing_the_node_that_holds_a_stages_worker_loses_nothing(three_workers, local_hash, tmp_path, stage):
    """Once ``stage`` has made an item, the node whose worker made it is killed: the calls that
    worker had, and those sent to it after, fail over to a new worker within a bounded time, and
    the run ends with the local run's bytes."""
    cluster = three_workers
    by_node = {w.node_id[:12]: w for w in cluster.workers}
    killed: list[str] = []

    def kill_under_stage() -> None:
        folder = stage_dir(tmp_path, stage)
        while True:
            time.sleep(0.2)
            if not count_records(folder):
                continue
            nodes = [r.node for r in read_manifest(folder).items.values() if r.node in by_node]
            if nodes:
                cluster.remove_node(by_node[nodes[0]], allow_graceful=False)
                killed.append(nodes[0])
                return

    killer = threading.Thread(target=kill_under_stage, daemon=True)
    killer.start()
    t0 = time.perf_counter()
    run_pipeline(CFG, tmp_path, RunOptions(address=cluster.address, progress_interval=60))
    print(f"{stage}: node {killed} lost; the run took {time.perf_counter() - t0:.0f} s")
    assert killed, f"no {stage} item was made on a worker node"
    for s in DATA_STAGES:
        m = read_manifest(stage_dir(tmp_path, s))
        assert m.complete and m.counts.failed == 0, s
    assert dataset_content_hash(tmp_path) == local_hash


def _driver(config_file: Path, run: Path, address: str) -> subprocess.Popen:
    return subprocess.Popen(cli("-q", "run", str(config_file), "--run-dir", str(run), "--address", address),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)


def test_the_driver_killed_mid_run_then_started_again_resumes_to_the_same_bytes(cluster, config_file, local_hash, tmp_path):
    driver = _driver(config_file, tmp_path, cluster.address)
    while records_so_far(tmp_path) < 6 and driver.poll() is None:
        time.sleep(0.2)
    assert driver.poll() is None, "the run ended before it could be killed"
    os.killpg(driver.pid, signal.SIGKILL)
    driver.wait()
    done_before = records_so_far(tmp_path)
    again = _driver(config_file, tmp_path, cluster.address)
    assert again.wait(timeout=900) == 0, again.stderr.read().decode()[-2000:]
    assert records_so_far(tmp_path) >= done_before and dataset_content_hash(tmp_path) == local_hash


def test_twenty_sigkills_of_the_driver_at_random_instants_then_a_resume(cluster, config_file, local_hash, tmp_path):
    rng = random.Random(20)  # the instants are random, and the same on every run of the test
    kills, fresh = 0, 0
    run = tmp_path / "run0"
    while kills < 20:
        driver = _driver(config_file, run, cluster.address)
        time.sleep(rng.uniform(1.0, 12.0))
        if driver.poll() is not None:  # it finished before this kill: start over on a fresh run directory
            assert driver.returncode == 0, driver.stderr.read().decode()[-2000:]
            assert dataset_content_hash(run) == local_hash
            fresh += 1
            run = tmp_path / f"run{fresh}"
            continue
        os.killpg(driver.pid, signal.SIGKILL)
        driver.wait()
        kills += 1
    final = _driver(config_file, run, cluster.address)
    assert final.wait(timeout=900) == 0, final.stderr.read().decode()[-2000:]
    for s in DATA_STAGES:
        m = read_manifest(stage_dir(run, s))
        assert m.complete and m.counts.failed == 0, s
    assert dataset_content_hash(run) == local_hash
