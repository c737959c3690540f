"""Exports of a run's dataset: LeRobot (v3.0 layout) and DP3's zarr (format 2), read back with
pyarrow and zarr; streaming, atomic, deterministic, and one-line errors with exit code 2.
(``test_exports_interop.py`` loads them with the real LeRobot and zarr 2 readers.)"""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import zarr
from dataset_helpers import VIEWS, fake_frames, make_run
from PIL import Image
from typer.testing import CliRunner

from anchordp3.cli import app
from anchordp3.dataset.export_dp3 import DP3Writer
from anchordp3.dataset.export_lerobot import LeRobotWriter
from anchordp3.dataset.files import tree_checksum
from anchordp3.dataset.reader import open_dataset
from anchordp3.pipeline.exports import export_dp3, export_lerobot
from anchordp3.stages.files import save_npz
from anchordp3.stages.render import prune_frames

runner = CliRunner()
DEFAULT_COLUMNS = {"timestamp", "frame_index", "episode_index", "index", "task_index"}


@pytest.fixture(scope="module")
def run(tmp_path_factory, cfg) -> Path:
    return make_run(tmp_path_factory.mktemp("run"), cfg)


@pytest.fixture(scope="module")
def lerobot(run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("lr") / "lerobot"
    export_lerobot(run, out, stream=io.StringIO())
    return out


@pytest.fixture(scope="module")
def dp3(run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dp3") / "data.zarr"
    export_dp3(run, out, stream=io.StringIO())
    return out


def _data(root: Path):
    return pq.read_table(sorted((root / "data").glob("chunk-*/file-*.parquet"))).to_pydict()


def _episodes(root: Path):
    return pq.read_table(sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))).to_pydict()


