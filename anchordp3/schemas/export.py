"""What an export of a run's dataset to another project's format produced (``anchordp3 export``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

ExportFormat = Literal["lerobot", "dp3"]


class ExportResult(BaseModel):
    """One finished export: where it is, what it holds, what it came from."""

    model_config = ConfigDict(extra="forbid")

    format: ExportFormat = Field(description="lerobot: a LeRobotDataset (v3.0); dp3: DP3's zarr (format 2).")
    out: str = Field(description="The export folder.")
    source: str = Field(description="The dataset folder it was read from.")
    fingerprint: str = Field(description="The source dataset's fingerprint (dataset.json).")
    episodes: int = Field(ge=0, description="Episodes exported.")
    frames: int = Field(ge=0, description="Frames (samples) exported.")
    cameras: list[str] = Field(default_factory=list, description="Camera views exported as images (lerobot only).")
    files: int = Field(ge=0, description="Files in the export.")
    nbytes: int = Field(ge=0, description="Bytes on disk.")
    seconds: float = Field(ge=0, description="Wall time.")

    def line(self) -> str:
        """One line for a terminal."""
        views = f", images of {', '.join(self.cameras)}" if self.cameras else (", no images" if self.format == "lerobot" else "")
        return (f"wrote {self.out} ({self.format}): {self.episodes} episodes, {self.frames} frames{views}, "
                f"{self.files} files, {self.nbytes / 1e6:.1f} MB in {self.seconds:.1f} s")


def label_meaning(plan: str | None) -> dict[str, str]:
    """What an export's ``action`` and ``next_anchors`` hold, for the run's frame plan
    (``anchors.plan``: ``anchors``, ``dense``, or None when unknown, taken as ``anchors``)."""
    if plan == "dense":
        return {"action": "the next commanded action, as the 32-d state it reaches (dense DP3-style plan; anchors[0])",
                "next_anchors": "the next 8 commanded actions (every action_stride steps) as 32-d states"}
    return {"action": "the next anchor: the 32-d state the robot should reach when the current atomic operation ends (anchors[0])",
            "next_anchors": "the next 8 anchors as 32-d states; the last anchor repeats past the episode's end"}
