"""Fixtures of the cluster tests: the tiny config's file and the dataset hash of the same config
run on one local Ray (computed once per session)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml

from anchordp3.pipeline.report import dataset_content_hash
from anchordp3.pipeline.runner import keep_ray_on_loopback
from tests.cluster.helpers import LOOPBACK_ENV, TINY, cli

keep_ray_on_loopback()  # every Ray this process starts (the multi-node Cluster) keeps 127.0.0.1


@pytest.fixture(scope="session")
def config_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "cluster.yaml"
    path.write_text(yaml.safe_dump(TINY, sort_keys=False))
    return path


@pytest.fixture(scope="session")
def local_hash(config_file, tmp_path_factory) -> str:
    """The dataset hash of the same config run on one local Ray (the CLI, its own process)."""
    run = tmp_path_factory.mktemp("local")
    subprocess.run(cli("-q", "run", str(config_file), "--run-dir", str(run)), check=True, timeout=900, env=LOOPBACK_ENV)
    return dataset_content_hash(run)
