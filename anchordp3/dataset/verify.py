"""Check a written dataset against its ``dataset.json``: every shard and table, by checksum."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from anchordp3.dataset.files import tree_checksum
from anchordp3.schemas.dataset import INFO_FILE, DatasetInfo


class Problem(BaseModel):
    """One missing or corrupt file or shard."""

    model_config = ConfigDict(extra="forbid")

    path: str = Field(description="The shard folder or table file.")
    kind: Literal["missing", "corrupt"] = Field(description="Absent, or present with other content.")
    detail: str = Field(default="", description="What differs.")

    def line(self) -> str:
        """One line for a terminal."""
        return f"{self.kind}: {self.path}" + (f" ({self.detail})" if self.detail else "")


class VerifyReport(BaseModel):
    """Outcome of verifying a dataset."""

    model_config = ConfigDict(extra="forbid")

    dataset: str = Field(description="The dataset folder.")
    checked: int = Field(ge=0, description="Shards and tables checked.")
    problems: list[Problem] = Field(default_factory=list, description="Missing or corrupt items.")

    @property
    def ok(self) -> bool:
        """No problems found."""
        return not self.problems


def verify_shard(path: Path, checksum: str) -> Problem | None:
    """Recompute a shard folder's checksum; a Problem when it is missing or differs."""
    path = Path(path)
    if not path.is_dir():
        return Problem(path=str(path), kind="missing")
    got, _ = tree_checksum(path)
    if got != checksum:
        return Problem(path=str(path), kind="corrupt", detail=f"checksum {got[:12]} != recorded {checksum[:12]}")
    return None


def verify_file(path: Path, checksum: str) -> Problem | None:
    """sha256 of one file against the recorded one."""
    path = Path(path)
    if not path.is_file():
        return Problem(path=str(path), kind="missing")
    got = hashlib.sha256(path.read_bytes()).hexdigest()
    if got != checksum:
        return Problem(path=str(path), kind="corrupt", detail=f"checksum {got[:12]} != recorded {checksum[:12]}")
    return None


def verify_dataset(path: str | Path) -> VerifyReport:
    """Check every shard and table of the dataset at ``path``.

    Raises ValueError naming the path when there is no readable ``dataset.json``."""
    root = Path(path)
    info_path = root / INFO_FILE
    if not info_path.is_file():
        raise ValueError(f"{root}: not an anchordp3 dataset (no {INFO_FILE})")
    try:
        info = DatasetInfo.model_validate_json(info_path.read_bytes())
    except ValidationError as e:
        raise ValueError(f"{info_path}: not a valid dataset description ({e.error_count()} errors)") from None
    problems = [p for s in info.shards if (p := verify_shard(root / s.path, s.checksum))]
    problems += [p for name, sha in info.files.items() if (p := verify_file(root / name, sha))]
    return VerifyReport(dataset=str(root), checked=len(info.shards) + len(info.files), problems=problems)
