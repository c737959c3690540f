"""Writing shards: exact round trip, deterministic bytes, atomic rename, failed and bad inputs."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import zarr
from dataset_helpers import EPISODES, N_POINTS, build, fake_features, instruction

from anchordp3.dataset import shard as shard_mod
from anchordp3.dataset.files import tree_files
from anchordp3.schemas.dataset import LAYOUT, WriteConfig
from anchordp3.stages.files import save_npz
from anchordp3.stages.files import features_file
from anchordp3.stages.write import plan_tasks, shard_plan, write_shard


def folder_hashes(root: Path) -> dict[str, str]:
    return {rel: hashlib.sha256((root / rel).read_bytes()).hexdigest() for rel in tree_files(root)}


def test_every_array_round_trips_exactly(built):
    out, info, records, _ = built
    for rec in records:
        g = zarr.open_group(out / rec.path, mode="r")
        assert set(g.array_keys()) == {s.name for s in LAYOUT}
        for span in rec.episodes:
            f = fake_features(span.task, span.seed)
            sl = slice(span.start, span.stop)
            for name in ("points", "labels", "state", "anchors", "kind"):
                got = g[name][sl]
                assert got.dtype == f[name].dtype and np.array_equal(got, f[name]), name
            assert np.array_equal(g["timestep"][sl], f["t"]) and g["timestep"].dtype == np.int32
            assert (g["episode_index"][sl] == span.episode_index).all()
            assert (g["task_id"][sl] == info.tasks.index(span.task)).all() and g["task_id"].dtype == np.int16
            texts = g.attrs["anchordp3"]["instructions"]
            assert {texts[i] for i in g["instruction_index"][sl]} == {instruction(span.task, span.seed)}


def test_arrays_use_zarr_sharding_with_small_inner_chunks(built, cfg):
    out, _, records, _ = built
    a = zarr.open_array(out / records[0].path / "points", mode="r")
    assert a.metadata.zarr_format == 3
    assert a.chunks == (cfg.inner_chunk, N_POINTS, 11) and a.shards[0] >= a.shape[0]
    assert [p for p in tree_files(out / records[0].path / "points") if p.startswith("c/")] == ["c/0/0/0"]


def test_two_writes_and_any_shard_order_give_identical_bytes(features_dir, cfg, built, tmp_path):
    first = built[0]
    info2, _, plan = build(features_dir, tmp_path / "a", cfg, failed=[("place_bell", 5)])
    info3, _, _ = build(features_dir, tmp_path / "b", cfg, failed=[("place_bell", 5)],
                        order=list(reversed(range(len(plan)))))
    h1 = folder_hashes(first)
    assert h1 == folder_hashes(tmp_path / "a") == folder_hashes(tmp_path / "b")
    assert info2.fingerprint == info3.fingerprint == built[1].fingerprint


def test_plan_depends_on_the_set_of_episodes_only():
    cfg = WriteConfig(episodes_per_shard=3)
    a = shard_plan(EPISODES, cfg)
    b = shard_plan(list(reversed(EPISODES)), cfg)
    assert a == b and [len(s) for s in a] == [3, 3, 3]
    flat = [m for s in a for m in s]
    assert [(m.task, m.seed) for m in flat] == sorted(EPISODES)
    assert [m.episode_index for m in flat] == list(range(len(EPISODES)))
    with pytest.raises(ValueError, match="listed twice"):
        shard_plan(EPISODES + [EPISODES[0]], cfg)


def test_crash_mid_write_leaves_no_shard_under_final_name(features_dir, cfg, tmp_path, monkeypatch):
    plan = shard_plan(EPISODES, cfg)
    real = shard_mod._write_array
    calls = []

    def flaky(group, spec, data, c):
        calls.append(spec.name)
        if len(calls) == 3:
            raise RuntimeError("simulated crash")
        real(group, spec, data, c)

    monkeypatch.setattr(shard_mod, "_write_array", flaky)
    with pytest.raises(RuntimeError, match="simulated crash"):
        write_shard(0, plan[0], features_dir, tmp_path, cfg)
    assert not (tmp_path / "shards" / "00000.zarr").exists()
    assert list((tmp_path / "shards").iterdir()) == []  # temporary folder cleaned up too

    # a crash while re-writing an existing shard keeps the old complete one
    monkeypatch.setattr(shard_mod, "_write_array", real)
    rec = write_shard(0, plan[0], features_dir, tmp_path, cfg)
    before = folder_hashes(tmp_path / rec.path)
    calls.clear()
    monkeypatch.setattr(shard_mod, "_write_array", flaky)
    with pytest.raises(RuntimeError):
        write_shard(0, plan[0], features_dir, tmp_path, cfg)
    assert folder_hashes(tmp_path / rec.path) == before


def test_stale_temporary_folder_of_a_killed_writer_is_removed(features_dir, cfg, tmp_path):
    plan = shard_plan(EPISODES, cfg)
    stale = tmp_path / "shards" / ".00000.zarr.tmp-99999"
    (stale / "points").mkdir(parents=True)
    write_shard(0, plan[0], features_dir, tmp_path, cfg)
    assert sorted(p.name for p in (tmp_path / "shards").iterdir()) == ["00000.zarr"]


def test_failed_members_are_dropped_and_all_failed_gives_an_empty_shard(features_dir, cfg, tmp_path):
    plan = shard_plan(EPISODES, cfg)
    members = plan[0]
    rec = write_shard(0, members, features_dir, tmp_path, cfg, failed=[(m.task, m.seed) for m in members])
    assert rec.samples == 0 and rec.episodes == [] and len(rec.dropped) == len(members)
    assert zarr.open_array(tmp_path / rec.path / "points", mode="r").shape[0] == 0


def test_missing_or_malformed_features_are_named(cfg, tmp_path):
    plan = shard_plan([("place_bell", 0), ("place_bell", 1)], cfg)
    with pytest.raises(FileNotFoundError, match="place_bell/000000.npz"):
        write_shard(0, plan[0], tmp_path, tmp_path / "out", cfg)
    bad = fake_features("place_bell", 0)
    bad["state"] = bad["state"].astype(np.float64)
    save_npz(tmp_path / features_file("place_bell", 0), bad)
    with pytest.raises(ValueError, match=r"000000\.npz: state must be float32"):
        write_shard(0, plan[0], tmp_path, tmp_path / "out", cfg)
    assert not (tmp_path / "out" / "shards" / "00000.zarr").exists()


def test_write_config_rejects_bad_values():
    with pytest.raises(ValueError, match="level"):
        WriteConfig(codec="blosc-zstd", level=12)
    with pytest.raises(ValueError):
        WriteConfig(bogus=1)
    assert plan_tasks(shard_plan(EPISODES, WriteConfig())) == ["place_bell", "stack_blocks_three"]


def test_role_labels_are_written_and_labels_that_are_no_role_are_refused_naming_the_file(tmp_path):
    from anchordp3.schemas.dataset import ROBOT_ROLE
    from anchordp3.stages.write import load_features

    f = fake_features("stack_blocks_three", 0)
    f["labels"][1, :4] = [1, 2, 3, ROBOT_ROLE]  # three blocks and the robot
    save_npz(tmp_path / "ok.npz", f)
    np.testing.assert_array_equal(load_features(tmp_path / "ok.npz")["labels"], f["labels"])
    f["labels"][1, 0] = 77
    save_npz(tmp_path / "bad.npz", f)
    with pytest.raises(ValueError, match=r"bad\.npz: labels must be roles"):
        load_features(tmp_path / "bad.npz")
