"""The stage graph: every data stage declared once, as data; the runner is generic over it.

A ``Stage`` says what the stage is called, where its outputs live, the plain function that does
one item, the payload model of its records, what it needs from earlier stages, the module whose
code makes its outputs (its fingerprint), and the part of the run config they depend on.

A ``Graph`` is a chain of *episode* stages (one item per ``(task, seed)``; an episode goes from
one to the next while each record ``continues``), at most one *group* stage (one item per group
of episodes, ready once every member is resolved, then one finishing item over all groups), then
*batch* stages (a fixed list of items, started once the stages they come ``after`` are complete:
a model to train, the episodes of an evaluation). ``pipeline.work`` declares the data stages,
``pipeline.products`` the training and evaluation stages and the whole graph; ``pipeline.noop`` a
synthetic one for measuring the runner itself. Adding a stage is adding one ``Stage`` (its
function and payload beside it).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import anchordp3
from anchordp3.pipeline.codehash import stage_hashes
from anchordp3.schemas.manifest import Fingerprint, P
from anchordp3.schemas.records import Payload
from anchordp3.schemas.run import PoolConfig, RunConfig, config_hash

CONFIG_FILE = "config.yaml"  # a run directory's copy of its run config


@dataclass(frozen=True)
class EpisodeItem:
    """One episode as a stage's input: its id and the payloads of the stages it ``needs``.

    ``ok`` (group members only): the episode made it through every episode stage."""

    task: str
    seed: int
    inputs: tuple[Payload, ...] = ()
    ok: bool = True

    def get(self, model: type[P]) -> P:
        """The input of type ``model`` (a payload the stage declared in ``needs``)."""
        for p in self.inputs:
            if isinstance(p, model):
                return p
        raise LookupError(f"{model.__name__}: not an input of this item (declare it in the stage's needs)")


@dataclass(frozen=True)
class GroupItem:
    """One group of a group stage: the plan's members (``.task``, ``.seed`` and whatever else the
    stage's ``group`` function gives them) and, in the same order, each as an ``EpisodeItem``."""

    index: int
    members: tuple[Any, ...]
    episodes: tuple[EpisodeItem, ...]


@dataclass(frozen=True)
class BatchItem:
    """One item of a batch stage: its id (a model's name, an evaluation episode ``task/000042``)
    and the stage's folder. ``stop_at``: stages run in the driver stop there, resumable
    (training: tests, demos)."""

    id: str
    folder: Path
    stop_at: int | None = None


@dataclass(frozen=True)
class BatchContext:
    """What a batch stage's hooks see besides the config: the run directory, the stage's folder,
    the stages this call runs, whether it may redo outputs made otherwise (``--force``) and
    whether it keeps outputs that only other code made (``--keep-outputs``)."""

    run_dir: Path
    folder: Path
    stages: frozenset[str] = frozenset()
    force: bool = False
    keep_outputs: bool = False

    def keeps(self, changes: list[str]) -> bool:
        """Whether outputs made under a fingerprint with these ``changes`` are kept as they are:
        ``keep_outputs`` keeps a change of code alone, unless ``force`` redoes it."""
        return changes == ["code"] and self.keep_outputs and not self.force

    def refuses(self, changes: list[str]) -> bool:
        """Whether such outputs are refused: changed, neither redone (``force``) nor kept."""
        return bool(changes) and not self.force and not self.keeps(changes)


@dataclass(frozen=True)
class StageOutput:
    """What one item of a stage produced: its output file (relative to the stage folder), that
    file's sha256, and the stage's payload."""

    output: str | None
    checksum: str | None
    info: Payload


