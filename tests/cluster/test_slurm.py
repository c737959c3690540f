"""Slurm for real, on this one host: munged, slurmctld and slurmd in a network namespace of
their own that has only the loopback interface (Slurm 22.05 listens on every address; there,
every address is 127.0.0.1), then ``sbatch examples/slurm_batch.sh`` runs the tiny config on the
allocation (a Ray head on 127.0.0.1 started by ``srun``, the driver joining it) and writes the
same dataset bytes as a local run; submitted again, it resumes and redoes nothing.

The set-up installs Debian's ``slurm-wlm`` and ``munge`` when they are missing (as root, with
apt); without them, or without network namespaces, the test is skipped with the reason.
Marked ``cluster``: ``pytest -m cluster``."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from anchordp3.pipeline.report import dataset_content_hash
from anchordp3.pipeline.store import read_manifest
from anchordp3.pipeline.work import DATA_STAGES, stage_dir
from tests.cluster.helpers import REPO, kill_pids, own_token, pids_using, short_tmp

pytestmark = pytest.mark.cluster

NS_ADDRESS = "10.255.255.1"
SLURM_CONF = """\
ClusterName=anchordp3test
SlurmctldHost={host}(127.0.0.1)
SlurmctldPort=6817
SlurmdPort=6818
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={d}/munge.sock
StateSaveLocation={d}/state
SlurmdSpoolDir={d}/spool
SlurmctldPidFile={d}/slurmctld.pid
SlurmdPidFile={d}/slurmd.pid
SlurmctldLogFile={d}/slurmctld.log
SlurmdLogFile={d}/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SchedulerType=sched/builtin
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
MpiDefault=none
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
PropagateResourceLimits=NONE
NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
"""


def _install_slurm() -> str | None:
    """Install slurm-wlm and munge when missing; the reason they cannot be had, else None."""
    if all(shutil.which(b) for b in ("sbatch", "slurmctld", "slurmd", "munged")):
        return None
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        return "slurm-wlm and munge are not installed, and this is not root with apt-get to install them"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for cmd in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", "slurm-wlm", "munge"]):
        res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
        if res.returncode != 0:
            return f"`{' '.join(cmd)}` failed: {(res.stderr or res.stdout).strip().splitlines()[-1:]}"
    return None


class LocalSlurm:
    """munged, slurmctld and slurmd of a private folder, in a network namespace holding only
    loopback; ``run`` runs a command there with this Slurm's config."""

    def __init__(self, d: Path):
        self.d, self.procs = d, []
        self.token = own_token(d)  # the job's Ray: token authentication with a token of its own
        self.env = {**os.environ, "SLURM_CONF": str(d / "slurm.conf")}
        (d / "state").mkdir()
        (d / "spool").mkdir()
        host = subprocess.run(["hostname", "-s"], capture_output=True, text=True, check=True).stdout.strip()
        (d / "slurm.conf").write_text(SLURM_CONF.format(host=host, d=d, cpus=os.cpu_count() or 1))
        # Slurm finds no address to listen on where the only one is 127.0.0.1 (getaddrinfo with
        # AI_ADDRCONFIG): a second one on the namespace's loopback device, reachable from nowhere else
        self.ns = subprocess.Popen(["unshare", "--net", "sh", "-c",
                                    f"ip link set lo up && ip addr add {NS_ADDRESS}/32 dev lo && exec sleep infinity"],
                                   start_new_session=True)

    def cmd(self, *args: str) -> list[str]:
        return ["nsenter", "-t", str(self.ns.pid), "-n", *args]

    def start(self) -> None:
        time.sleep(0.5)  # the namespace's loopback comes up
        d = self.d
        daemons = [["munged", "-F", "-f", f"--socket={d}/munge.sock", f"--pid-file={d}/munged.pid",
                    f"--log-file={d}/munged.log", f"--seed-file={d}/munged.seed"],
                   ["slurmctld", "-D", "-f", f"{d}/slurm.conf"], ["slurmd", "-D", "-f", f"{d}/slurm.conf"]]
        for argv in daemons:
            self.procs.append(subprocess.Popen(self.cmd(*argv), env=self.env, stdout=open(d / f"{argv[0]}.out", "wb"),
                                               stderr=subprocess.STDOUT, start_new_session=True))
            time.sleep(1.0)
        for _ in range(60):
            if any(p.poll() is not None for p in self.procs):
                break  # a daemon died: its log says why
            state = self.run("sinfo", "-h", "-o", "%T", timeout=20).stdout.strip()
            if state == "idle":
                return
            time.sleep(1)
        raise RuntimeError(f"the Slurm node did not come up; see {d}/slurmctld.log, {d}/slurmd.log")

    def run(self, *args: str, timeout: float = 60, **kw) -> subprocess.CompletedProcess:
        return subprocess.run(self.cmd(*args), env={**self.env, **kw.pop("env", {})}, capture_output=True, text=True,
                              timeout=timeout, **kw)

    def stop(self) -> None:
        for p in reversed(self.procs):
            p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        kill_pids(pids_using(str(self.d)))  # job steps' leftovers (the Ray head) by their ids
        self.ns.kill()
        self.ns.wait()
        shutil.rmtree(self.d, ignore_errors=True)


@pytest.fixture(scope="module")
def slurm():
    reason = _install_slurm()
    if reason:
        pytest.skip(reason)
    if subprocess.run(["unshare", "--net", "true"], capture_output=True).returncode != 0:
        pytest.skip("no network namespace (unshare --net) for a loopback-only Slurm")
    s = LocalSlurm(short_tmp("adp3-slurm-"))
    try:
        s.start()
        yield s
    finally:
        s.stop()


def _batch(slurm: LocalSlurm, name: str, config: Path, run_dir: Path) -> tuple[int, str]:
    """``sbatch --wait examples/slurm_batch.sh`` on one node: its exit code and output."""
    out = slurm.d / f"{name}-{time.monotonic_ns()}.out"
    token = ",".join(f"{k}={v}" for k, v in slurm.token.items())
    export = (f"ALL,NAME={name},CONFIG={config},RUN_DIR={run_dir},REPO={REPO},HEAD_IP=127.0.0.1,RAY_CPUS=3,"
              f"RAY_TMPDIR={slurm.d}/ray,RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0,{token}")
    res = slurm.run("sbatch", "--wait", "--nodes=1", "--time=30", f"--output={out}", f"--export={export}",
                    str(REPO / "examples" / "slurm_batch.sh"), timeout=1500, cwd=str(slurm.d))
    text = out.read_text() if out.exists() else ""
    return res.returncode, f"{res.stdout}{res.stderr}\n{text}"


def test_sbatch_of_the_example_writes_the_local_runs_bytes_and_resumes(slurm, config_file, local_hash, tmp_path):
    run = tmp_path / "run"
    rc, out = _batch(slurm, "slurm-tiny", config_file, run)
    assert rc == 0, out[-3000:]
    assert "ray cluster: 1 nodes" in out
    assert dataset_content_hash(run) == local_hash
    before = {s: read_manifest(stage_dir(run, s)).items for s in DATA_STAGES}
    rc, out = _batch(slurm, "slurm-tiny", config_file, run)  # submitted again: resumes, nothing left to do
    assert rc == 0, out[-3000:]
    assert {s: read_manifest(stage_dir(run, s)).items for s in DATA_STAGES} == before
    assert dataset_content_hash(run) == local_hash
