"""The orchestrated data stages on a real Ray: same dataset bytes however the run was scheduled,
interrupted (SIGKILL) or retried; faults retried then recorded; one process per run directory."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import ray
import yaml

from anchordp3.pipeline.lock import RunLock
from anchordp3.pipeline.report import dataset_content_hash
from anchordp3.pipeline.runner import RunOptions, run_pipeline
from anchordp3.pipeline.store import StaleStageError, count_records, read_manifest
from anchordp3.pipeline.work import stage_dir
from anchordp3.schemas.records import ShardInfo
from anchordp3.schemas.run import RunConfig

TINY = {
    "name": "tiny", "tasks": ["place_mouse", "place_bell"], "seeds": "0-1", "preset": "randomized",
    "cameras": {"width": 64, "height": 48}, "features": {"n_points": 256},
    "anchors": {"dagger": {"fraction": 0.2}}, "write": {"episodes_per_shard": 2, "validation_fraction": 0.25},
    "execution": {"pools": {s: {"workers": 1, "cpus": 0.4} for s in ("rollout", "anchors", "render", "features", "write")}},
}


def tiny(**changes) -> RunConfig:
    return RunConfig.model_validate({**TINY, **changes})


@pytest.fixture(scope="module")
def reference(ray_session, tmp_path_factory):
    """An uninterrupted run with one worker per stage, and its dataset hash."""
    run = tmp_path_factory.mktemp("ref")
    run_pipeline(tiny(), run, RunOptions(progress_interval=60))
    return run, dataset_content_hash(run)


def test_uninterrupted_run_writes_a_complete_dataset_with_manifests(reference):
    run, _ = reference
    for s in ("rollout", "anchors", "render", "features", "write"):
        m = read_manifest(stage_dir(run, s))
        assert m.complete and m.counts.failed == 0, s
    assert read_manifest(stage_dir(run, "rollout")).counts.done == 4
    assert (stage_dir(run, "write") / "dataset.json").is_file()
    assert (run / "config.yaml").is_file()


def test_every_done_item_records_the_cpu_time_its_worker_spent(reference):
    run, _ = reference
    for s in ("rollout", "render", "features"):
        cpu = [r.cpu_seconds for r in read_manifest(stage_dir(run, s)).items.values()]
        assert cpu and all(c is not None and c > 0 for c in cpu), (s, cpu)


def test_two_workers_per_stage_give_the_same_dataset_bytes(reference, tmp_path):
    pools = {s: {"workers": 2, "cpus": 0.2} for s in ("rollout", "anchors", "render", "features", "write")}
    run_pipeline(tiny(execution={"pools": pools}), tmp_path, RunOptions(progress_interval=60))
    assert dataset_content_hash(tmp_path) == reference[1]


def test_rerunning_a_finished_run_redoes_nothing(reference):
    run, h = reference
    before = {s: read_manifest(stage_dir(run, s)).model_dump() for s in ("rollout", "write")}
    run_pipeline(tiny(), run, RunOptions(progress_interval=60))
    assert {s: read_manifest(stage_dir(run, s)).model_dump() for s in ("rollout", "write")} == before
    assert dataset_content_hash(run) == h


def test_a_run_of_fewer_seeds_counts_only_its_own_episodes_in_its_progress(reference, tmp_path, caplog):
    import shutil
    run = tmp_path / "run"
    shutil.copytree(reference[0], run)
    with caplog.at_level("INFO", logger="anchordp3.pipeline.runner"):
        run_pipeline(tiny(seeds="0"), run, RunOptions(progress_interval=0.01, from_stage="write"))
    lines = [r.getMessage() for r in caplog.records if "rollout:" in r.getMessage()]
    assert lines and all("rollout: 2/2 done" in line and "anchors: 2/2 done" in line for line in lines), lines[-1]


def _records(run: Path, stage: str) -> int:
    try:
        return count_records(stage_dir(run, stage))
    except ValueError:  # the file is being created
        return 0


@pytest.mark.parametrize("stage, records", [("rollout", 1), ("render", 1), ("features", 3)])
def test_sigkill_then_resume_gives_the_uninterrupted_dataset(reference, tmp_path, stage, records):
    cfg_path = tmp_path / "tiny.yaml"
    cfg_path.write_text(yaml.safe_dump(TINY))
    run = tmp_path / "run"
    address = ray.get_runtime_context().gcs_address
    proc = subprocess.Popen([sys.executable, "-m", "anchordp3.cli", "run", str(cfg_path), "--run-dir", str(run), "--address", address],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.time() + 240
        while _records(run, stage) < records and proc.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, "the run finished before it could be killed"
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert not (stage_dir(run, "write") / "dataset.json").exists()
    run_pipeline(tiny(), run, RunOptions(progress_interval=60))
    assert dataset_content_hash(run) == reference[1]
    for s in ("rollout", "anchors", "render", "features"):
        m = read_manifest(stage_dir(run, s))
        assert m.counts.done == m.counts.planned and m.counts.failed == 0


def test_injected_faults_are_retried_then_recorded_as_failed(ray_session, tmp_path):
    faults = "render:place_bell/000000:1,features:place_mouse/000001:5,rollout:place_bell/000001:9:crash"
    cfg = tiny(execution={**TINY["execution"], "max_attempts": 2, "max_failure_ratio": 1.0})
    run_pipeline(cfg, tmp_path, RunOptions(progress_interval=60, faults=faults))
    render = read_manifest(stage_dir(tmp_path, "render")).items["place_bell/000000"]
    assert render.status == "done" and render.attempts == 2  # failed once, then succeeded
    feats = read_manifest(stage_dir(tmp_path, "features")).items["place_mouse/000001"]
    assert feats.status == "failed" and feats.attempts == 2 and feats.reason == "InjectedFault"
    crashed = read_manifest(stage_dir(tmp_path, "rollout")).items["place_bell/000001"]
    assert crashed.status == "failed" and crashed.attempts == 2
    info = read_manifest(stage_dir(tmp_path, "write"))
    assert info.complete  # the dataset was still written, without the two failed episodes
    dropped = sorted(d for r in info.items.values() if r.item.startswith("shard/") for d in r.payload(ShardInfo).shard.dropped)
    assert dropped == ["place_bell/000001", "place_mouse/000001"]


def test_a_changed_config_is_refused_until_forced(reference, tmp_path):
    run_pipeline(tiny(tasks=["place_mouse"], seeds="0"), tmp_path, RunOptions(progress_interval=60))
    changed = tiny(tasks=["place_mouse"], seeds="0", features={"n_points": 128})
    with pytest.raises(StaleStageError, match=r"features \(config\), write \(upstream features\)"):
        run_pipeline(changed, tmp_path, RunOptions(progress_interval=60))
    rollout_before = read_manifest(stage_dir(tmp_path, "rollout")).model_dump()
    run_pipeline(changed, tmp_path, RunOptions(force=True, progress_interval=60))
    assert read_manifest(stage_dir(tmp_path, "rollout")).model_dump() == rollout_before  # upstream kept
    from anchordp3.dataset.reader import open_dataset

    assert open_dataset(stage_dir(tmp_path, "write"))[0]["points"].shape == (128, 11)


def test_a_second_process_on_the_same_run_directory_is_refused(tmp_path):
    with RunLock(tmp_path):
        res = subprocess.run([sys.executable, "-m", "anchordp3.cli", "run", "configs/demo.yaml", "--run-dir", str(tmp_path)],
                             capture_output=True, text=True, cwd=Path(__file__).resolve().parents[2])
    assert res.returncode == 2
    assert "in use by another process" in res.stderr and len(res.stderr.strip().splitlines()) == 1


def test_discarding_frames_keeps_the_dataset_and_verifies(reference, tmp_path):
    from anchordp3.pipeline.verify import verify_run
    from anchordp3.stages.render import load_frames

    run_pipeline(tiny(render={"keep_frames": False}), tmp_path, RunOptions(progress_interval=60))
    assert dataset_content_hash(tmp_path) == reference[1]
    frames = sorted((stage_dir(tmp_path, "render") / "frames").rglob("*.npz"))
    assert frames and all("rgb" not in load_frames(f) and "K" in load_frames(f) for f in frames)
    assert verify_run(tmp_path).ok