@dataclass(frozen=True)
class Stage:
    """One declared stage.

    run: ``(run_dir, cfg, item) -> StageOutput``, item an ``EpisodeItem`` or (group stages) a
    ``GroupItem``; a plain function that writes into ``folder`` and raises on failure.
    config: the part of the run config the outputs depend on (hashed into the fingerprint).
    code: the module whose source, with everything it imports from the package, makes the outputs.
    needs: payload models of earlier stages whose records each item carries (``EpisodeItem.get``).
    group: group stages only: ``(cfg, episodes) -> groups``, each a list of members with
    ``.task`` and ``.seed``, fixed by the set of episodes alone.
    finish: group stages only: ``(run_dir, cfg, group records) -> StageOutput``, the stage's last
    item (``finish_item``), run in the driver once every group is done.
    release: ``(run_dir, cfg, record) -> StageOutput | None``, run in the driver once the next
    stage has the episode's output: may slim this stage's output (None: nothing to do).
    resources: the stage's actor pool when the run config has none for it (``execution.pools``).
    pool: ``cfg -> PoolConfig``, the pool a batch stage's settings give (evaluation: its workers).
    gpu_share: with ``gpus`` unset, the pool's actors share the cluster's GPUs when it has any.

    Batch stages (``items`` set) only:
    items: ``cfg -> item ids`` (``BatchItem.id``), fixed by the config; ``run`` gets a ``BatchItem``.
    after: stages that must be complete before the first item runs.
    fingerprint: ``(BatchContext, cfg) -> Fingerprint``: what the outputs depend on, read from
    the files of the stages ``after`` (a dataset's index, a model's checkpoint) once they are done.
    wanted: ``cfg -> bool``: whether a run with no stages named does this one (its section is set).
    check: ``(BatchContext, cfg) -> None``: refuses, before anything runs, what the stage would
    refuse only later (raises ``ValueError``).
    report: ``(BatchContext, cfg, records by item) -> None``, run in the driver after each call:
    the stage's summary files (tables, charts) from the records it has.
    in_driver: items run in the driver process, one at a time, with its device and live progress
    (training), not in actors.
    phase: what the stage's wall time counts towards in reports (``data``, ``train``, ``eval``)."""

    name: str
    folder: str
    run: Callable[[Path, RunConfig, Any], StageOutput]
    record: type[Payload]
    code: str
    config: Callable[[RunConfig], dict]
    needs: tuple[type[Payload], ...] = ()
    group: Callable[[RunConfig, Sequence[tuple[str, int]]], list[list[Any]]] | None = None
    finish: Callable[[Path, RunConfig, list], StageOutput] | None = None
    finish_item: str = "final"
    release: Callable[[Path, RunConfig, Any], StageOutput | None] | None = None
    resources: PoolConfig = field(default_factory=PoolConfig)
    pool: Callable[[RunConfig], PoolConfig] | None = None
    gpu_share: bool = False
    items: Callable[[RunConfig], list[str]] | None = None
    after: tuple[str, ...] = ()
    fingerprint: Callable[[BatchContext, RunConfig], Fingerprint] | None = None
    wanted: Callable[[RunConfig], bool] | None = None
    check: Callable[[BatchContext, RunConfig], None] | None = None
    report: Callable[[BatchContext, RunConfig, dict], None] | None = None
    in_driver: bool = False
    phase: str = "data"

    @property
    def batch(self) -> bool:
        """A batch stage: a fixed list of items, after other stages are complete."""
        return self.items is not None

    def pool_of(self, cfg: RunConfig) -> PoolConfig:
        """The stage's actor pool: the run config's ``execution.pools`` entry, else what its
        settings give (``pool``), else its declared ``resources``."""
        return getattr(cfg.execution.pools, self.name, None) or (self.pool(cfg) if self.pool else self.resources)

    @property
    def stop_payload(self) -> type[Payload] | None:
        """The payload model whose ``continues`` may stop an episode at this stage (its manifest
        indexes those items): ``record`` for an episode stage, None for a group or batch stage."""
        return self.record if self.group is None and not self.batch else None


