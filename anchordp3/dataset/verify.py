"""Check a written dataset against its ``dataset.json``: every shard and table, by checksum."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from anchordp3.dataset.files import file_sha256, tree_checksum
from anchordp3.dataset.reader import read_dataset_info


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
    got = file_sha256(path)
    if got != checksum:
        return Problem(path=str(path), kind="corrupt", detail=f"checksum {got[:12]} != recorded {checksum[:12]}")
    return None


def verify_dataset(path: str | Path) -> VerifyReport:
    """Check every shard and table of the dataset at ``path``.

    Raises ValueError naming the path when there is no readable ``dataset.json``."""
    root = Path(path)
    info = read_dataset_info(root)
    problems = [p for s in info.shards if (p := verify_shard(root / s.path, s.checksum))]
    problems += [p for name, sha in info.files.items() if (p := verify_file(root / name, sha))]
    return VerifyReport(dataset=str(root), checked=len(info.shards) + len(info.files), problems=problems)
