"""Running a stage graph as streaming pools of Ray actors, with manifests and resume.

The driver (this module) owns the manifests and decides what runs; actors (``actors.py``) do the
items. The loop knows no stage by name: it walks the declared graph (``graph.Graph``;
``products.GRAPH`` by default: the data stages, training, evaluation). An episode flows through
the episode stages (rollout → anchors → render → features) as soon as each step is done; a group
(a shard) is written as soon as every episode it holds is resolved (through every stage, stopped,
or failed); the group stage's finishing item (the dataset's index and statistics) comes when every
group is done. Then each batch stage (the models, one at a time in the driver; the evaluation's
episodes, in a pool of actors with the same retries and crash triage) once its inputs are
complete. Work in flight is bounded per actor, and only IDs, paths and small typed payloads
travel between processes.

Messages and progress lines go to ``logging`` (``anchordp3.logs``); what a worker logs while it
does an item comes back with the item's result and is re-emitted here, so the run's log file
(``<run>/logs/driver.log``) holds the driver's and every worker's messages.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import math
import os
import sqlite3
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import ray
import yaml

import anchordp3
from anchordp3.logs import replay, to_file
from anchordp3.pipeline.actors import FAULTS_ENV, NO_SPACE, ItemResult, StageWorker, one_line
from anchordp3.pipeline.graph import (
    CONFIG_FILE,
    BatchContext,
    BatchItem,
    EpisodeItem,
    Graph,
    GroupItem,
    Stage,
    StageOutput,
    fingerprints,
    translate_layout,
)
from anchordp3.pipeline.lock import RunLock
from anchordp3.pipeline.products import GRAPH
from anchordp3.pipeline.reaper import watch_local_ray
from anchordp3.pipeline.store import ManifestStore, StaleStageError, read_summary
from anchordp3.schemas.episode import episode_id
from anchordp3.schemas.manifest import Fingerprint, ItemRecord, task_change
from anchordp3.schemas.run import RunConfig
from anchordp3.stages.files import atomic_write_bytes, no_space, sweep_interrupted_writes

log = logging.getLogger(__name__)

LOG_FILE = "logs/driver.log"  # the driver's messages, progress and its workers' messages, appended per invocation
CALL_SECONDS = 0.05  # work an actor call should carry before items are batched into it
MAX_BATCH = 256      # items per actor call at most
NODE_CHECK_S = 2.0   # how often the driver asks which Ray nodes are alive (actors on a dead one are replaced)
REPLACE_START_S = 60.0  # a replacement actor not answering after this long is replaced by one that reserves no CPU


class RunAborted(RuntimeError):
    """Too many items of a stage failed, or a stage's workers cannot start."""


class NoSpaceLeft(RunAborted):
    """The run directory's disk is full: the run stops at once (what is recorded done is whole),
    and resumes once space is freed."""

    def __init__(self, what: str):
        super().__init__(f"{what}; the run stopped: free space there, then run the same command again to resume")


@dataclass
class RunOptions:
    """How to run: which stages, how many workers, where, and what to redo."""

    stages: tuple[str, ...] | None = None  # None: the graph's targets for the config (``Graph.targets``)
    workers: int | None = None          # overrides every pool's size
    address: str | None = None          # None: a local Ray; "auto" or "ray://…": join a cluster
    force: bool = False                 # redo stages whose fingerprint changed
    redo: tuple[str, ...] = ()          # batch stages redone when their fingerprint changed (``force`` for these only)
    keep_outputs: bool = False          # keep outputs that only other code made (same config): adopt them
    from_stage: str | None = None       # redo this stage and everything downstream
    progress_interval: float | None = None  # seconds between progress lines (None: 2 on a terminal, 15 in a log)
    faults: str = field(default_factory=lambda: os.environ.get(FAULTS_ENV, ""))
    stop_at: dict[str, int] = field(default_factory=dict)  # model name -> step: training stops there, resumable (tests, demos)
    on_phase: Callable[[str, float], None] | None = None  # told each phase's wall seconds (``Stage.phase``) as it ends




def read_fingerprints(run_dir: Path, graph: Graph = GRAPH) -> dict[str, Fingerprint]:
    """The stored fingerprints of the stages with outputs in ``run_dir``, as written."""
    stored = {}
    for st in graph.data_stages:
        d = Path(run_dir) / st.folder
        if d.exists() and (m := read_summary(d)) is not None:
            stored[st.name] = m.fingerprint
    return stored


def stored_fingerprints(cfg: RunConfig, run_dir: Path, graph: Graph = GRAPH) -> dict[str, Fingerprint]:
    """The fingerprints of the stages with outputs in ``run_dir``, in the current layout."""
    return translate_layout(cfg, graph, read_fingerprints(run_dir, graph))


def stage_changes(cfg: RunConfig, run_dir: Path, graph: Graph = GRAPH,
                  fps: dict[str, Fingerprint] | None = None) -> dict[str, list[str]]:
    """Stages whose stored outputs were made with another fingerprint than ``cfg`` (and this code)
    gives, in pipeline order, each with what changed (``Fingerprint.changes``). ``fps``: those
    fingerprints when already computed (``fingerprints`` hashes the stages' code)."""
    fps = fps or fingerprints(cfg, graph)
    stored = stored_fingerprints(cfg, run_dir, graph)
    return {st.name: changed for st in graph.data_stages if st.name in stored and (changed := stored[st.name].changes(fps[st.name]))}


