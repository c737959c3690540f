"""Running the data stages as streaming pools of Ray actors, with manifests and resume.

The driver (this module) owns the manifests and decides what runs; actors (``actors.py``) do the
items. An episode flows rollout → anchors → render → features as soon as each step is done;
a shard is written as soon as every episode it holds is resolved (featurised, not kept, or
failed); the dataset's index and statistics are computed when every shard is written. Work in
flight is bounded per actor, and only IDs and paths travel between processes.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import ray
import yaml

import anchordp3
from anchordp3.dataset.files import file_sha256
from anchordp3.pipeline.actors import FAULTS_ENV, StageWorker
from anchordp3.pipeline.codehash import code_hash
from anchordp3.pipeline.lock import RunLock
from anchordp3.pipeline.store import ManifestStore, StaleStageError, read_manifest
from anchordp3.pipeline.work import STAGE_CODE, stage_dir
from anchordp3.schemas.dataset import ShardMember, ShardRecord
from anchordp3.schemas.episode import episode_id
from anchordp3.schemas.manifest import Fingerprint, ItemRecord
from anchordp3.schemas.run import DATA_STAGES, RunConfig, config_hash
from anchordp3.stages.files import atomic_write_bytes
from anchordp3.stages.render import prune_frames
from anchordp3.stages.write import finalize, plan_tasks, shard_plan

EPISODE_STAGES = ("rollout", "anchors", "render", "features")
INDEX_ITEM = "dataset"  # the write stage's last item: index, statistics, dataset.json
CONFIG_FILE = "config.yaml"


class RunAborted(RuntimeError):
    """Too many items of a stage failed."""


@dataclass
class RunOptions:
    """How to run: which stages, how many workers, where, and what to redo."""

    stages: tuple[str, ...] = DATA_STAGES
    workers: int | None = None          # overrides every pool's size
    address: str | None = None          # None: a local Ray; "auto" or "ray://…": join a cluster
    force: bool = False                 # redo stages whose fingerprint changed
    keep_outputs: bool = False          # keep outputs that only other code made (same config): adopt them
    from_stage: str | None = None       # redo this stage and everything downstream
    progress_interval: float | None = None  # seconds between progress lines (None: 2 on a terminal, 15 in a log)
    faults: str = field(default_factory=lambda: os.environ.get(FAULTS_ENV, ""))


def fingerprints(cfg: RunConfig) -> dict[str, Fingerprint]:
    """Each data stage's fingerprint: code version and hash, its config part, its upstream's digest."""
    out: dict[str, Fingerprint] = {}
    prev = None
    for s in DATA_STAGES:
        up = {prev: out[prev].digest()} if prev else {}
        out[s] = Fingerprint(code_version=anchordp3.__version__, code_hash=code_hash([STAGE_CODE[s]]),
                             config_hash=config_hash(cfg.stage_config(s)), upstream=up)
        prev = s
    return out


def stage_changes(cfg: RunConfig, run_dir: Path) -> dict[str, list[str]]:
    """Stages whose stored outputs were made with another fingerprint than ``cfg`` (and this code)
    gives, in pipeline order, each with what changed (``Fingerprint.changes``)."""
    fps = fingerprints(cfg)
    out = {}
    for s in DATA_STAGES:
        d = stage_dir(run_dir, s)
        m = read_manifest(d) if d.exists() else None
        if m is not None and (changed := m.fingerprint.changes(fps[s])):
            out[s] = changed
    return out


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

    def __init__(self):
        self.t0 = time.perf_counter()
        self.done = {s: 0 for s in DATA_STAGES}
        self.failed = {s: 0 for s in DATA_STAGES}
        self.compute = {s: 0.0 for s in DATA_STAGES}

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
    """One invocation of ``anchordp3 run`` on a run directory (use ``run_pipeline``)."""

    def __init__(self, cfg: RunConfig, run_dir: Path, opts: RunOptions, say: Callable[[str], None]):
        self.cfg, self.run_dir, self.opts, self.say = cfg, Path(run_dir), opts, say
        self.fps = fingerprints(cfg)
        self.episodes = [(t, s) for t in cfg.tasks for s in cfg.seed_list]
        self.plan = shard_plan(self.episodes, cfg.write)
        self.tasks = plan_tasks(self.plan)
        self.shard_of = {(m.task, m.seed): k for k, members in enumerate(self.plan) for m in members}
        self.stats = _Stats()
        self.interval = opts.progress_interval if opts.progress_interval is not None else (2.0 if sys.stderr.isatty() else 15.0)

    # ----------------------------------------------------------------------------- setup
    def open_stores(self) -> dict[str, ManifestStore]:
        changes = stage_changes(self.cfg, self.run_dir)
        redo: set[str] = set()
        if self.opts.from_stage:
            redo |= set(DATA_STAGES[DATA_STAGES.index(self.opts.from_stage):])
        if self.opts.force:
            redo |= set(changes)
        keep = set(adoptable({s: c for s, c in changes.items() if s not in redo})) if self.opts.keep_outputs else set()
        left = {s: c for s, c in changes.items() if s not in redo and s not in keep}
        if left:
            code_only = all("config" not in c for c in left.values())
            hint = ("--force to redo them, or --keep-outputs to keep what the old code made" if code_only
                    else f"--force, or --from-stage {next(iter(left))}")
            raise StaleStageError(
                f"{self.run_dir}: stage(s) {describe_changes(left)} were made with another "
                f"{'code' if code_only else 'config or code'} than now; refusing to mix old and new outputs: rerun with {hint}")
        for s in DATA_STAGES:
            if s in keep:
                self.say(f"{s}: keeping the outputs other code made ({', '.join(changes[s])}), as --keep-outputs asks")
        return {s: ManifestStore(stage_dir(self.run_dir, s), s, self.fps[s], reset=s in redo, adopt=s in keep)
                for s in DATA_STAGES}

    def check_inputs(self, stores: dict[str, ManifestStore]) -> None:
        """A stage run without its upstream must find the upstream complete."""
        enabled = set(self.opts.stages)
        for s in self.opts.stages:
            i = DATA_STAGES.index(s)
            if i == 0 or DATA_STAGES[i - 1] in enabled:
                continue
            up = DATA_STAGES[i - 1]
            m = stores[up].manifest
            if not m.complete:
                raise ValueError(f"stage {s}: its input stage {up} is not complete ({m.counts.done} done, "
                                 f"{m.counts.failed} failed of {m.counts.planned}); run {up} first or both together")

    # ----------------------------------------------------------------------------- episode flow
    def next_stage(self, stores: dict[str, ManifestStore], ep: tuple[str, int]) -> str | None:
        """The stage ``ep`` needs next, or None when it is resolved."""
        eid = episode_id(*ep)
        for s in EPISODE_STAGES:
            r = stores[s].items.get(eid)
            if r is None:
                return s
            if r.status == "failed":
                return None
            if s == "rollout" and not r.info.get("kept"):
                return None
        return None

    def episode_ok(self, stores: dict[str, ManifestStore], ep: tuple[str, int]) -> bool:
        return stores["features"].done(episode_id(*ep))

    def item_payload(self, stores: dict[str, ManifestStore], stage: str, ep: tuple[str, int]) -> dict:
        item = {"task": ep[0], "seed": ep[1]}
        if stage in ("anchors", "render"):
            item["record"] = stores["rollout"].items[episode_id(*ep)].info["record"]
        return item

    def shard_payload(self, stores: dict[str, ManifestStore], k: int) -> dict:
        members, failed = [], []
        for m in self.plan[k]:
            ep = (m.task, m.seed)
            rec = stores["rollout"].items.get(episode_id(*ep))
            text = rec.info["record"]["instruction"] if rec is not None and rec.status == "done" else ""
            members.append(ShardMember(task=m.task, seed=m.seed, episode_index=m.episode_index, task_id=m.task_id,
                                       instruction=text).model_dump(mode="json"))
            if not self.episode_ok(stores, ep):
                failed.append([m.task, m.seed])
        return {"shard": k, "members": members, "failed": failed, "tasks": self.tasks}

    # ----------------------------------------------------------------------------- the run
    def run(self) -> dict:
        with RunLock(self.run_dir):
            stores = self.open_stores()
            try:
                self.check_inputs(stores)
                atomic_write_bytes(self.run_dir / CONFIG_FILE, yaml.safe_dump(self.cfg.model_dump(mode="json"), sort_keys=False).encode())
                self._loop(stores)
                if "write" in self.opts.stages:
                    self._finalize(stores)
            finally:
                for s, st in stores.items():
                    st.compact(self._planned(stores, s), self._complete(stores, s))
            return {s: stores[s].manifest.counts.model_dump() for s in DATA_STAGES}

    def _planned(self, stores: dict[str, ManifestStore], s: str) -> int:
        if s == "rollout":
            return len(self.episodes)
        if s == "write":
            return len(self.plan) + 1
        prev = EPISODE_STAGES[EPISODE_STAGES.index(s) - 1]
        recs = [stores[prev].items.get(episode_id(*ep)) for ep in self.episodes]
        if prev == "rollout":
            return sum(1 for r in recs if r is not None and r.status == "done" and r.info.get("kept"))
        return sum(1 for r in recs if r is not None and r.status == "done")

    def _complete(self, stores: dict[str, ManifestStore], s: str) -> bool:
        if s == "write":
            return stores["write"].done(INDEX_ITEM)
        upstream_complete = s == "rollout" or self._complete(stores, EPISODE_STAGES[EPISODE_STAGES.index(s) - 1])
        items = stores[s].items
        return upstream_complete and len(items) >= self._planned(stores, s) and (s != "rollout" or len(items) == len(self.episodes))

    def _loop(self, stores: dict[str, ManifestStore]) -> None:
        enabled = [s for s in DATA_STAGES if s in self.opts.stages]
        queues: dict[str, deque] = {s: deque() for s in DATA_STAGES}
        queued: set[tuple[str, str]] = set()
        shards_left = {k for k in range(len(self.plan)) if not stores["write"].done(f"shard/{k:05d}")}

        def enqueue_episode(ep):
            s = self.next_stage(stores, ep)
            if s in enabled and (s, episode_id(*ep)) not in queued:
                queues[s].append(ep)
                queued.add((s, episode_id(*ep)))

        def enqueue_ready_shards(candidates):
            """Queue the shards among ``candidates`` whose every episode is resolved."""
            if "write" not in enabled:
                return
            for k in sorted(candidates & shards_left):
                if ("write", str(k)) in queued:
                    continue
                if all(self.next_stage(stores, (m.task, m.seed)) is None for m in self.plan[k]):
                    queues["write"].append(k)
                    queued.add(("write", str(k)))

        for ep in self.episodes:
            if stores["features"].done(episode_id(*ep)):
                self._prune(stores, episode_id(*ep))  # finishes a prune a crash interrupted
            enqueue_episode(ep)
        enqueue_ready_shards(set(shards_left))
        if not any(queues.values()):
            return

        pools = self._start_pools(enabled, queues)
        in_flight: dict = {}  # ObjectRef → (stage, item id, key, attempt, actor index)
        load = {s: [0] * len(pools.get(s, [])) for s in DATA_STAGES}
        triage = CrashTriage()
        pings: dict = {}      # ObjectRef of a ping → actor (stage, index) that died
        ping_due: dict = {}   # actor → when to ping it (again)
        attempts: dict[tuple[str, str], int] = {}
        last_print = 0.0
        cap = self.cfg.execution.in_flight_per_worker
        try:
            while True:
                for s in reversed(enabled):  # downstream first: finish episodes before starting new ones
                    while queues[s] and pools.get(s):
                        key = queues[s][0]
                        item_id = f"shard/{key:05d}" if s == "write" else episode_id(*key)
                        free = [a for a in range(len(load[s])) if triage.can_take((s, a), (s, item_id), load[s][a], cap)]
                        if not free:
                            break
                        queues[s].popleft()
                        payload = self.shard_payload(stores, key) if s == "write" else self.item_payload(stores, s, key)
                        a = min(free, key=lambda i: load[s][i])
                        attempt = attempts.get((s, item_id), 0) + 1
                        attempts[(s, item_id)] = attempt
                        ref = pools[s][a].run.remote(item_id, payload, attempt)
                        in_flight[ref] = (s, item_id, key, attempt, a)
                        triage.submitted((s, a), (s, item_id))
                        load[s][a] += 1
                now = time.perf_counter()
                for actor, due in list(ping_due.items()):  # a dead actor is trusted again once it answers
                    if now >= due:
                        del ping_due[actor]
                        pings[pools[actor[0]][actor[1]].ping.remote()] = actor
                if not in_flight and not pings and not ping_due:
                    break
                if not in_flight and not pings:
                    time.sleep(0.1)  # only pings waiting for their time
                    continue
                ready, _ = ray.wait(list(in_flight) + list(pings), num_returns=1, timeout=0.5)
                for ref in ready:
                    if ref in pings:
                        actor = pings.pop(ref)
                        try:
                            ray.get(ref)
                            triage.up(actor)
                        except ray.exceptions.RayActorError:
                            ping_due[actor] = time.perf_counter() + 0.5
                        continue
                    s, item_id, key, attempt, a = in_flight.pop(ref)
                    load[s][a] -= 1
                    try:
                        res = ray.get(ref)
                    except Exception as e:  # noqa: BLE001 - any item failure is retried, then recorded
                        if isinstance(e, ray.exceptions.RayActorError):
                            if (s, a) not in triage.down:  # its first lost call: ping it until it is back
                                ping_due[(s, a)] = time.perf_counter() + 0.5
                            blame = triage.lost((s, a), (s, item_id))
                            triage.finished((s, a), (s, item_id), ok=False)
                            if not blame:  # lost with the actor, not (yet) known to be its fault
                                attempts[(s, item_id)] -= 1
                                queues[s].appendleft(key)
                                continue
                        else:
                            triage.finished((s, a), (s, item_id), ok=False)
                        if attempt < self.cfg.execution.max_attempts:
                            queues[s].appendleft(key)
                            continue
                        cause = getattr(e, "cause", None) or e
                        detail = (str(cause).strip().splitlines() or [type(cause).__name__])[-1][:300]
                        stores[s].record(ItemRecord(item=item_id, status="failed", attempts=attempt,
                                                    reason=type(cause).__name__, detail=detail))
                        self.stats.failed[s] += 1
                        self._check_failures(stores, s)
                    else:
                        triage.finished((s, a), (s, item_id), ok=True)
                        stores[s].record(ItemRecord(item=item_id, status="done", output=res["output"], checksum=res["checksum"],
                                                    seconds=res["seconds"], attempts=attempt, info=res["info"]))
                        if s == "features":
                            self._prune(stores, item_id)
                        self.stats.done[s] += 1
                        self.stats.compute[s] += res["seconds"]
                    queued.discard((s, str(key) if s == "write" else item_id))
                    if s == "write":
                        shards_left.discard(key)
                    else:
                        enqueue_episode(key)
                        enqueue_ready_shards({self.shard_of[key]})  # only the finished episode's shard can have become ready
                now = time.perf_counter()
                if now - last_print >= self.interval:
                    last_print = now
                    self._print_progress(stores, enabled)
        finally:
            for refs in pools.values():
                for actor in refs:
                    ray.kill(actor)
        self._print_progress(stores, enabled)

    def _prune(self, stores: dict[str, ManifestStore], eid: str) -> None:
        """With ``render.keep_frames: false``, drop a featurised episode's images and re-record
        the render item with the slim file's checksum."""
        rec = stores["render"].items.get(eid)
        if self.cfg.render.keep_frames or rec is None or rec.info.get("pruned"):
            return
        path = stage_dir(self.run_dir, "render") / rec.output
        prune_frames(path)
        stores["render"].record(rec.model_copy(update={"checksum": file_sha256(path), "info": {**rec.info, "pruned": True}}))

    def _print_progress(self, stores: dict[str, ManifestStore], enabled: list[str]) -> None:
        lines = []
        for s in enabled:
            total = self._planned(stores, s) if s != "write" else len(self.plan)
            already = len(stores[s].items) - self.stats.done[s] - self.stats.failed[s]
            lines.append(self.stats.line(s, total, already))
        self.say(" | ".join(lines))

    def _check_failures(self, stores: dict[str, ManifestStore], s: str) -> None:
        c = stores[s].manifest.items.values()
        failed = sum(r.status == "failed" for r in c)
        n = len(stores[s].manifest.items)
        if n >= 10 and failed / n > self.cfg.execution.max_failure_ratio:
            raise RunAborted(f"stage {s}: {failed} of {n} items failed, above execution.max_failure_ratio="
                             f"{self.cfg.execution.max_failure_ratio}; see `anchordp3 inspect {self.run_dir} {s}`")

    def _start_pools(self, enabled: list[str], queues: dict[str, deque]) -> dict[str, list]:
        ensure_ray(self.opts.address, self.cfg)
        resources = ray.cluster_resources()
        gpus_available = resources.get("GPU", 0) > 0
        need = sum(getattr(self.cfg.execution.pools, s).cpus * (self.opts.workers or getattr(self.cfg.execution.pools, s).workers) for s in enabled)
        if need > resources.get("CPU", 0) + 1e-9:
            raise ValueError(f"execution.pools: the pools reserve {need:g} CPUs but the Ray cluster has {resources.get('CPU', 0):g}; "
                             "lower workers or cpus per stage (actors hold their CPUs for the whole run)")
        pools = {}
        for s in enabled:
            pc = getattr(self.cfg.execution.pools, s)
            n = self.opts.workers or pc.workers
            gpus = pc.gpus if pc.gpus is not None else (1.0 / n if s == "render" and gpus_available else 0.0)
            if gpus > 0 and not gpus_available:
                raise ValueError(f"execution.pools.{s}.gpus: {gpus} GPUs asked for, but the Ray cluster has none")
            pools[s] = [StageWorker.options(num_cpus=pc.cpus, num_gpus=gpus, max_restarts=-1, max_task_retries=0)
                        .remote(s, str(self.run_dir.resolve()), self.cfg.model_dump_json(), self.opts.faults) for _ in range(n)]
        return pools

    def _finalize(self, stores: dict[str, ManifestStore]) -> None:
        st = stores["write"]
        if st.done(INDEX_ITEM) or not all(st.done(f"shard/{k:05d}") for k in range(len(self.plan))):
            return
        t0 = time.perf_counter()
        records = [ShardRecord.model_validate(st.items[f"shard/{k:05d}"].info["shard"]) for k in range(len(self.plan))]
        info = finalize(stage_dir(self.run_dir, "write"), records, self.cfg.write)
        st.record(ItemRecord(item=INDEX_ITEM, status="done", output="dataset.json",
                             checksum=file_sha256(stage_dir(self.run_dir, "write") / "dataset.json"),
                             seconds=time.perf_counter() - t0, info={"samples": info.counts.samples, "episodes": info.counts.episodes}))


