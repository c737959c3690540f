"""What the cluster tests share: a tiny run config (3 logical CPUs of pools, so that every pool
still fits once a 2-CPU worker node is gone), helpers to start and stop processes by their own
ids, and a count of what a run has recorded."""

from __future__ import annotations

import os
import signal
import socket
import sys
import tempfile
from pathlib import Path

from anchordp3.pipeline import runner
from anchordp3.pipeline.store import count_records
from anchordp3.pipeline.work import DATA_STAGES, stage_dir

REPO = Path(__file__).resolve().parents[2]
# Every Ray these tests start keeps 127.0.0.1 (see ``runner.LOOPBACK_ENV``): this process's through
# ``runner.keep_ray_on_loopback`` (called in conftest), the processes it starts through
# ``LOOPBACK_ENV`` (this environment with Ray's switch set) given to them as their environment.
LOOPBACK_ENV = {**os.environ, **runner.LOOPBACK_ENV}

BIN = Path(sys.executable).parent  # the virtualenv's bin: anchordp3, ray
POOLS = {"rollout": {"workers": 2, "cpus": 0.4}, "anchors": {"workers": 1, "cpus": 0.2}, "render": {"workers": 2, "cpus": 0.5},
         "features": {"workers": 2, "cpus": 0.4}, "write": {"workers": 1, "cpus": 0.2}}
TINY = {
    "name": "cluster", "tasks": ["place_mouse", "place_bell"], "seeds": "0-3", "preset": "randomized",
    "cameras": {"width": 64, "height": 48}, "features": {"n_points": 256},
    "anchors": {"dagger": {"fraction": 0.2}}, "write": {"episodes_per_shard": 2, "validation_fraction": 0.25},
    "execution": {"pools": POOLS},
}


def own_token(d: Path) -> dict[str, str]:
    """Ray's token authentication (on by default since 2.5x) with a token of this test's own, in
    ``d``: the environment a head, its clients and its jobs share."""
    import secrets

    path = d / "auth_token"
    path.write_text(secrets.token_hex(32))
    path.chmod(0o600)
    return {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": str(path)}


def cli(*args: str) -> list[str]:
    """The ``anchordp3`` command line, in this interpreter."""
    return [sys.executable, "-m", "anchordp3.cli", *args]


def short_tmp(prefix: str) -> Path:
    """A fresh folder with a short path under /tmp (Ray's and munge's Unix sockets live in it,
    and a socket path is at most 107 bytes), searchable by every user."""
    d = Path(tempfile.mkdtemp(prefix=prefix, dir="/tmp"))
    d.chmod(0o755)
    return d


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def records_so_far(run: Path) -> int:
    """Items recorded so far over the data stages of ``run`` (read while a run may be writing)."""
    return sum(count_records(stage_dir(run, s)) for s in DATA_STAGES if stage_dir(run, s).exists())


def pids_using(marker: str) -> list[int]:
    """The processes whose command line names ``marker`` (a folder this test made), and their
    descendants (Ray's agents rename themselves): what daemons left behind, to stop by id."""
    found, parent = set(), {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit() and int(d.name) != os.getpid():
            try:
                if marker in (d / "cmdline").read_bytes().decode(errors="replace"):
                    found.add(int(d.name))
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    grew = True
    while grew:
        more = {pid for pid, pp in parent.items() if pp in found} - found
        found |= more
        grew = bool(more)
    return sorted(found)


def kill_pids(pids: list[int]) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