def adoptable(changes: dict[str, list[str]]) -> list[str]:
    """The changed stages whose outputs ``--keep-outputs`` keeps: those whose config is the same and
    whose upstream changed only where an adopted stage did (only code differs along the way)."""
    kept: list[str] = []
    for s, changed in changes.items():
        if all(c == "code" or (c.startswith("upstream ") and c.split(" ", 1)[1] in kept) for c in changed):
            kept.append(s)
    return kept


def describe_changes(changes: dict[str, list[str]]) -> str:
    """``render (code), features (upstream render)``."""
    return ", ".join(f"{s} ({', '.join(c)})" for s, c in changes.items())


class _Stats:
    """Per-stage counters for the progress display."""

    def __init__(self, names: tuple[str, ...]):
        self.t0 = time.perf_counter()
        self.done = {s: 0 for s in names}
        self.failed = {s: 0 for s in names}
        self.compute = {s: 0.0 for s in names}

    def line(self, s: str, total: int, already: int) -> str:
        el = time.perf_counter() - self.t0
        n = self.done[s] + self.failed[s]
        rate = n / el if el > 0 else 0.0
        left = max(total - already - n, 0)
        eta = f"{left / rate:.0f}s" if rate > 0 else "?"
        return f"{s:>8}: {already + self.done[s]}/{total} done, {self.failed[s]} failed, {rate:.2f}/s, ETA {eta}"


class CrashTriage:
    """Who is to blame when an actor dies.

    The errors alone cannot tell: the call that killed the process, calls whose replies died with
    it, and calls sent while it restarted all fail alike. So every call lost with an actor is
    retried free, as a *suspect*, and a suspect runs alone on an actor known to be up (it answered
    a ping): a crash then has exactly one cause, and only that crash costs its item an attempt.
    Actors are ``(stage, index)``; items are ``(stage, item id)``."""

    def __init__(self):
        self.suspects: set = set()  # items lost with an actor
        self.down: set = set()      # actors that died and have not answered a ping since
        self.alone: dict = {}       # actor → the suspect running alone on it

    def can_take(self, actor, item, load: int, cap: int) -> bool:
        """Whether ``item`` may be sent to ``actor``, which has ``load`` calls in flight now."""
        if actor in self.down or actor in self.alone:
            return False
        return load == 0 if item in self.suspects else load < cap

    def submitted(self, actor, item) -> None:
        if item in self.suspects:
            self.alone[actor] = item

    def lost(self, actor, item) -> bool:
        """A call of ``item`` failed because ``actor`` died: True if the item is to blame (it ran
        alone there), False if it is retried free. Either way it is a suspect from now on."""
        blame = self.alone.get(actor) == item
        self.suspects.add(item)
        self.down.add(actor)
        return blame

    def finished(self, actor, item, ok: bool) -> None:
        """A call of ``item`` on ``actor`` came back (``ok``: it succeeded)."""
        if self.alone.get(actor) == item:
            del self.alone[actor]
        if ok:
            self.suspects.discard(item)

    def up(self, actor) -> None:
        """``actor`` answered a ping: it takes calls again."""
        self.down.discard(actor)


