"""verify: intact datasets pass; corrupt or missing shards and tables are reported by path."""

from __future__ import annotations

import shutil

import pytest

from anchordp3.dataset.verify import verify_dataset


def test_intact_dataset_verifies(built):
    rep = verify_dataset(built[0])
    assert rep.ok and rep.checked == len(built[1].shards) + 2


def test_corrupt_and_missing_shards_are_reported_by_path(built, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(built[0], out)
    f = out / "shards" / "00002.zarr" / "state" / "c" / "0" / "0"
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0x01
    f.write_bytes(bytes(data))
    shutil.rmtree(out / "shards" / "00003.zarr")
    (out / "instructions.parquet").unlink()
    rep = verify_dataset(out)
    got = {(p.kind, p.path) for p in rep.problems}
    assert got == {
        ("corrupt", str(out / "shards" / "00002.zarr")),
        ("missing", str(out / "shards" / "00003.zarr")),
        ("missing", str(out / "instructions.parquet")),
    }
    assert all("\n" not in p.line() for p in rep.problems)


def test_verify_of_a_foreign_folder_names_it(tmp_path):
    with pytest.raises(ValueError, match=str(tmp_path)):
        verify_dataset(tmp_path)


def test_finalize_refuses_a_shard_changed_after_its_record(built, cfg, tmp_path):
    from anchordp3.stages.write import finalize
    out = tmp_path / "copy"
    shutil.copytree(built[0], out)
    (out / "shards" / "00001.zarr" / "zarr.json").write_text("{}")
    with pytest.raises(ValueError, match="00001.zarr: shard content differs"):
        finalize(out, built[2], cfg)
    assert not (out / "dataset.json").exists()
