"""Fixtures: small features files in the exact format of the features stage, random contents."""

from __future__ import annotations

from pathlib import Path

import pytest
from dataset_helpers import build, write_features

from anchordp3.schemas.dataset import WriteConfig


@pytest.fixture(scope="session")
def features_dir(tmp_path_factory) -> Path:
    return write_features(tmp_path_factory.mktemp("feat"))


@pytest.fixture(scope="session")
def cfg() -> WriteConfig:
    return WriteConfig(episodes_per_shard=2, validation_fraction=0.25, split_seed=3, inner_chunk=2)


@pytest.fixture(scope="session")
def built(features_dir, cfg, tmp_path_factory):
    """A dataset with episode ("place_bell", 5) failed upstream (its file exists but is skipped)."""
    out = tmp_path_factory.mktemp("ds")
    info, records, plan = build(features_dir, out, cfg, failed=[("place_bell", 5)])
    return out, info, records, plan
