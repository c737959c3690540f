"""The exports checked by the real readers: LeRobot's ``LeRobotDataset`` and DP3's zarr 2 reads.

Marked ``interop`` (skipped by default; ``pytest -m interop`` runs it). The readers run as
subprocesses of a separate virtualenv, never the project's ``.venv``: by default
``~/.cache/anchordp3-interop/venv`` (``ANCHORDP3_INTEROP_DIR`` moves it), created once and reused
(a marker file records what was installed; a changed list reinstalls). It installs:

- ``torch==2.14.1 torchvision==0.29.1`` first: on this project's machines pip takes both from
  local disk (a CUDA build, ~5.5 GB, no download; PyPI's torchvision does not import beside the
  2.13.0 CPU wheel the project pins). ``ANCHORDP3_INTEROP_TORCH`` overrides the two specifiers.
- ``lerobot==0.4.4 --no-deps``: its declared requirements pin ``torch<2.11`` and
  ``torchvision<0.26`` (gigabytes of CUDA packages to download) and bring robot, teleoperation,
  logging and video-encoding packages (pynput, pyserial, wandb, rerun-sdk, gymnasium, cmake,
  opencv, draccus, ...) that loading a dataset never imports.
- only what ``lerobot.datasets.lerobot_dataset`` imports, within lerobot's declared ranges:
  ``datasets`` (with pandas, pyarrow, fsspec), ``huggingface-hub``, ``accelerate``
  (``lerobot.utils.utils``), ``av`` (``lerobot.datasets.video_utils``), ``packaging``; and
  ``zarr<3`` for DP3's reader (DP3 pins zarr 2).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from dataset_helpers import VIEWS, fake_frames, make_run

from anchordp3.dataset.reader import open_dataset
from anchordp3.pipeline.exports import export_dp3, export_lerobot

pytestmark = pytest.mark.interop

HERE = Path(__file__).parent / "interop"
TORCH = os.environ.get("ANCHORDP3_INTEROP_TORCH", "torch==2.14.1 torchvision==0.29.1").split()
LEROBOT = "lerobot==0.4.4"
DEPENDENCIES = [
    "datasets>=4.0.0,<5.0.0", "huggingface-hub>=0.34.2,<0.36.0", "accelerate>=1.10.0,<2.0.0",
    "av>=15.0.0,<16.0.0", "packaging>=24.2,<26.0", "zarr<3",
]
INSTALL_TIMEOUT = 3600


def _pip(python: Path, *args: str) -> None:
    subprocess.run(["nice", str(python), "-m", "pip", "install", "--quiet", *args], check=True, timeout=INSTALL_TIMEOUT)


@pytest.fixture(scope="session")
def interop_python() -> Path:
    """The python of the interop virtualenv, created (or completed) when needed."""
    root = Path(os.environ.get("ANCHORDP3_INTEROP_DIR", Path.home() / ".cache" / "anchordp3-interop"))
    venv, marker = root / "venv", root / "venv.installed.json"
    python = venv / "bin" / "python"
    wanted = {"torch": TORCH, "lerobot": LEROBOT, "dependencies": DEPENDENCIES}
    if python.exists() and marker.is_file() and json.loads(marker.read_text()) == wanted:
        return python
    root.mkdir(parents=True, exist_ok=True)
    marker.unlink(missing_ok=True)
    if not python.exists():
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    _pip(python, *TORCH)
    _pip(python, "--no-deps", LEROBOT)
    _pip(python, *DEPENDENCIES)
    subprocess.run([str(python), "-c", "import lerobot.datasets.lerobot_dataset, zarr"], check=True, timeout=600)
    marker.write_text(json.dumps(wanted, indent=1) + "\n")
    return python


def _read(python: Path, script: str, path: Path, home: Path) -> dict:
    """Run a reader script of ``interop/`` in the interop venv, offline; its last stdout line as JSON."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "HF_HOME": str(home),
           "HF_LEROBOT_HOME": str(home / "lerobot"), "PYTHONPATH": ""}
    env.pop("VIRTUAL_ENV", None)
    res = subprocess.run(["nice", str(python), str(HERE / script), str(path)], capture_output=True, text=True,
                         env=env, timeout=900)
    assert res.returncode == 0, res.stderr[-4000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    from anchordp3.schemas.dataset import WriteConfig

    cfg = WriteConfig(episodes_per_shard=2, validation_fraction=0.25, split_seed=3, inner_chunk=2)
    return make_run(tmp_path_factory.mktemp("interop"), cfg)


def test_lerobot_loads_the_export_and_a_dataloader_iterates_it(interop_python, run, tmp_path):
    out = tmp_path / "lerobot"
    export_lerobot(run, out, stream=io.StringIO())
    got = _read(interop_python, "read_lerobot.py", out, tmp_path / "hf")

    ds = open_dataset(run / "dataset")
    entries = sorted(ds.episodes(), key=lambda e: (e.split != "train", e.episode_index))
    assert got["codebase_version"] == "v3.0" and got["fps"] == 1
    assert (got["len"], got["num_episodes"]) == (len(ds), len(entries))
    assert got["camera_keys"] == [f"observation.images.{v}" for v in VIEWS]
    assert got["policy_features"]["observation.state"] == ["FeatureType.STATE", [32]]
    assert got["policy_features"]["action"] == ["FeatureType.ACTION", [32]]
    assert got["policy_features"]["observation.images.head"] == ["FeatureType.VISUAL", [3, 12, 16]]
    assert got["batches"] == -(-len(ds) // 4) and got["batch_tasks"] >= 1
    assert got["batch_shapes"]["next_anchors"][1:] == [8, 32]
    assert got["batch_shapes"]["observation.points"][1:] == [ds.info.n_points, 11]

    bounds = np.cumsum([0] + [e.frames for e in entries])
    assert got["episodes"] == [[int(a), int(b)] for a, b in zip(bounds[:-1], bounds[1:])]
    assert got["tasks"] == sorted({e.instruction for e in entries}) and got["task_index"] == list(range(len(got["tasks"])))

    first, src = got["first"], ds.episode_arrays(entries[0])
    assert first["task"] == entries[0].instruction and (first["episode_index"], first["index"]) == (0, 0)
    np.testing.assert_allclose(first["action"], src["anchors"][0, 0], rtol=0, atol=0)
    np.testing.assert_allclose(first["state"], src["state"][0], rtol=0, atol=0)
    rgb = fake_frames(entries[0].task, entries[0].seed)["rgb"][0]
    for v, view in enumerate(VIEWS):
        assert first["images"][f"observation.images.{view}"] == hashlib.sha256(rgb[v].tobytes()).hexdigest()

    # delta_timestamps in keyframes: the last frame of an episode pads the next two actions
    assert got["chunk_action_shape"] == [3, 32] and got["chunk_action_is_pad"] == [False, True, True]
    assert got["chunk_state_is_pad"] == [True, False]
    assert all(got["stats_agree"].values()), got["stats_agree"]


def test_dp3s_zarr_2_read_gets_the_layout_and_episodes(interop_python, run, tmp_path):
    out = tmp_path / "data.zarr"
    export_dp3(run, out, stream=io.StringIO())
    got = _read(interop_python, "read_dp3.py", out, tmp_path / "hf")

    ds = open_dataset(run / "dataset")
    entries = ds.episodes()
    T, N = len(ds), ds.info.n_points
    assert got["zarr_version"].startswith("2.") and got["zgroup"]
    assert got["shapes"] == {"state": [T, 32], "action": [T, 32], "point_cloud": [T, N, 6]}
    assert set(got["dtypes"].values()) == {"float32"}
    assert got["episode_ends"] == np.cumsum([e.frames for e in entries]).tolist()
    assert got["lengths"] == [e.frames for e in entries]
    arrays = [ds.episode_arrays(e) for e in entries]
    expect = {"state": np.concatenate([a["state"] for a in arrays]),
              "action": np.concatenate([a["anchors"][:, 0] for a in arrays]),
              "point_cloud": np.concatenate([a["points"][..., :6] for a in arrays])}
    assert got["sha256"] == {k: hashlib.sha256(np.ascontiguousarray(v, np.float32).tobytes()).hexdigest() for k, v in expect.items()}
    assert "episode_ends" in got["meta_keys"]