@dataclass(frozen=True)
class Graph:
    """Episode stages in order, then at most one group stage, then batch stages.

    former: earlier layouts of the stages' config parts, each ``cfg -> {stage: part}`` (the
    stages it leaves out kept their part): outputs fingerprinted under one of them, for the same
    settings, are the outputs the current layout describes, so a run made then is re-stamped
    instead of redone (``runner.translate_layout``)."""

    stages: tuple[Stage, ...]
    former: tuple[Callable[[RunConfig], dict[str, dict]], ...] = ()
    names: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(s.name for s in self.stages))
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"stage graph: duplicate stage names in {self.names}")
        data = [s for s in self.stages if not s.batch]
        if any(s.batch for s in self.stages[:len(data)]):
            raise ValueError("stage graph: batch stages come after every episode and group stage")
        groups = [i for i, s in enumerate(data) if s.group is not None]
        if groups and groups != [len(data) - 1]:
            raise ValueError("stage graph: a group stage must be the last stage before the batch stages")
        produced: list[type[Payload]] = []
        for i, s in enumerate(self.stages):
            missing = [m.__name__ for m in s.needs if m not in produced]
            if missing:
                raise ValueError(f"stage graph: {s.name} needs {missing}, which no earlier stage records")
            unknown = [a for a in s.after if a not in self.names[:i]]
            if unknown:
                raise ValueError(f"stage graph: {s.name} comes after {unknown}, which are not earlier stages")
            produced.append(s.record)

    def __getitem__(self, name: str) -> Stage:
        for s in self.stages:
            if s.name == name:
                return s
        raise KeyError(f"unknown stage {name!r}; choose from {', '.join(self.names)}")

    @property
    def episode_stages(self) -> tuple[Stage, ...]:
        return tuple(s for s in self.stages if s.group is None and not s.batch)

    @property
    def group_stage(self) -> Stage | None:
        return next((s for s in self.stages if s.group is not None), None)

    @property
    def data_stages(self) -> tuple[Stage, ...]:
        """The episode stages and the group stage: the chain of per-episode work."""
        return tuple(s for s in self.stages if not s.batch)

    @property
    def batch_stages(self) -> tuple[Stage, ...]:
        return tuple(s for s in self.stages if s.batch)

    def upstream(self, name: str) -> str | None:
        """The data stage before data stage ``name`` (None for the first; batch stages name
        theirs in ``after``)."""
        names = [s.name for s in self.data_stages]
        i = names.index(name)
        return names[i - 1] if i else None

    def targets(self, cfg: RunConfig) -> tuple[str, ...]:
        """The stages a run with none named does: every data stage, and each batch stage the
        config asks for (``wanted``)."""
        return tuple(s.name for s in self.stages if not s.batch or (s.wanted is not None and s.wanted(cfg)))

    def with_folder(self, name: str, folder: str | Path) -> "Graph":
        """This graph with stage ``name``'s outputs in ``folder`` (relative to the run directory,
        or absolute: an evaluation written elsewhere)."""
        return Graph(tuple(replace(s, folder=str(folder)) if s.name == name else s for s in self.stages), self.former)

    def producer(self, model: type[Payload]) -> str:
        """The stage whose records are ``model``."""
        return next(s.name for s in self.stages if s.record is model)


def fingerprints(cfg: RunConfig, graph: Graph) -> dict[str, Fingerprint]:
    """Each data stage's fingerprint: code version and hash, its config part, its upstream's digest
    (a batch stage's depends on files: ``Stage.fingerprint``)."""
    out: dict[str, Fingerprint] = {}
    for st in graph.data_stages:
        up = graph.upstream(st.name)
        code, own = stage_hashes([st.code], cfg.tasks)  # each task's own module counts in its task's hash only
        before = out[up].tasks if up else {}
        tasks = {t: chain_hash(own.get(t, ""), before.get(t, "")) for t in cfg.tasks if t in own or t in before}
        out[st.name] = Fingerprint(code_version=anchordp3.__version__, code_hash=code,
                                   config_hash=config_hash(st.config(cfg)), upstream={up: out[up].digest()} if up else {},
                                   tasks=tasks)
    return out


def chain_hash(own: str, upstream: str) -> str:
    """One task's hash at a stage: its module's hash as the stage's code reaches it, after its upstream's."""
    return hashlib.sha256(f"{own}\0{upstream}".encode()).hexdigest()[:16]


def translate_layout(cfg: RunConfig, graph: Graph, stored: dict[str, Fingerprint]) -> dict[str, Fingerprint]:
    """The ``stored`` fingerprints (of the stages that have outputs) as the current config layout
    reads them: when every stored config hash is the one a former layout (``Graph.former``) gives
    for ``cfg``, each takes the current layout's config hash and its upstream the translated
    digest (code hashes stay: a code change is still one). Otherwise ``stored`` unchanged."""
    for former in graph.former:
        parts = former(cfg)
        old = {st.name: config_hash(parts.get(st.name, st.config(cfg))) for st in graph.data_stages}
        if not stored or any(fp.config_hash != old[s] for s, fp in stored.items()) or all(
                fp.config_hash == config_hash(graph[s].config(cfg)) for s, fp in stored.items()):
            continue
        out: dict[str, Fingerprint] = {}
        for st in graph.data_stages:
            if st.name not in stored:
                continue
            fp, up = stored[st.name], graph.upstream(st.name)
            out[st.name] = fp.model_copy(update={"config_hash": config_hash(st.config(cfg)),
                                                 "upstream": {up: out[up].digest()} if up in out else fp.upstream})
        return out
    return stored
