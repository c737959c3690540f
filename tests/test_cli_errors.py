"""Every bad input is one line: ``error: ...`` naming the path or argument, exit code 2, and
nothing created or half-written. One mechanism serves every command that writes: the
destinations each declares are checked before any work starts, and any OS error while writing
is reported by the path the user gave or the file that failed."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from anchordp3.cli import app
from anchordp3.pipeline.evaluation import selected_seeds
from anchordp3.schemas.evaluation import EvalOptions
from anchordp3.pipeline.reaper import holders
from anchordp3.schemas.run import RunConfig
from anchordp3.stages.files import atomic_write_bytes, check_destination, os_error_line, user_path

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[1]
DEMO = str(ROOT / "configs" / "demo.yaml")
RECIPE = str(ROOT / "configs" / "recipe.yaml")

# Every command that writes, with DEST where it writes (a folder, or a file for snapshot and show).
FOLDER_WRITERS = {
    "run": ["run", DEMO, "--run-dir", "DEST"],
    "stage": ["stage", "render", "--run-dir", "DEST"],
    "rollout": ["rollout", "place_mouse", "--seeds", "0", "--out", "DEST"],
    "demo": ["demo", "--run-dir", "DEST"],
    "train": ["train", "policy", "--run-dir", "DEST"],
    "eval": ["eval", "--models", "pretrained", "--episodes", "1", "--out", "DEST"],
    "experiment recipe": ["experiment", "recipe", RECIPE, "--out", "DEST"],
    "export pretrained": ["export", "pretrained", "RUN", "--dest", "DEST"],
    "export lerobot": ["export", "lerobot", "RUN", "DEST"],
    "export dp3": ["export", "dp3", "RUN", "DEST"],
    "verify --repair": ["verify", "DEST", "--repair"],
}
FILE_WRITERS = {
    "snapshot": ["snapshot", "place_mouse", "--out", "DEST"],
    "show": ["show", "RUN", "--out", "DEST"],
}


def invoke(args: list[str], dest: Path, run: Path) -> list[str]:
    """Run the command with DEST and RUN filled in; its non-empty output lines (exit code 2 asserted)."""
    args = [str(dest) if a == "DEST" else str(run) if a == "RUN" else a for a in args]
    res = runner.invoke(app, args)
    assert res.exit_code == 2, (args, res.output, res.exception)
    return [line for line in res.output.splitlines() if line.strip()]


def one_line_naming(lines: list[str], *names: str) -> None:
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    assert all(n in lines[0] for n in names), (lines, names)


def tree(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.mark.parametrize("command", list(FOLDER_WRITERS))
def test_a_folder_destination_that_is_a_file_is_one_line_naming_it(tmp_path, command):
    dest = tmp_path / "a_file"
    dest.write_text("keep me")
    before = tree(tmp_path)
    one_line_naming(invoke(FOLDER_WRITERS[command], dest, tmp_path / "run"), str(dest), "not a directory")
    assert dest.read_text() == "keep me" and tree(tmp_path) == before


@pytest.mark.parametrize("command", list(FOLDER_WRITERS) + list(FILE_WRITERS))
def test_a_destination_under_a_file_is_one_line_and_creates_nothing(tmp_path, command):
    (tmp_path / "a_file").write_text("")
    dest = tmp_path / "a_file" / "below" / "out.png"
    args = {**FOLDER_WRITERS, **FILE_WRITERS}[command]
    one_line_naming(invoke(args, dest, tmp_path / "run"), str(dest))
    assert tree(tmp_path) == ["a_file"]


@pytest.mark.parametrize("command", list(FILE_WRITERS))
def test_a_file_destination_that_is_a_folder_is_one_line_naming_it(tmp_path, command):
    one_line_naming(invoke(FILE_WRITERS[command], tmp_path, tmp_path / "run"), str(tmp_path), "directory")
    assert tree(tmp_path) == []


@pytest.fixture(scope="module")
def read_only(tmp_path_factory):
    """A read-only bind mount of an empty folder (needs the right to mount; skipped without it)."""
    src, mnt = tmp_path_factory.mktemp("ro-src"), tmp_path_factory.mktemp("ro")
    ok = subprocess.run(["mount", "--bind", str(src), str(mnt)], capture_output=True).returncode == 0
    if ok and subprocess.run(["mount", "-o", "remount,bind,ro", str(mnt)], capture_output=True).returncode != 0:
        subprocess.run(["umount", str(mnt)], capture_output=True)
        ok = False
    if not ok:
        pytest.skip("cannot make a read-only mount here")
    yield mnt
    subprocess.run(["umount", str(mnt)], capture_output=True)


@pytest.mark.parametrize("command", list(FOLDER_WRITERS) + list(FILE_WRITERS))
def test_a_read_only_destination_is_one_line_naming_it(read_only, tmp_path, command):
    dest = read_only / ("out.png" if command in FILE_WRITERS else "out")
    one_line_naming(invoke({**FOLDER_WRITERS, **FILE_WRITERS}[command], dest, tmp_path / "run"), str(dest), "read-only")


@pytest.mark.parametrize("args, name", [
    (["run", DEMO, "--run-dir", "DEST", "--workers", "0"], "--workers"),
    (["eval", "--models", "pretrained", "--out", "DEST", "--episodes", "0"], "--episodes"),
    (["eval", "--models", "pretrained", "--out", "DEST", "--ddim-steps", "0"], "--ddim-steps"),
    (["snapshot", "place_mouse", "--seed", "-5", "--out", "DEST"], "--seed"),
    (["run", DEMO], "--run-dir"),
    (["experiment", "recipe", RECIPE, "--out", "DEST", "--from-stage", "bogus"], "--from-stage"),
    (["no-such-command"], "no-such-command"),
])
def test_the_command_lines_own_argument_errors_are_one_line(tmp_path, args, name):
    one_line_naming(invoke(args, tmp_path / "dest", tmp_path / "run"), name)
    assert tree(tmp_path) == []


def test_misleading_messages_say_what_is_wrong(tmp_path):
    (tmp_path / "cfg").mkdir()
    one_line_naming(invoke(["config", "validate", str(tmp_path / "cfg")], tmp_path, tmp_path), "cfg", "a directory")
    one_line_naming(invoke(["stage", "bogus", "--run-dir", "DEST"], tmp_path / "run", tmp_path), "stage 'bogus'")
    (tmp_path / "run" / "render" / "frames").mkdir(parents=True)
    one_line_naming(invoke(["show", "RUN", "--episode", "7", "--out", "DEST"], tmp_path / "f.png", tmp_path / "run"),
                    "--episode", "TASK/SEED")


def test_a_refused_address_creates_no_run_directory(tmp_path):
    """In a process of its own, as from a shell: an address Ray cannot join is refused before the
    run directory exists."""
    res = subprocess.run([sys.executable, "-m", "anchordp3.cli", "run", DEMO, "--run-dir", str(tmp_path / "run"),
                          "--address", "notanaddress"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stderr
    one_line_naming([line for line in res.stderr.splitlines() if line.strip()], "--address", "notanaddress")
    assert tree(tmp_path) == []


@pytest.mark.parametrize("seeds", ["9-1", "x-3", "1,,2"])
def test_refused_evaluation_seeds_create_no_evaluation_folder(tmp_path, seeds):
    lines = invoke(["eval", "--models", "pretrained", "--seeds", seeds, "--out", "DEST"], tmp_path / "ev", tmp_path)
    one_line_naming(lines, "--seeds")
    assert tree(tmp_path) == []


def test_episodes_take_the_first_training_seeds_and_contradict_an_explicit_list():
    cfg = RunConfig(name="t", tasks=["place_mouse"], seeds="0-199")
    assert selected_seeds(cfg, EvalOptions(seeds="train", episodes=1)) == [0]
    assert len(selected_seeds(cfg, EvalOptions(seeds="train"))) == 200
    assert selected_seeds(cfg, EvalOptions(seeds="5,7")) == [5, 7]
    with pytest.raises(ValueError, match="--episodes"):
        selected_seeds(cfg, EvalOptions(seeds="5,7", episodes=3))
    assert len(selected_seeds(cfg, EvalOptions())) == 10


def test_verify_refuses_a_folder_where_nothing_ran(tmp_path):
    (tmp_path / "config.yaml").write_text(Path(DEMO).read_text())
    one_line_naming(invoke(["verify", "RUN"], tmp_path, tmp_path), str(tmp_path), "nothing to verify")


def test_os_errors_name_the_path_the_user_gave_not_a_temporary_one(tmp_path):
    assert user_path(tmp_path / ".out.zarr.tmp-123" / "data" / "x") == str(tmp_path / "out.zarr")
    assert user_path(tmp_path / "plain") == str(tmp_path / "plain")
    e = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / ".lr.tmp-9" / "meta.json"))
    assert os_error_line(e) == f"{tmp_path / 'lr'}: no space left on device"
    (tmp_path / "f").write_text("")
    with pytest.raises(OSError) as info:
        atomic_write_bytes(tmp_path / "f" / "x.npz", b"1")
    assert os_error_line(info.value).startswith(str(tmp_path / "f"))
    check_destination(tmp_path / "new" / "deeper", folder=True)  # fine, and creates nothing
    assert tree(tmp_path) == ["f"]


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MB tmpfs (needs the right to mount; skipped without it)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    yield mnt
    subprocess.run(["umount", str(mnt)], capture_output=True)


def test_a_full_disk_while_writing_is_one_line_naming_the_file_and_leaves_nothing(small_disk):
    (small_disk / "filler").write_bytes(b"\0" * (2 * 1024 * 1024 - 64 * 1024))
    target = small_disk / "out" / "frames.npz"
    with pytest.raises(OSError) as info:
        atomic_write_bytes(target, os.urandom(512 * 1024))
    assert os_error_line(info.value) == f"{target}: no space left on device"
    assert sorted(p.name for p in small_disk.rglob("*")) == ["filler", "out"]


def test_a_local_ray_is_gone_soon_after_its_driver_is_killed(tmp_path):
    """SIGKILL of a run's driver: the watcher it started ends what its local Ray left behind."""
    driver = subprocess.Popen([sys.executable, "-m", "anchordp3.cli", "-q", "run", DEMO, "--run-dir", str(tmp_path / "run")],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    session = None
    deadline = time.monotonic() + 120
    while session is None and time.monotonic() < deadline:
        time.sleep(0.5)
        for p in Path("/proc").iterdir():
            if p.name.isdigit():
                try:
                    args = (p / "cmdline").read_bytes().split(b"\0")
                except OSError:
                    continue
                if b"anchordp3.pipeline.reaper" in args and args[args.index(b"anchordp3.pipeline.reaper") + 1] == str(driver.pid).encode():
                    session = args[args.index(b"anchordp3.pipeline.reaper") + 2].decode()
    assert session is not None, "the run started no local Ray watcher"
    while not holders(session) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert holders(session), "the local Ray never started"
    driver.kill()
    driver.wait()
    deadline = time.monotonic() + 30
    while holders(session) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert holders(session) == []


def test_version_prints_the_packages_version():
    from anchordp3 import __version__

    res = runner.invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.strip() == f"anchordp3 {__version__}"
