"""Stage manifests: what a stage consumed, what it produced per item, and how it went."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field

if TYPE_CHECKING:
    from anchordp3.schemas.records import Payload

P = TypeVar("P", bound="Payload")

MANIFEST_SCHEMA_VERSION = 1
ItemStatus = Literal["done", "failed"]


class Fingerprint(BaseModel):
    """What a stage's outputs depend on: a change of code, config or upstream invalidates the stage
    and everything downstream; a change of one task's hash only that task's items there and downstream."""

    model_config = ConfigDict(extra="forbid")

    code_version: str = Field(description="anchordp3 version that wrote the outputs.")
    code_hash: str = Field(default="", description="sha256 of the package modules that produced the outputs "
                                                  "(pipeline.codehash; empty: made before code was fingerprinted).")
    config_hash: str = Field(description="sha256 of the stage's part of the run config.")
    upstream: dict[str, str] = Field(default_factory=dict, description="Upstream stage name → its fingerprint digest.")
    tasks: dict[str, str] = Field(default_factory=dict, description="Task name → hash of its own module (the task's "
                                                                    "scene and expert) and of its upstream's, for the "
                                                                    "tasks whose code the stage or its upstream runs; "
                                                                    "code_hash leaves those modules out.")

    def changes(self, new: Fingerprint) -> list[str]:
        """What differs from ``new``: ``code``, ``config``, ``upstream <name>`` per upstream and ``task
        <name>`` per task, in that order; empty when the two are equal. A ``task`` change concerns
        only that task's outputs."""
        out = []
        if (self.code_version, self.code_hash) != (new.code_version, new.code_hash):
            out.append("code")
        if self.config_hash != new.config_hash:
            out.append("config")
        out += [f"upstream {k}" for k in sorted(set(self.upstream) | set(new.upstream)) if self.upstream.get(k) != new.upstream.get(k)]
        out += [f"task {k}" for k in sorted(set(self.tasks) | set(new.tasks)) if self.tasks.get(k) != new.tasks.get(k)]
        return out

    def digest(self) -> str:
        """A short hash of this fingerprint but its tasks' hashes (what downstream stages record:
        they carry the tasks' hashes on in their own ``tasks``)."""
        from anchordp3.schemas.run import config_hash

        return config_hash(self.model_dump(mode="json", exclude={"tasks"}))[:16]


def task_change(change: str) -> str | None:
    """The task a ``Fingerprint.changes`` entry concerns (``task place_mouse`` -> ``place_mouse``), else None."""
    return change.split(" ", 1)[1] if change.startswith("task ") else None


class ItemRecord(BaseModel):
    """One item's outcome. Written only after its output is durable."""

    model_config = ConfigDict(extra="forbid")

    item: str = Field(description="Item id, e.g. 'place_mouse/000003' or 'shard/00002'.")
    status: ItemStatus = Field(description="done: output durable; failed: gave up after retries.")
    output: str | None = Field(default=None, description="Output path relative to the stage folder (None when there is none).")
    checksum: str | None = Field(default=None, description="sha256 of the output's bytes.")
    seconds: float = Field(default=0.0, ge=0, description="Compute time of the successful (or last) attempt, seconds.")
    cpu_seconds: float | None = Field(default=None, ge=0, description="CPU time of the worker process during the successful "
                                                                        "attempt (all its threads, a renderer's included), seconds: "
                                                                        "the item's cost whatever else shared the machine; None when not measured.")
    attempts: int = Field(default=1, ge=1, description="Tries made.")
    reason: str | None = Field(default=None, description="Failure reason class (exception type or stage reason).")
    detail: str = Field(default="", description="Failure message, one line.")
    info: dict = Field(default_factory=dict, description="The stage's own facts, its payload model as JSON "
                                                      "(schemas.records: read them with ``payload``).")
    node: str | None = Field(default=None, description="The Ray node that did the item (its node ID's first 12 hex "
                                                       "digits; None when not known, e.g. records from before nodes were noted).")

    def payload(self, model: type[P]) -> P:
        """``info`` as its stage's payload model, e.g. ``rec.payload(RolloutInfo).record.steps``."""
        return model.model_validate(self.info)


class StageCounts(BaseModel):
    """Totals of a stage."""

    model_config = ConfigDict(extra="forbid")

    planned: int = Field(default=0, ge=0, description="Items the stage will see (known so far).")
    done: int = Field(default=0, ge=0, description="Items with a durable output.")
    failed: int = Field(default=0, ge=0, description="Items that failed after retries.")
    seconds: float = Field(default=0.0, ge=0, description="Sum of the items' compute seconds.")


class StageManifest(BaseModel):
    """A stage's manifest (``<run>/<stage>/records.sqlite``, read and written by ``pipeline.store``)."""

    model_config = ConfigDict(extra="forbid")

    schema_version: int = Field(default=MANIFEST_SCHEMA_VERSION, description="Version of this manifest format.")
    stage: str = Field(description="Stage name.")
    fingerprint: Fingerprint = Field(description="What the outputs depend on.")
    complete: bool = Field(default=False, description="Every planned item has a record.")
    counts: StageCounts = Field(default_factory=StageCounts, description="Totals.")
    items: dict[str, ItemRecord] = Field(default_factory=dict, description="Item id → record, sorted by id.")
