"""Stops what a local Ray leaves behind when the process that started it dies without shutting it
down (SIGKILL, out of memory): its dashboard and runtime-env agents otherwise outlive it by a
minute or more.

``watch_local_ray(session_dir)`` starts, beside the driver, a small process in a session of its
own that waits for the driver to die and then ends every process holding a file open in the
Ray session's folder (Ray's own processes log there), first politely, then by force. When the
driver shuts Ray down itself, nothing is left to end and the watcher just exits.

    python -m anchordp3.pipeline.reaper DRIVER_PID SESSION_DIR
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

POLL_S = 0.5   # how often the watcher looks whether the driver is alive
GRACE_S = 3.0  # after the driver died: Ray's own shutdown first, then SIGTERM, then this long before SIGKILL


def watch_local_ray(session_dir: str) -> subprocess.Popen:
    """Start the watcher of this process's local Ray (``session_dir``: the folder of its session)."""
    return subprocess.Popen([sys.executable, "-m", __name__, str(os.getpid()), session_dir], start_new_session=True,
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1][0] != "Z"
    except (OSError, IndexError):
        return False


def holders(folder: str) -> list[int]:
    """The processes (other than this one) with a file open under ``folder``."""
    prefix, found = folder.rstrip("/") + "/", []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if any(os.readlink(fd).startswith(prefix) for fd in (entry / "fd").iterdir()):
                found.append(int(entry.name))
        except OSError:  # gone meanwhile, or not ours to read
            continue
    return found


def reap(folder: str) -> int:
    """End every process holding a file under ``folder``: SIGTERM, then SIGKILL for those left
    after ``GRACE_S``. Returns how many there were."""
    pids = holders(folder)
    found = len(pids)
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + GRACE_S
        while any(alive(p) for p in pids) and time.monotonic() < deadline:
            time.sleep(0.1)
        pids = [p for p in pids if alive(p)]
        if not pids:
            break
    return found


def main(driver_pid: int, session_dir: str) -> None:
    while alive(driver_pid):
        time.sleep(POLL_S)
    time.sleep(GRACE_S)  # a driver that exited normally has shut Ray down already
    reap(session_dir)


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2])