def test_lerobot_export_has_the_v3_layout(run, lerobot):
    ds = open_dataset(run / "dataset")
    info = json.loads((lerobot / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 1
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet" and info["video_path"] is None
    assert (info["total_episodes"], info["total_frames"]) == (len(ds.episodes()), len(ds))
    feats = info["features"]
    assert DEFAULT_COLUMNS <= set(feats)
    assert feats["observation.state"]["shape"] == [32] and len(feats["observation.state"]["names"]) == 32
    assert feats["action"]["shape"] == [32] and feats["observation.points"]["shape"] == [ds.info.n_points, 11]
    assert {f"observation.images.{v}" for v in VIEWS} <= set(feats)
    assert feats["observation.images.head"] == {"dtype": "image", "shape": [12, 16, 3], "names": ["height", "width", "channels"]}
    assert "next anchor" in info["anchordp3"]["action"] and "keyframe" in info["anchordp3"]["time_axis"]

    data = _data(lerobot)
    assert set(data) == set(feats)
    assert data["index"] == list(range(len(ds)))
    assert data["timestamp"] == pytest.approx([i / info["fps"] for i in data["frame_index"]])

    tasks = pq.read_table(lerobot / "meta" / "tasks.parquet")
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["task"]
    assert tasks.column("task_index").to_pylist() == list(range(info["total_tasks"]))
    assert tasks.column("task").to_pylist() == sorted({e.instruction for e in ds.episodes()})


def test_lerobot_episodes_hold_the_samples_with_the_next_anchor_as_action(run, lerobot):
    ds = open_dataset(run / "dataset")
    data, eps = _data(lerobot), _episodes(lerobot)
    info = json.loads((lerobot / "meta" / "info.json").read_text())
    tasks = pq.read_table(lerobot / "meta" / "tasks.parquet").column("task").to_pylist()
    source = {e.episode_index: e for e in ds.episodes()}
    assert eps["episode_index"] == list(range(len(source)))
    splits = eps["anchordp3/split"]
    assert splits == sorted(splits, key=lambda s: s != "train")  # train first, then validation
    n_train = splits.count("train")
    assert info["splits"] == {"train": f"0:{n_train}", "validation": f"{n_train}:{len(splits)}"}
    for k, (lo, hi) in enumerate(zip(eps["dataset_from_index"], eps["dataset_to_index"])):
        e = source[eps["anchordp3/episode_index"][k]]
        assert (eps["anchordp3/task"][k], eps["anchordp3/seed"][k], hi - lo) == (e.task, e.seed, e.frames)
        assert eps["tasks"][k] == [e.instruction] and tasks[data["task_index"][lo]] == e.instruction
        src = ds.episode_arrays(e)
        assert data["episode_index"][lo:hi] == [k] * e.frames and data["frame_index"][lo:hi] == list(range(e.frames))
        np.testing.assert_array_equal(np.array(data["observation.state"][lo:hi], np.float32), src["state"])
        np.testing.assert_array_equal(np.array(data["action"][lo:hi], np.float32), src["anchors"][:, 0])
        np.testing.assert_array_equal(np.array(data["next_anchors"][lo:hi], np.float32), src["anchors"])
        np.testing.assert_array_equal(np.array(data["observation.points"][lo:hi], np.float32), src["points"])
        np.testing.assert_array_equal(data["control_step"][lo:hi], src["timestep"])
        rgb = fake_frames(e.task, e.seed)["rgb"]
        for v, view in enumerate(VIEWS):
            got = [np.asarray(Image.open(io.BytesIO(x["bytes"]))) for x in data[f"observation.images.{view}"][lo:hi]]
            np.testing.assert_array_equal(np.stack(got), rgb[:, v])


def test_lerobot_stats_describe_the_data(lerobot):
    stats = json.loads((lerobot / "meta" / "stats.json").read_text())
    data = _data(lerobot)
    action = np.array(data["action"], np.float64)
    s = stats["action"]
    assert s["count"] == [len(action)]
    np.testing.assert_allclose(s["mean"], action.mean(0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s["std"], action.std(0), rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(s["min"], action.min(0))
    assert {"q01", "q10", "q50", "q90", "q99"} <= set(s)
    assert np.array(stats["observation.images.head"]["mean"]).shape == (3, 1, 1)
    assert np.array(stats["observation.points"]["mean"]).shape == (11,)
    eps = _episodes(lerobot)
    assert sum(c[0] for c in eps["stats/action/count"]) == len(action)


def _copy(run: Path, dest: Path) -> Path:
    shutil.copytree(run, dest)
    return dest


def test_lerobot_export_without_kept_images_warns_and_has_no_image_features(run, tmp_path, caplog):
    pruned = _copy(run, tmp_path / "run")
    for f in (pruned / "render").rglob("*.npz"):
        prune_frames(f)  # what render.keep_frames: false leaves
    res = export_lerobot(pruned, tmp_path / "lr", stream=io.StringIO())
    assert res.cameras == [] and "no kept camera images" in caplog.text
    info = json.loads((tmp_path / "lr" / "meta" / "info.json").read_text())
    assert not [k for k in info["features"] if k.startswith("observation.images.")]


def test_dp3_export_is_zarr_format_2_in_dp3s_layout(run, dp3):
    ds = open_dataset(run / "dataset")
    meta = json.loads((dp3 / "data" / "point_cloud" / ".zarray").read_text())
    assert meta["zarr_format"] == 2 and meta["compressor"]["id"] == "blosc" and (dp3 / ".zgroup").is_file()
    root = zarr.open_group(str(dp3), mode="r")
    entries = ds.episodes()
    ends = root["meta"]["episode_ends"][:]
    assert ends.tolist() == np.cumsum([e.frames for e in entries]).tolist()
    T, N = len(ds), ds.info.n_points
    assert root["data"]["point_cloud"].shape == (T, N, 6)
    assert root["data"]["state"].shape == root["data"]["action"].shape == (T, 32)
    start = 0
    for e, end in zip(entries, ends):
        src = ds.episode_arrays(e)
        np.testing.assert_array_equal(root["data"]["point_cloud"][start:end], src["points"][..., :6])
        np.testing.assert_array_equal(root["data"]["action"][start:end], src["anchors"][:, 0])
        np.testing.assert_array_equal(root["data"]["state"][start:end], src["state"])
        start = int(end)
    assert root["meta"]["episode_validation"][:].tolist() == [e.split == "validation" for e in entries]


def test_exports_are_deterministic(run, lerobot, dp3, tmp_path):
    export_lerobot(run, tmp_path / "lr", stream=io.StringIO())
    export_dp3(run, tmp_path / "d.zarr", stream=io.StringIO())
    assert tree_checksum(tmp_path / "lr") == tree_checksum(lerobot)
    assert tree_checksum(tmp_path / "d.zarr") == tree_checksum(dp3)


def test_lerobot_export_writes_each_episode_as_it_is_read(lerobot):
    # streaming: one parquet row group per episode, written before the next episode is read
    files = sorted((lerobot / "data").glob("chunk-*/file-*.parquet"))
    assert sum(pq.ParquetFile(f).num_row_groups for f in files) == json.loads((lerobot / "meta" / "info.json").read_text())["total_episodes"]


def test_dp3_export_holds_at_most_a_chunk_of_rows(run, tmp_path, monkeypatch):
    import anchordp3.dataset.export_dp3 as mod

    monkeypatch.setattr(mod, "CHUNK_FRAMES", 4)
    held = []
    add = DP3Writer.add

    def watch(self, entry, arrays):
        add(self, entry, arrays)
        held.append(max(sum(len(r) for r in rows.held) for rows in self.rows.values()))

    monkeypatch.setattr(DP3Writer, "add", watch)
    export_dp3(run, tmp_path / "d.zarr", stream=io.StringIO())
    assert held and max(held) < 4


@pytest.mark.parametrize("fmt, writer", [("lerobot", LeRobotWriter), ("dp3", DP3Writer)])
def test_an_interrupted_export_leaves_no_output(run, tmp_path, monkeypatch, fmt, writer):
    calls = []
    add = writer.add

    def crash_on_third(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        add(self, *args, **kwargs)

    monkeypatch.setattr(writer, "add", crash_on_third)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        (export_lerobot if fmt == "lerobot" else export_dp3)(run, out, stream=io.StringIO())
    assert list(tmp_path.iterdir()) == []


def test_cli_exports_print_a_progress_line_and_a_summary(run, tmp_path):
    res = runner.invoke(app, ["export", "dp3", str(run), str(tmp_path / "d.zarr")])
    assert res.exit_code == 0, res.output
    assert "items/s" in res.output and "ETA" in res.output
    assert f"wrote {tmp_path / 'd.zarr'} (dp3): 8 episodes" in res.output


def _one_line_error(args: list[str]) -> str:
    res = runner.invoke(app, args)
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    return lines[0]


@pytest.mark.parametrize("fmt", ["lerobot", "dp3"])
def test_cli_refuses_a_run_without_a_dataset_or_an_existing_output(run, tmp_path, fmt):
    empty = tmp_path / "empty_run"
    empty.mkdir()
    assert "no complete dataset" in _one_line_error(["export", fmt, str(empty), str(tmp_path / "o")])
    assert "no such run directory" in _one_line_error(["export", fmt, str(tmp_path / "nope"), str(tmp_path / "o")])
    (tmp_path / "o").mkdir()
    assert "already exists" in _one_line_error(["export", fmt, str(run), str(tmp_path / "o")])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty_run", "o"] and not any((tmp_path / "o").iterdir())


@pytest.mark.parametrize("fmt", ["lerobot", "dp3"])
def test_cli_refuses_a_corrupt_or_foreign_dataset(run, tmp_path, fmt):
    corrupt = _copy(run, tmp_path / "a")
    chunk = sorted(p for p in (corrupt / "dataset" / "shards").rglob("*") if p.is_file() and "/c/" in p.as_posix())[0]
    chunk.write_bytes(chunk.read_bytes()[:-1] + b"\0")
    line = _one_line_error(["export", fmt, str(corrupt), str(tmp_path / "o1")])
    assert "corrupt" in line and "shards/" in line

    foreign = _copy(run, tmp_path / "b")
    (foreign / "dataset" / "dataset.json").write_text('{"name": "some other dataset"}')
    assert "dataset.json: not a valid dataset description" in _one_line_error(["export", fmt, str(foreign), str(tmp_path / "o2")])
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()


def test_cli_no_images_leaves_the_cameras_out(run, tmp_path):
    res = runner.invoke(app, ["export", "lerobot", str(run), str(tmp_path / "lr"), "--no-images"])
    assert res.exit_code == 0, res.output
    assert "no images" in res.output
    info = json.loads((tmp_path / "lr" / "meta" / "info.json").read_text())
    assert not [k for k in info["features"] if k.startswith("observation.images.")]


def test_rendered_frames_that_are_not_the_datasets_samples_are_refused(run, tmp_path):
    other = _copy(run, tmp_path / "run")
    f = sorted((other / "render").rglob("*.npz"))[0]
    with np.load(f) as z:
        frames = {k: z[k] for k in z.files}
    frames["rgb"] = np.concatenate([frames["rgb"], frames["rgb"][:1]])  # one frame more than the dataset has
    save_npz(f, frames)
    line = _one_line_error(["export", "lerobot", str(other), str(tmp_path / "lr")])
    assert f.name in line and "rendered again" in line
    assert not (tmp_path / "lr").exists()