class Runner:
    """One invocation of ``anchordp3 run`` on a run directory (use ``run_pipeline``), generic over
    a stage graph (``graph.Graph``; the data stages by default)."""

    def __init__(self, cfg: RunConfig, run_dir: Path, opts: RunOptions, graph: Graph = GRAPH):
        self.cfg, self.run_dir, self.opts, self.graph = cfg, Path(run_dir), opts, graph
        self.names = tuple(st.name for st in graph.data_stages)  # the data stages; batch stages run after them
        self.chain = graph.episode_stages
        self.group = graph.group_stage
        wanted = opts.stages or graph.targets(cfg)
        self.enabled = [s for s in self.names if s in wanted]
        self.batches = [st for st in graph.batch_stages if st.name in wanted]
        self.fps = fingerprints(cfg, graph)
        self.episodes = [(t, s) for t in cfg.tasks for s in cfg.seed_list]
        self.plan = self.group.group(cfg, self.episodes) if self.group else []
        self.group_of = {(m.task, m.seed): k for k, members in enumerate(self.plan) for m in members}
        self.halted: dict[str, set[str]] = {st.name: set() for st in self.chain}  # done, but the episode stops here
        self.stats = _Stats(graph.names)
        self._actor_options: dict[str, dict] = {}
        self.interval = opts.progress_interval if opts.progress_interval is not None else (2.0 if sys.stderr.isatty() else 15.0)

    def _dir(self, stage: str) -> Path:
        return self.run_dir / self.graph[stage].folder

    # ----------------------------------------------------------------------------- setup
    def open_stores(self) -> dict[str, ManifestStore]:
        written = read_fingerprints(self.run_dir, self.graph)
        stored = translate_layout(self.cfg, self.graph, written)
        every = {s: c for s in self.names if s in stored and (c := stored[s].changes(self.fps[s]))}
        changes = {s: w for s, c in every.items() if (w := [x for x in c if task_change(x) is None])}
        redo: set[str] = set()
        if self.opts.from_stage in self.names:
            redo |= set(self.names[self.names.index(self.opts.from_stage):])
        if self.opts.force:
            redo |= set(changes)
        tasks_only = {s for s in every if s not in changes and s not in redo}  # only some tasks' code changed
        keep: set[str] = set()
        if self.opts.keep_outputs:
            keep = set(adoptable({s: c for s, c in changes.items() if s not in redo})) | tasks_only
        left = {s: c for s, c in changes.items() if s not in redo and s not in keep}
        if left:
            code_only = all("config" not in c for c in left.values())
            hint = ("--force to redo them, or --keep-outputs to keep what the old code made" if code_only
                    else f"--force, or --from-stage {next(iter(left))}")
            raise StaleStageError(
                f"{self.run_dir}: stage(s) {describe_changes(left)} were made with another "
                f"{'code' if code_only else 'config or code'} than now; refusing to mix old and new outputs: rerun with {hint}")
        restamp = {s for s in stored if s not in changes and written[s] != stored[s]}  # made under a former layout
        retask = {s: [t for x in every[s] if (t := task_change(x))] for s in tasks_only - keep}  # their items alone redone
        for s in self.names:
            if s in keep:
                log.info(f"{s}: keeping the outputs other code made ({', '.join(every[s])}), as --keep-outputs asks")
            if s in restamp:
                log.info(f"{s}: outputs fingerprinted under an earlier config layout; re-stamped, nothing redone")
            if s in retask:
                log.info(f"{s}: the code of {', '.join(retask[s])} changed: their items are made again, the other tasks' kept")
        adopt = (keep | restamp | set(retask)) - redo
        stores = {s: ManifestStore(self._dir(s), s, self.fps[s], reset=s in redo, adopt=s in adopt,
                                   payload=self.graph[s].stop_payload, forget=self._items_of(s, retask.get(s, ())))
                  for s in self.names}
        for st in self.chain:
            self.halted[st.name] = stores[st.name].stopped()
        return stores

    def _items_of(self, stage: str, tasks: Sequence[str]) -> list[str]:
        """The item ids of ``stage`` that hold an episode of ``tasks``: the episodes themselves, or
        for the group stage the groups with such a member and its finishing item."""
        if not tasks:
            return []
        if self.group is not None and stage == self.group.name:
            groups = [_group_id(k) for k, members in enumerate(self.plan) if any(m.task in tasks for m in members)]
            return groups + ([self.group.finish_item] if groups and self.group.finish is not None else [])
        return [episode_id(t, s) for t, s in self.episodes if t in tasks]

    def check_inputs(self, stores: dict[str, ManifestStore]) -> None:
        """A stage run without its upstream must find the upstream complete."""
        for s in self.enabled:
            up = self.graph.upstream(s)
            if up is None or up in self.enabled:
                continue
            m = stores[up].manifest
            if not m.complete:
                raise ValueError(f"stage {s}: its input stage {up} is not complete ({m.counts.done} done, "
                                 f"{m.counts.failed} failed of {m.counts.planned}); run {up} first or both together")

    # ----------------------------------------------------------------------------- episode flow
    def next_stage(self, stores: dict[str, ManifestStore], eid: str) -> str | None:
        """The episode stage ``eid`` needs next, or None when it is resolved."""
        for st in self.chain:
            status = stores[st.name].status.get(eid)
            if status is None:
                return st.name
            if status == "failed" or eid in self.halted[st.name]:
                return None
        return None

    def episode_ok(self, stores: dict[str, ManifestStore], eid: str) -> bool:
        """The episode went through every episode stage."""
        return bool(self.chain) and stores[self.chain[-1].name].done(eid)

    def episode_item(self, stores: dict[str, ManifestStore], stage: Stage, ep: tuple[str, int], ok: bool = True) -> EpisodeItem:
        """``ep`` as ``stage``'s input: the payloads it needs, of those records that are done."""
        eid = episode_id(*ep)
        inputs = []
        for model in stage.needs:
            rec = stores[self.graph.producer(model)].items.get(eid)
            if rec is not None and rec.status == "done":
                inputs.append(rec.payload(model))
        return EpisodeItem(ep[0], ep[1], tuple(inputs), ok)

    def group_item(self, stores: dict[str, ManifestStore], k: int) -> GroupItem:
        members = self.plan[k]
        eps = tuple(self.episode_item(stores, self.group, (m.task, m.seed), self.episode_ok(stores, episode_id(m.task, m.seed)))
                    for m in members)
        return GroupItem(k, tuple(members), eps)

    # ----------------------------------------------------------------------------- the run
    def run(self) -> dict:
        checked = set()  # a hook several stages share (the train stages') checks them all at once
        for st in self.batches:  # refusals that would otherwise come after the stages before them ran
            if st.check is not None and st.check not in checked:
                checked.add(st.check)
                st.check(self._context(st), self.cfg)
        try:
            with RunLock(self.run_dir), to_file(self.run_dir / LOG_FILE):
                t0 = time.perf_counter()
                counts = self._run_data() if self.enabled else {}
                if self.enabled:
                    self._phase_done("data", t0)
                else:
                    atomic_write_bytes(self.run_dir / CONFIG_FILE, yaml.safe_dump(self.cfg.model_dump(mode="json"), sort_keys=False).encode())
                for phase, stages in itertools.groupby(self.batches, key=lambda st: st.phase):
                    t0 = time.perf_counter()
                    for st in stages:
                        counts[st.name] = self._run_batch(st)
                    self._phase_done(phase, t0)
                return counts
        except (OSError, sqlite3.OperationalError) as e:
            if (what := no_space(e, self.run_dir)) is None:
                raise
            raise NoSpaceLeft(what) from None

    def _phase_done(self, phase: str, t0: float) -> None:
        if self.opts.on_phase is not None:
            self.opts.on_phase(phase, time.perf_counter() - t0)

    def _run_data(self) -> dict:
        """The data stages: episodes stream through the episode stages, groups are written as
        their members resolve; per-stage counts."""
        for s in self.names:
            sweep_interrupted_writes(self._dir(s))
        stores = self.open_stores()
        try:
            self.check_inputs(stores)
            atomic_write_bytes(self.run_dir / CONFIG_FILE, yaml.safe_dump(self.cfg.model_dump(mode="json"), sort_keys=False).encode())
            self._loop(stores)
            if self.group is not None and self.group.name in self.enabled:
                self._finish(stores)
        except BaseException:
            self._close(stores, failing=True)
            raise
        self._close(stores)
        return {s: stores[s].manifest.counts.model_dump() for s in self.names}

    # ----------------------------------------------------------------------------- batch stages
    def _context(self, st: Stage) -> BatchContext:
        return BatchContext(self.run_dir, self._dir(st.name), frozenset(s.name for s in self.batches) | set(self.enabled),
                            self.opts.force or st.name in self.opts.redo or self._redone(st.name), self.opts.keep_outputs)

    def _redone(self, name: str) -> bool:
        """``--from-stage`` names ``name`` or a stage before it."""
        names = self.graph.names
        return self.opts.from_stage is not None and names.index(name) >= names.index(self.opts.from_stage)

    def _complete_on_disk(self, name: str) -> bool:
        d = self._dir(name)
        m = read_summary(d) if d.is_dir() else None
        return m is not None and m.complete

    def _run_batch(self, st: Stage) -> dict:
        """A batch stage: its inputs complete, its fingerprint from their files, its items in the
        driver (``in_driver``) or in a pool of actors, then its report; its counts."""
        for a in st.after:
            if not self._complete_on_disk(a):
                raise ValueError(f"stage {st.name}: its input stage {a} is not complete ({self._dir(a)}); run it first")
        ctx = self._context(st)
        sweep_interrupted_writes(ctx.folder)
        fp = st.fingerprint(ctx, self.cfg)
        stored = read_summary(ctx.folder) if ctx.folder.is_dir() else None
        changed = stored.fingerprint.changes(fp) if stored is not None else []
        keep = ctx.keeps(changed)
        if ctx.refuses(changed):
            raise StaleStageError(f"{ctx.folder}: made with another {', '.join(changed)} than now (stage {st.name}); "
                                  f"rerun with --force to redo it{', or --keep-outputs to keep it' if changed == ['code'] else ''}")
        if changed and not keep:
            log.info(f"{st.name}: {', '.join(changed)} changed; redoing it from scratch (--force)")
        elif keep:
            log.info(f"{st.name}: keeping the outputs other code made, as --keep-outputs asks")
        store = ManifestStore(ctx.folder, st.name, fp, reset=bool(changed) and not keep, adopt=keep)
        try:
            items = st.items(self.cfg)
            pending = [i for i in items if not store.done(i)]
            log.info(f"{st.name}: {len(items)} items ({len(items) - len(pending)} already done)")
            store.finish(len(items), not pending)  # the fingerprint is on disk before any output is
            if pending and st.in_driver:
                for i in pending:
                    t0 = time.perf_counter()
                    out = st.run(self.run_dir, self.cfg, BatchItem(i, ctx.folder, self.opts.stop_at.get(i)))
                    if out is None:
                        break  # stopped on purpose: resumable
                    store.record(_done_record(i, out, time.perf_counter() - t0, 1))
                    self.stats.done[st.name] += 1
            elif pending:
                self._loop({st.name: store}, lone=st, pending=pending)
            store.finish(len(items), all(store.done(i) for i in items))
            if st.report is not None:
                st.report(ctx, self.cfg, {i: r for i in items if (r := store.items.get(i)) is not None})
            return store.manifest.counts.model_dump()
        finally:
            store.close()

    def _close(self, stores: dict[str, ManifestStore], failing: bool = False) -> None:
        """Commit each store's totals and close it. On a full disk the rest are closed without
        committing (what is not committed is redone on resume) and the error is raised, unless
        the run is ``failing`` already (its own error is the one to report)."""
        full = None
        for s, st in stores.items():
            try:
                if full is None:
                    st.finish(self._planned(stores, s), self._complete(stores, s))
            except (OSError, sqlite3.OperationalError) as e:
                if no_space(e) is None:
                    raise
                full = e
            finally:
                st.close(commit=full is None)
        if full is not None and not failing:
            raise full

    def _planned(self, stores: dict[str, ManifestStore], s: str) -> int:
        if self.group is not None and s == self.group.name:
            return len(self.plan) + (1 if self.group.finish else 0)
        prev = self.graph.upstream(s)
        if prev is None:
            return len(self.episodes)
        status, halted = stores[prev].status, self.halted[prev]
        return sum(1 for ep in self.episodes if status.get(eid := episode_id(*ep)) == "done" and eid not in halted)

    def _recorded(self, stores: dict[str, ManifestStore], s: str) -> int:
        """Items of this run's plan that stage ``s`` has a record of (not those of a run with more seeds)."""
        status = stores[s].status
        if self.group is not None and s == self.group.name:
            return sum(1 for k in range(len(self.plan)) if _group_id(k) in status)
        return sum(1 for ep in self.episodes if episode_id(*ep) in status)

    def _complete(self, stores: dict[str, ManifestStore], s: str) -> bool:
        if self.group is not None and s == self.group.name:
            if self.group.finish:
                return stores[s].done(self.group.finish_item)
            return all(stores[s].done(_group_id(k)) for k in range(len(self.plan)))
        prev = self.graph.upstream(s)
        upstream_complete = prev is None or self._complete(stores, prev)
        status = stores[s].status  # may hold episodes a run with more seeds left: count this run's
        n = sum(1 for ep in self.episodes if episode_id(*ep) in status)
        return upstream_complete and n >= self._planned(stores, s)

    def _loop(self, stores: dict[str, ManifestStore], lone: Stage | None = None, pending: Sequence[str] = ()) -> None:
        """Run items in pools of actors until none is left: the enabled data stages' (episodes
        flowing from stage to stage, groups as they become ready), or the ``pending`` items of
        ``lone``, a batch stage."""
        enabled = [lone.name] if lone is not None else self.enabled
        group = self.group.name if self.group is not None and lone is None else None
        queues: dict[str, deque] = {s: deque() for s in self.graph.names}
        queued: set[tuple[str, str]] = set()
        groups_left = {k for k in range(len(self.plan)) if not stores[group].done(_group_id(k))} if group else set()

        unresolved = {k: len(self.plan[k]) for k in groups_left}  # members still to resolve, per group left

        def enqueue_episode(eid, ep) -> bool:
            """Queue ``ep`` for the stage it needs next; False when it needs none (resolved)."""
            s = self.next_stage(stores, eid)
            if s is None:
                return False
            if s in enabled and (s, eid) not in queued:
                queues[s].append(ep)
                queued.add((s, eid))
            return True

        def resolved(ep) -> None:
            """``ep`` needs no more episode stages: its group may be ready."""
            k = self.group_of.get(ep)
            if k is None or k not in unresolved:
                return
            unresolved[k] -= 1
            if unresolved[k] == 0 and group in enabled:
                queues[group].append(k)
                queued.add((group, _group_id(k)))

        if lone is not None:
            queues[lone.name].extend(pending)
        for ep in self.episodes if lone is None else ():
            eid = episode_id(*ep)
            self._release(stores, eid)  # finishes a release a crash interrupted
            if not enqueue_episode(eid, ep):
                resolved(ep)
        for store in stores.values():
            store.flush()
        if not any(queues.values()):
            return

        pools = self._start_pools(enabled, most=len(pending) if lone is not None else None)
        in_flight: dict = {}  # ObjectRef → (stage, actor index, [(item id, key, attempt), …])
        load = {s: [0] * len(pools.get(s, [])) for s in self.graph.names}  # calls in flight per actor
        triage = CrashTriage()
        pings: dict = {}      # ObjectRef of a ping → actor (stage, index): a died one, or a new one telling its node
        ping_due: dict = {}   # actor → when to ping it (again)
        node_of: dict = {}    # actor → its Ray node (``actors.node_id``), from its answers
        replaced: dict = {}   # actor → (when it was replaced, its replacement reserves CPU), until the new one answers
        last_node_check = time.perf_counter()
        for s in pools:
            for a, actor in enumerate(pools[s]):
                pings[actor.ping.remote()] = (s, a)  # each actor tells its node: the driver sees it if the node goes
        attempts: dict[tuple[str, str], int] = {}
        last_print = 0.0
        cap = self.cfg.execution.in_flight_per_worker

        def item_id_of(s, key) -> str:
            if lone is not None:
                return key
            return _group_id(key) if s == group else episode_id(*key)

        def item_of(s, key):
            if lone is not None:
                return BatchItem(key, self._dir(s))
            return self.group_item(stores, key) if s == group else self.episode_item(stores, self.graph[s], key)

        consumer = {st.name: nxt.name for st, nxt in zip(self.chain, self.chain[1:])
                    if st.release is not None and nxt.name in enabled}

        def held_back(s: str) -> bool:
            """Whether ``s``, a stage whose outputs are transient (``release``), is far enough ahead of
            the stage that consumes them: its unconsumed outputs (the consumer's backlog, plus ``s``'s
            own calls in flight) fill every consumer actor's queue twice. Bounds their disk."""
            nxt = consumer.get(s)
            if nxt is None:
                return False
            pending = len(queues[nxt]) + sum(len(b) for st_, _, b in in_flight.values() if st_ in (s, nxt))
            return pending >= 2 * cap * max(1, len(pools.get(nxt, ())))

        def submit(s: str) -> None:
            """Send ``s``'s queued items to its free actors, a batch per call (``_batch_size``)."""
            st, size = self.graph[s], self._batch_size(s)
            while queues[s] and pools.get(s) and not held_back(s):
                first = item_id_of(s, queues[s][0])
                free = [a for a in range(len(load[s])) if triage.can_take((s, a), (s, first), load[s][a], cap)]
                if not free:
                    return
                a = min(free, key=lambda i: load[s][i])
                batch = []
                while queues[s] and len(batch) < (1 if (s, first) in triage.suspects else size):
                    key = queues[s][0]
                    item_id = item_id_of(s, key)
                    if batch and (s, item_id) in triage.suspects:
                        break  # a suspect runs alone
                    queues[s].popleft()
                    attempts[(s, item_id)] = attempts.get((s, item_id), 0) + 1
                    batch.append((item_id, key, attempts[(s, item_id)]))
                    triage.submitted((s, a), (s, item_id))
                items = [(i, item_of(s, k), n) for i, k, n in batch]
                in_flight[pools[s][a].run_many.remote(items)] = (s, a, batch)
                load[s][a] += 1

        def retry_free(s: str, item_id: str, key) -> None:
            """Queue an item lost with its actor again, first in line, without costing it an attempt."""
            attempts[(s, item_id)] -= 1
            queues[s].appendleft(key)

        def replace(actor, why: str, reserve: bool = True) -> None:
            """Give up on ``actor`` (its node is gone, or it never came back): its calls in flight
            go back to the queue at no cost to their items, and a new actor takes its place."""
            s, a = actor
            log.warning(f"stage {s}: worker {a} {why}; a new one takes its place{'' if reserve else ', reserving no CPU'}")
            for ref, (s_, a_, batch) in list(in_flight.items()):
                if (s_, a_) == actor:
                    del in_flight[ref]
                    load[s][a] -= 1
                    for item_id, key, _ in batch:
                        triage.finished(actor, (s, item_id), ok=False)
                        retry_free(s, item_id, key)
            for ref in [r for r, who in pings.items() if who == actor]:
                del pings[ref]
            ping_due.pop(actor, None)
            node_of.pop(actor, None)
            with contextlib.suppress(Exception):
                ray.kill(pools[s][a], no_restart=True)
            pools[s][a] = self._new_actor(s, reserve)
            triage.down.add(actor)  # takes calls once it answers its ping
            pings[pools[s][a].ping.remote()] = actor
            replaced[actor] = (time.perf_counter(), reserve)

        def check_nodes() -> None:
            """Replace every actor whose node is gone, and every replacement that never answered."""
            alive = {n["NodeID"][:12] for n in ray.nodes() if n["Alive"]}
            for actor, node in list(node_of.items()):
                if node not in alive:
                    replace(actor, f"was on node {node}, which is gone")
            now = time.perf_counter()
            for actor, (since, reserve) in list(replaced.items()):
                if reserve and now - since > REPLACE_START_S:
                    replace(actor, f"could not be placed for {REPLACE_START_S:.0f} s", reserve=False)

        def settle(s: str, item_id: str, key, attempt: int, result) -> None:
            """Record one item's outcome (an ``actors.ItemResult``) or queue its retry."""
            replay(result.logs, f"{s} {item_id}")
            out, seconds, reason, detail = result.output, result.seconds, result.reason, result.detail
            if out is None and reason == NO_SPACE:
                raise NoSpaceLeft(detail)  # not the item's fault: nothing recorded, the run stops
            if out is None and attempt < self.cfg.execution.max_attempts:
                log.warning(f"{s} {item_id}: {reason}: {detail}; trying again (attempt {attempt + 1})")
                queues[s].appendleft(key)
                return
            if out is None:
                stores[s].record(ItemRecord(item=item_id, status="failed", attempts=attempt, reason=reason, detail=detail,
                                            node=result.node), durable=False)
                self.stats.failed[s] += 1
                self._check_failures(stores, s)
            else:
                stores[s].record(_done_record(item_id, out, seconds, attempt, result.node, result.cpu_seconds), durable=False)
                if lone is None and s != group and not out.info.continues:
                    self.halted[s].add(item_id)
                self.stats.done[s] += 1
                self.stats.compute[s] += seconds
                if lone is None and s != group:
                    self._release(stores, item_id)
            queued.discard((s, item_id))
            if lone is None and s != group and not enqueue_episode(item_id, key):
                resolved(key)

        try:
            while True:
                for s in reversed(enabled):  # downstream first: finish episodes before starting new ones
                    submit(s)
                now = time.perf_counter()
                for actor, due in list(ping_due.items()):  # a dead actor is trusted again once it answers
                    if now >= due:
                        del ping_due[actor]
                        pings[pools[actor[0]][actor[1]].ping.remote()] = actor
                if not in_flight and not any(queues[s] for s in enabled):
                    break  # nothing left to do: actors still being pinged do not matter
                if now - last_node_check >= NODE_CHECK_S:
                    last_node_check = now
                    check_nodes()
                if not in_flight and not pings:
                    time.sleep(0.1)  # only pings waiting for their time
                    continue
                refs = list(in_flight) + list(pings)
                ready, _ = ray.wait(refs, num_returns=len(refs), timeout=0)  # everything that is back: one commit for all
                if not ready:
                    ready, _ = ray.wait(refs, num_returns=1, timeout=0.5)
                for ref in ready:
                    if ref not in pings and ref not in in_flight:
                        continue  # a call of an actor that was replaced meanwhile
                    if ref in pings:
                        actor = pings.pop(ref)
                        try:
                            node_of[actor] = ray.get(ref)
                            triage.up(actor)
                            replaced.pop(actor, None)
                        except ray.exceptions.RayActorError as e:
                            _refuse_unstartable(actor[0], e)
                            ping_due[actor] = time.perf_counter() + 0.5
                        continue
                    s, a, batch = in_flight.pop(ref)
                    load[s][a] -= 1
                    try:
                        results = ray.get(ref)
                    except ray.exceptions.RayActorError as e:  # the actor died: every item of the call is lost with it
                        _refuse_unstartable(s, e)
                        if (s, a) not in triage.down:  # its first lost call: ping it until it is back
                            ping_due[(s, a)] = time.perf_counter() + 0.5
                            log.warning(f"stage {s}: worker {a} died with {', '.join(i for i, _, _ in batch)} in flight "
                                        f"({type(e).__name__}); they run again, each alone, on a worker that answers")
                        for item_id, key, attempt in batch:
                            blame = triage.lost((s, a), (s, item_id))
                            triage.finished((s, a), (s, item_id), ok=False)
                            if not blame:  # lost with the actor, not (yet) known to be its fault
                                retry_free(s, item_id, key)
                                continue
                            settle(s, item_id, key, attempt, ItemResult(None, 0.0, type(e).__name__, one_line(e)))
                        continue
                    if results and results[0].node:
                        node_of[(s, a)] = results[0].node
                    for (item_id, key, attempt), result in zip(batch, results):
                        triage.finished((s, a), (s, item_id), ok=result.output is not None)
                        settle(s, item_id, key, attempt, result)
                for store in stores.values():  # durable before any work that builds on them is sent
                    store.flush()
                now = time.perf_counter()
                if now - last_print >= self.interval:
                    last_print = now
                    self._print_progress(stores, lone, len(pending))
        finally:
            for refs in pools.values():
                for actor in refs:
                    ray.kill(actor)
        self._print_progress(stores, lone, len(pending))

    def _batch_size(self, s: str) -> int:
        """Items per actor call for stage ``s``: one until a few are measured, then as many as
        make a call of about ``CALL_SECONDS`` (real stages take seconds an item: one; no-op-like
        stages: up to ``MAX_BATCH``, so Ray's cost per call is shared by many items)."""
        done = self.stats.done[s]
        if done < 4:
            return 1
        per_item = self.stats.compute[s] / done
        return int(min(MAX_BATCH, max(1, CALL_SECONDS / max(per_item, 1e-9))))

    def _release(self, stores: dict[str, ManifestStore], eid: str) -> None:
        """Let each stage that declares ``release`` slim its output of ``eid`` once the next
        stage has that episode done (re-recorded with the new checksum and payload)."""
        for i, st in enumerate(self.chain[:-1]):
            if st.release is None or not stores[self.chain[i + 1].name].done(eid):
                continue
            rec = stores[st.name].items.get(eid)
            if rec is None or rec.status != "done":
                continue
            out = st.release(self.run_dir, self.cfg, rec)
            if out is not None:
                stores[st.name].record(rec.model_copy(update={"output": out.output, "checksum": out.checksum,
                                                               "info": out.info.model_dump(mode="json")}), durable=False)

    def _print_progress(self, stores: dict[str, ManifestStore], lone: Stage | None = None, pending: int = 0) -> None:
        """One line: per enabled data stage (or the batch stage ``lone``, ``pending`` items of
        this call) items done, failed, rate and ETA."""
        if lone is not None:
            log.info(self.stats.line(lone.name, pending, 0))
            return
        lines = []
        for s in self.enabled:
            total = len(self.plan) if self.group is not None and s == self.group.name else self._planned(stores, s)
            already = self._recorded(stores, s) - self.stats.done[s] - self.stats.failed[s]
            lines.append(self.stats.line(s, total, already))
        log.info(" | ".join(lines))

    def _check_failures(self, stores: dict[str, ManifestStore], s: str) -> None:
        c = stores[s].counts
        failed, n = c.failed, c.done + c.failed
        if n >= 10 and failed / n > self.cfg.execution.max_failure_ratio:
            raise RunAborted(f"stage {s}: {failed} of {n} items failed, above execution.max_failure_ratio="
                             f"{self.cfg.execution.max_failure_ratio}; see `anchordp3 inspect {self.run_dir} {s}`")

    def _start_pools(self, enabled: list[str], most: int | None = None) -> dict[str, list]:
        """An actor pool per enabled stage (``most``: at most that many actors in a pool, for a
        batch stage with fewer items left than workers)."""
        ensure_ray(self.opts.address, self.cfg, self.graph)
        resources = ray.cluster_resources()
        gpus_available = resources.get("GPU", 0) > 0
        def pool(s: str):
            return self.graph[s].pool_of(self.cfg)

        def size(s: str) -> int:
            return min(self.opts.workers or pool(s).workers, most or math.inf)

        need = sum(pool(s).cpus * size(s) for s in enabled)
        if need > resources.get("CPU", 0) + 1e-9:
            raise ValueError(f"execution.pools: the pools reserve {need:g} CPUs but the Ray cluster has {resources.get('CPU', 0):g}; "
                             "lower workers or cpus per stage (actors hold their CPUs for the whole run)")
        pools = {}
        for s in enabled:
            pc = pool(s)
            n = size(s)
            gpus = pc.gpus if pc.gpus is not None else (1.0 / n if self.graph[s].gpu_share and gpus_available else 0.0)
            if gpus > 0 and not gpus_available:
                raise ValueError(f"execution.pools.{s}.gpus: {gpus} GPUs asked for, but the Ray cluster has none")
            # SPREAD: a pool's actors go to different nodes where they fit (on one node: no change)
            self._actor_options[s] = dict(num_cpus=pc.cpus, num_gpus=gpus, max_restarts=-1, max_task_retries=0, scheduling_strategy="SPREAD")
            pools[s] = [self._new_actor(s) for _ in range(n)]
        return pools

    def _new_actor(self, s: str, reserve: bool = True):
        """A new actor of stage ``s``'s pool; ``reserve=False``: one that reserves no CPU (it fits
        on any live node, where a cluster that lost a node has its free CPUs in pieces too small)."""
        options = self._actor_options[s] if reserve else {**self._actor_options[s], "num_cpus": 0}
        return StageWorker.options(**options).remote(self.graph[s], str(self.run_dir.resolve()), self.cfg.model_dump_json(), self.opts.faults)

    def _finish(self, stores: dict[str, ManifestStore]) -> None:
        """The group stage's finishing item, once every group is done."""
        st, store = self.group, stores[self.group.name]
        if st.finish is None or store.done(st.finish_item) or not all(store.done(_group_id(k)) for k in range(len(self.plan))):
            return
        t0 = time.perf_counter()
        out = st.finish(self.run_dir, self.cfg, [store.items[_group_id(k)] for k in range(len(self.plan))])
        store.record(_done_record(st.finish_item, out, time.perf_counter() - t0, 1))