class _TokenAuthNotice(logging.Filter):
    """Drops Ray's notice that a new local cluster enabled token authentication (it stays enabled)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("Token authentication is enabled")


def ensure_ray(address: str | None, cfg: RunConfig | None = None) -> None:
    """Connect to Ray: the running instance if any, a cluster at ``address``, or a new local one
    with enough logical CPUs for every pool (CPU counts are reservations, not a speed limit)."""
    if ray.is_initialized():
        return
    if address:
        ray.init(address=address, logging_level="WARNING", log_to_driver=False)
        return
    need = 0.0
    if cfg is not None:
        need = sum(getattr(cfg.execution.pools, s).cpus * getattr(cfg.execution.pools, s).workers for s in DATA_STAGES)
    # A new local Ray enables token authentication by default and warns that it did: nothing a
    # user needs to act on, so that one message is dropped. It listens on loopback only.
    logging.getLogger("ray._private.authentication.authentication_token_setup").addFilter(_TokenAuthNotice())
    ray.init(num_cpus=max(os.cpu_count() or 1, math.ceil(need)), include_dashboard=False, logging_level="WARNING",
             log_to_driver=False, object_store_memory=100 * 1024**2, _node_ip_address="127.0.0.1")


def run_pipeline(cfg: RunConfig, run_dir: Path, opts: RunOptions = RunOptions(), say: Callable[[str], None] = lambda m: print(m, file=sys.stderr)) -> dict:
    """Run (or resume) the data stages of ``cfg`` in ``run_dir``; returns per-stage counts."""
    unknown = [s for s in opts.stages if s not in DATA_STAGES]
    if unknown:
        raise ValueError(f"--stages: unknown stage {unknown[0]!r}; choose from {', '.join(DATA_STAGES)}")
    if opts.from_stage and opts.from_stage not in DATA_STAGES:
        raise ValueError(f"--from-stage: unknown stage {opts.from_stage!r}; choose from {', '.join(DATA_STAGES)}")
    from anchordp3.pipeline.inspect import check_task_names

    check_task_names(cfg)
    return Runner(cfg, run_dir, opts, say).run()
