"""Reader: random access returns the right sample; bad paths give one-line errors naming them."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from dataset_helpers import fake_features, instruction

from anchordp3.dataset.chunks import ArrayReader
from anchordp3.dataset.reader import open_dataset


def test_random_access_returns_the_right_sample(built):
    out, info, _, _ = built
    ds = open_dataset(out)
    assert len(ds) == info.counts.samples and ds.tasks == info.tasks
    rng = np.random.default_rng(0)
    for i in rng.permutation(len(ds)):
        s = ds[int(i)]
        ep = next(e for e in ds.episodes() if e.start <= i < e.stop)
        f = fake_features(ep.task, ep.seed)
        j = int(i) - ep.start
        assert (s["episode_index"], s["task"], s["seed"]) == (ep.episode_index, ep.task, ep.seed)
        assert s["timestep"] == f["t"][j] and s["kind"] == f["kind"][j]
        assert s["task_id"] == info.tasks.index(ep.task) and s["instruction"] == instruction(ep.task, ep.seed)
        for k in ("points", "labels", "state", "anchors"):
            assert s[k].dtype == f[k].dtype and np.array_equal(s[k], f[k][j]), k
    assert ds[-1]["index"] == len(ds) - 1
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_dropped_episode_is_absent_and_tasks_filter(built):
    out, _, records, _ = built
    ds = open_dataset(out)
    assert ("place_bell", 5) not in {(e.task, e.seed) for e in ds.episodes()}
    assert any("place_bell/000005" in r.dropped for r in records)
    stack = ds.indices(tasks=["stack_blocks_three"])
    assert {ds[int(i)]["task"] for i in stack} == {"stack_blocks_three"}
    with pytest.raises(ValueError, match="unknown"):
        ds.indices(tasks=["nope"])


def test_fast_path_matches_zarr_for_other_codecs(features_dir, tmp_path):
    from dataset_helpers import build

    from anchordp3.schemas.dataset import WriteConfig
    for codec, level in (("blosc-lz4", 5), ("gzip", 1), ("none", 0)):
        cfg = WriteConfig(episodes_per_shard=4, inner_chunk=3, codec=codec, level=level)
        out = tmp_path / codec
        _, records, _ = build(features_dir, out, cfg)
        import zarr
        path = out / records[0].path / "points"
        r, z = ArrayReader(path), zarr.open_array(path, mode="r")
        assert r._fast
        for i in range(z.shape[0]):
            assert np.array_equal(r.sample(i), z[i])
        assert np.array_equal(r.read_all(), z[...])


def test_reader_pickles_and_keeps_working(built):
    ds = open_dataset(built[0])
    a = ds[3]
    ds2 = pickle.loads(pickle.dumps(ds))
    assert np.array_equal(ds2[3]["points"], a["points"])


def test_foreign_or_corrupt_paths_give_one_line_errors(built, tmp_path):
    with pytest.raises(ValueError, match="not an anchordp3 dataset") as e:
        open_dataset(tmp_path)
    assert str(tmp_path) in str(e.value) and "\n" not in str(e.value)
    (tmp_path / "dataset.json").write_text("{not json")
    with pytest.raises(ValueError, match="dataset.json: not a valid") as e:
        open_dataset(tmp_path)
    assert "\n" not in str(e.value)


def test_corrupt_shard_read_names_the_file(built, tmp_path):
    import shutil
    out = tmp_path / "copy"
    shutil.copytree(built[0], out)
    target = out / "shards" / "00001.zarr" / "points" / "c" / "0" / "0" / "0"
    data = bytearray(target.read_bytes())
    data[-10] ^= 0xFF  # inside the shard index
    target.write_bytes(bytes(data))
    ds = open_dataset(out)
    first = ds.info.shards[1].start
    with pytest.raises(ValueError, match="00001.zarr/points/c/0/0/0"):
        ds[first]


def test_empty_shard_in_the_middle_is_skipped(features_dir, tmp_path):
    from dataset_helpers import build

    from anchordp3.schemas.dataset import ShardRecord, WriteConfig
    cfg = WriteConfig(episodes_per_shard=2, validation_fraction=0.0)
    failed = [("place_bell", 2), ("place_bell", 5)]  # the whole of shard 1
    info, records, _ = build(features_dir, tmp_path, cfg, failed=failed)
    assert records[1].samples == 0 and info.shards[1].start == info.shards[2].start
    assert ShardRecord.model_validate_json(records[1].model_dump_json()) == records[1]
    ds = open_dataset(tmp_path)
    for e in ds.episodes():
        f = fake_features(e.task, e.seed)
        for j in range(e.frames):
            s = ds[e.start + j]
            assert (s["seed"], s["timestep"]) == (e.seed, f["t"][j])
            assert np.array_equal(s["points"], f["points"][j])


def test_a_dataset_of_the_earlier_schema_with_0_1_labels_still_opens_and_a_later_one_is_refused(built, tmp_path):
    import json
    import shutil

    from anchordp3.schemas.dataset import INFO_FILE, SCHEMA_VERSION

    root, *_ = built
    assert json.loads((root / INFO_FILE).read_text())["schema_version"] == SCHEMA_VERSION == 2
    for version, opens in ((1, True), (3, False)):
        copy = tmp_path / f"v{version}"
        shutil.copytree(root, copy)
        info = json.loads((copy / INFO_FILE).read_text())
        (copy / INFO_FILE).write_text(json.dumps({**info, "schema_version": version}))
        if opens:
            assert len(open_dataset(copy)) == len(open_dataset(root))
        else:
            with pytest.raises(ValueError, match="schema version 3, this code reads \\[1, 2\\]"):
                open_dataset(copy)
