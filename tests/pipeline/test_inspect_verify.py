"""`status`, `inspect` and `verify [--repair]` on one small real run (built once for the module).

The run has an injected fault that is retried (render of seed 1: 2 attempts) and one that is
recorded as failed (features of seed 1), so the tables have attempts and failure reasons to show.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest
import yaml
from typer.testing import CliRunner

from anchordp3.cli import app
from anchordp3.dataset.files import file_sha256, tree_files
from anchordp3.pipeline import codehash
from anchordp3.pipeline.inspect import failure_groups
from anchordp3.pipeline.report import dataset_content_hash
from anchordp3.pipeline.runner import RunOptions, run_pipeline
from anchordp3.pipeline.store import read_manifest
from anchordp3.pipeline.work import stage_dir
from anchordp3.schemas.manifest import ItemRecord, StageManifest
from anchordp3.pipeline.work import DATA_STAGES
from anchordp3.schemas.run import RunConfig

TINY = {
    "name": "tiny", "tasks": ["place_mouse"], "seeds": "0-1", "cameras": {"width": 64, "height": 48},
    "features": {"n_points": 256},
    "execution": {"max_attempts": 2, "pools": {s: {"workers": 1, "cpus": 0.4} for s in DATA_STAGES}},
}
FAULTS = "render:place_mouse/000001:1,features:place_mouse/000001:9"
cli = CliRunner()


@pytest.fixture(scope="module")
def run(ray_session, tmp_path_factory):
    """The module's run directory (tests that change it work on a copy)."""
    d = tmp_path_factory.mktemp("inspect") / "run"
    run_pipeline(RunConfig.model_validate(TINY), d, RunOptions(progress_interval=60, faults=FAULTS))
    return d


@pytest.fixture
def copy(run, tmp_path):
    """A private copy of the module's run."""
    dst = tmp_path / "run"
    shutil.copytree(run, dst)
    return dst


def rows(output: str) -> dict[str, list[str]]:
    """A text table's rows by first column."""
    return {cells[0]: cells for line in output.splitlines() if (cells := line.split())}


def one_error_line(res) -> str:
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: "), res.output
    return lines[0]


# ------------------------------------------------------------------------------- status / inspect
def test_status_has_a_line_per_stage_with_counts_and_freshness(run):
    res = cli.invoke(app, ["status", str(run)])
    assert res.exit_code == 0, res.output
    r = rows(res.output)
    assert r["rollout"][1:5] == ["2", "0", "2", "complete"]
    assert r["features"][1:5] == ["1", "1", "2", "complete"]
    assert r["write"][1:5] == ["2", "0", "2", "complete"]
    for s in DATA_STAGES:
        assert r[s][6] == read_manifest(stage_dir(run, s)).fingerprint.digest()
        assert r[s][7] == "current"


@pytest.mark.parametrize("command", ["status", "inspect"])
def test_reading_a_run_loads_neither_ray_nor_the_simulator_nor_torch(run, command):
    code = ("import sys; from anchordp3.cli import app\n"
            f"try:\n    app([{command!r}, {str(run)!r}])\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
            "heavy = sorted({'ray', 'sapien', 'torch'} & set(sys.modules))\n"
            "assert not heavy, heavy")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


def test_status_marks_stages_stale_when_config_yaml_changed(copy):
    cfg = yaml.safe_load((copy / "config.yaml").read_text())
    cfg["features"]["n_points"] = 128
    (copy / "config.yaml").write_text(yaml.safe_dump(cfg))
    r = rows(cli.invoke(app, ["status", str(copy)]).output)
    assert [r[s][7] for s in DATA_STAGES] == ["current", "current", "current", "STALE(config)", "STALE(upstream)"]


def test_a_code_change_is_named_by_status_refused_by_run_and_kept_when_asked(copy, tmp_path, monkeypatch):
    code = tmp_path / "code" / "anchordp3"
    shutil.copytree(codehash.ROOT, code, ignore=shutil.ignore_patterns("__pycache__", "assets", "pretrained"))
    features = code / "stages" / "features.py"
    features.write_text(features.read_text() + "\nEDITED = True\n")  # what a developer's edit does to the hash
    monkeypatch.setattr(codehash, "ROOT", code)
    r = rows(cli.invoke(app, ["status", str(copy)]).output)
    assert [r[s][7] for s in DATA_STAGES] == ["current", "current", "current", "STALE(code)", "STALE(upstream)"]
    before = {s: read_manifest(stage_dir(copy, s)).items for s in DATA_STAGES}
    line = one_error_line(cli.invoke(app, ["run", str(copy / "config.yaml"), "--run-dir", str(copy)]))
    assert "features (code), write (upstream features)" in line and "--keep-outputs" in line
    res = cli.invoke(app, ["run", str(copy / "config.yaml"), "--run-dir", str(copy), "--keep-outputs"])
    assert res.exit_code == 0, res.output
    r = rows(cli.invoke(app, ["status", str(copy)]).output)
    assert all(r[s][7] == "current" for s in DATA_STAGES)
    assert {s: read_manifest(stage_dir(copy, s)).items for s in DATA_STAGES} == before  # nothing redone


def test_inspect_without_stage_is_the_stage_table_and_json_parses(run):
    res = cli.invoke(app, ["inspect", str(run)])
    assert res.exit_code == 0, res.output
    assert "2 episodes" in res.output and all(s in rows(res.output) for s in DATA_STAGES)
    res = cli.invoke(app, ["inspect", str(run), "--json"])
    got = {s["stage"]: s for s in json.loads(res.output)}
    assert list(got) == list(DATA_STAGES)
    assert (got["features"]["done"], got["features"]["failed"], got["features"]["complete"]) == (1, 1, True)