def _refuse_unstartable(stage: str, e: Exception) -> None:
    """A worker whose constructor raised never takes a call: stop the run, naming why."""
    if getattr(e, "actor_init_failed", False):
        raise RunAborted(f"stage {stage}: its worker could not start: {one_line(e)}") from None


def _group_id(k: int) -> str:
    """Item id of group ``k`` of a group stage: ``shard/00002``."""
    return f"shard/{k:05d}"


def _done_record(item_id: str, out: StageOutput, seconds: float, attempt: int, node: str | None = None,
                 cpu_seconds: float | None = None) -> ItemRecord:
    return ItemRecord(item=item_id, status="done", output=out.output, checksum=out.checksum, seconds=seconds,
                      cpu_seconds=cpu_seconds,
                      attempts=attempt, info=out.info.model_dump(mode="json"), node=node)


class _TokenAuthNotice(logging.Filter):
    """Drops Ray's notice that a new local cluster enabled token authentication (it stays enabled)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("Token authentication is enabled")


# Ray (2.60) turns a node address of 127.0.0.1 into the machine's routable one, and its servers then
# listen on every address, unless it believes it runs on a one-machine platform (its Windows/macOS
# switch): set for a local Ray, it keeps 127.0.0.1. Processes Ray starts inherit it from the environment.
LOOPBACK_ENV = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}


def keep_ray_on_loopback() -> None:
    """Make a Ray that this process starts (``ray.init``, ``ray start``) listen on 127.0.0.1 only."""
    os.environ.update(LOOPBACK_ENV)
    import ray._private.ray_constants as constants

    constants.ENABLE_RAY_CLUSTER = False  # read when Ray was imported: set it here too


def ensure_ray(address: str | None, cfg: RunConfig | None = None, graph: Graph = GRAPH) -> None:
    """Connect to Ray: the running instance if any, a cluster at ``address`` (else at ``RAY_ADDRESS``,
    as inside a Ray Job), or a new local one with enough logical CPUs for every pool (CPU counts are
    reservations, not a speed limit). Without an address a run never joins a cluster that happens to
    run on the machine (Ray's own default would, through /tmp/ray/ray_current_cluster)."""
    if ray.is_initialized():
        return
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address:
        if address.split("://")[-1].split(":")[0] in ("127.0.0.1", "localhost"):
            keep_ray_on_loopback()  # else Ray dials the routable address, where a loopback-only cluster does not listen
        ray.init(address=address, logging_level="WARNING", log_to_driver=False)
        return
    need = 0.0
    if cfg is not None:
        pools = [st.pool_of(cfg) for st in graph.stages if not st.in_driver and (not st.batch or (st.wanted and st.wanted(cfg)))]
        need = sum(p.cpus * p.workers for p in pools)
    # A new local Ray enables token authentication by default and warns that it did: nothing a
    # user needs to act on, so that one message is dropped. It listens on loopback only.
    logging.getLogger("ray._private.authentication.authentication_token_setup").addFilter(_TokenAuthNotice())
    keep_ray_on_loopback()
    ctx = ray.init(address="local", num_cpus=max(os.cpu_count() or 1, math.ceil(need)), include_dashboard=False, logging_level="WARNING",
                   log_to_driver=False, object_store_memory=100 * 1024**2, _node_ip_address="127.0.0.1")
    watch_local_ray(ctx.address_info["session_dir"])  # its helpers go when this process dies, however it dies


def run_pipeline(cfg: RunConfig, run_dir: Path, opts: RunOptions = RunOptions(), graph: Graph = GRAPH) -> dict:
    """Run (or resume) stages of ``graph`` for ``cfg`` in ``run_dir``: ``opts.stages``, else the
    graph's targets for the config (the data stages, then training and evaluation where the config
    has their sections); returns per-stage counts."""
    check_options(cfg, opts, graph)
    from anchordp3.pipeline.inspect import check_task_names

    check_task_names(cfg)
    if opts.address or os.environ.get("RAY_ADDRESS"):
        join_cluster(opts.address, cfg, graph)  # before the run directory exists: a bad address creates nothing
    return Runner(cfg, run_dir, opts, graph).run()


def check_options(cfg: RunConfig, opts: RunOptions, graph: Graph = GRAPH) -> None:
    """Refuse ``opts`` that name stages ``graph`` lacks or that ``cfg`` has no section for, with a
    line naming the option; before anything is written."""
    unknown = [s for s in (opts.stages or ()) if s not in graph.names]
    if unknown:
        raise ValueError(f"--stages: unknown stage {unknown[0]!r}; choose from {', '.join(graph.names)}")
    unset = [s for s in (opts.stages or ()) if graph[s].batch and not (graph[s].wanted and graph[s].wanted(cfg))]
    if unset:
        section = "training" if unset[0].startswith("train") else "evaluation"
        raise ValueError(f"--stages: {unset[0]} needs the run config's {section} section (`anchordp3 train` / `anchordp3 eval` set it)")
    if opts.from_stage and opts.from_stage not in graph.names:
        raise ValueError(f"--from-stage: unknown stage {opts.from_stage!r}; choose from {', '.join(graph.names)}")


def join_cluster(address: str | None, cfg: RunConfig | None = None, graph: Graph = GRAPH) -> None:
    """``ensure_ray`` for a cluster address given by the user (``--address`` or ``RAY_ADDRESS``):
    an address Ray cannot parse or reach is a one-line error naming it."""
    try:
        ensure_ray(address, cfg, graph)
    except (ValueError, ConnectionError, TimeoutError) as e:
        given = address or os.environ.get("RAY_ADDRESS")
        raise ValueError(f"--address: cannot join the Ray cluster at {given!r} ({one_line(e)})") from None