def test_inspect_stage_shows_counts_fingerprint_slowest_failures_and_items(run):
    res = cli.invoke(app, ["inspect", str(run), "features"])
    assert res.exit_code == 0, res.output
    m = read_manifest(stage_dir(run, "features"))
    out = res.output
    assert m.fingerprint.digest() in out and "current" in out
    assert "slowest items:" in out and "failure reasons:" in out
    reasons = out.split("failure reasons:")[1]
    assert rows(reasons)["InjectedFault"][1] == "1"  # reason → count, with an example
    assert "place_mouse/000001" in reasons
    items = rows(out.split("items:")[-1])
    assert items["place_mouse/000000"][1] == "done" and items["place_mouse/000001"][1:3] == ["failed", "2"]


def test_inspect_stage_json_is_the_manifest(run):
    res = cli.invoke(app, ["inspect", str(run), "dataset", "--json"])  # the write stage by its folder name
    assert res.exit_code == 0, res.output
    assert StageManifest.model_validate_json(res.output) == read_manifest(stage_dir(run, "write"))


def test_inspect_item_gives_its_whole_record(run):
    res = cli.invoke(app, ["inspect", str(run), "render", "--item", "place_mouse/000001", "--json"])
    rec = ItemRecord.model_validate_json(res.output)
    assert rec == read_manifest(stage_dir(run, "render")).items["place_mouse/000001"] and rec.attempts == 2
    res = cli.invoke(app, ["inspect", str(run), "--item", "place_mouse/000001", "--json"])
    assert list(json.loads(res.output)) == ["rollout", "anchors", "render", "features"]
    res = cli.invoke(app, ["inspect", str(run), "features", "--item", "place_mouse/000001"])
    assert res.exit_code == 0 and "InjectedFault" in res.output and "attempts" in res.output


@pytest.mark.parametrize("args, named", [
    (["inspect", "{run}", "nosuchstage"], "nosuchstage"),
    (["inspect", "{run}", "render", "--item", "place_mouse/000099"], "place_mouse/000099"),
    (["inspect", "{run}", "--item", "shard/00042"], "shard/00042"),
    (["status", "{run}/nowhere"], "nowhere"),
    (["verify", "{run}/nowhere"], "nowhere"),
])
def test_unknown_stage_item_or_run_is_one_line_naming_it_with_exit_2(run, args, named):
    line = one_error_line(cli.invoke(app, [a.format(run=run) for a in args]))
    assert named in line


def test_failure_groups_count_by_reason_with_one_example():
    items = {f"t/{i:06d}": ItemRecord(item=f"t/{i:06d}", status="failed", reason=r, detail=f"d{i}")
             for i, r in enumerate(["IKError", "Timeout", "IKError", "IKError"])}
    items["t/000009"] = ItemRecord(item="t/000009", status="done")
    groups = failure_groups(items.values())
    assert groups == [("IKError", 3, "t/000000", "d0"), ("Timeout", 1, "t/000001", "d1")]


# ------------------------------------------------------------------------------- verify
def test_verify_a_sound_run_exits_0(run):
    res = cli.invoke(app, ["verify", str(run)])
    assert res.exit_code == 0, res.output
    assert "all good" in res.output


def test_verify_names_missing_outputs(copy):
    frames = stage_dir(copy, "render") / read_manifest(stage_dir(copy, "render")).items["place_mouse/000000"].output
    frames.unlink()
    (stage_dir(copy, "write") / "index.parquet").unlink()
    res = cli.invoke(app, ["verify", str(copy)])
    assert res.exit_code == 1
    assert f"missing: {frames}" in res.output and f"missing: {stage_dir(copy, 'write') / 'index.parquet'}" in res.output


def test_verify_names_corrupt_outputs_and_repair_redoes_exactly_them(copy):
    before_hash = dataset_content_hash(copy)
    manifests = {s: read_manifest(stage_dir(copy, s)) for s in DATA_STAGES}
    feat = stage_dir(copy, "features") / manifests["features"].items["place_mouse/000000"].output
    feat_sha = file_sha256(feat)
    shard = stage_dir(copy, "write") / manifests["write"].items["shard/00000"].output
    chunk = shard / next(f for f in tree_files(shard) if "/c/" in f)
    with open(feat, "ab") as f:
        f.write(b"rot")
    with open(chunk, "r+b") as f:
        f.write(b"\xff\xfe")

    res = cli.invoke(app, ["verify", str(copy)])
    assert res.exit_code == 1
    assert f"corrupt: {feat} " in res.output and f"corrupt: {shard} " in res.output

    res = cli.invoke(app, ["verify", str(copy), "--repair"])
    assert res.exit_code == 0, res.output
    assert res.output.rstrip().endswith("all good")
    assert dataset_content_hash(copy) == before_hash and file_sha256(feat) == feat_sha
    redone = {("features", "place_mouse/000000"), ("write", "shard/00000"), ("write", "dataset")}
    for s in DATA_STAGES:
        after = read_manifest(stage_dir(copy, s))
        assert after.complete
        for item, rec in manifests[s].items.items():
            if (s, item) in redone:
                assert after.items[item].checksum == rec.checksum
            else:
                assert after.items[item] == rec, (s, item)  # untouched: not redone
