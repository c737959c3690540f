"""Ray actors that run stage items; the only module besides ``runner`` that touches Ray.

An actor lives for the whole run, so per-process state (the SAPIEN renderer and its compiled
shaders, imported libraries) is paid once per worker, not once per item.

Fault injection for tests and drills: ``ANCHORDP3_INJECT_FAULTS="stage:item:n[:crash],…"`` makes
the first ``n`` attempts of ``item`` raise (or, with ``crash``, kill the worker process).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import NamedTuple

import ray

from anchordp3.logs import Capture, WorkerRecord
from anchordp3.pipeline.graph import Stage, StageOutput
from anchordp3.schemas.run import RunConfig
from anchordp3.stages.files import no_space

FAULTS_ENV = "ANCHORDP3_INJECT_FAULTS"
NO_SPACE = "NoSpace"  # ``ItemResult.reason`` of an item whose output did not fit on the disk


class InjectedFault(RuntimeError):
    """A failure injected on purpose (``ANCHORDP3_INJECT_FAULTS``)."""


def parse_faults(text: str) -> dict[tuple[str, str], tuple[int, bool]]:
    """``"render:place_mouse/000001:2:crash,…"`` → {(stage, item): (attempts to fail, crash)}."""
    out = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        bits = part.split(":")
        if len(bits) not in (3, 4) or not bits[2].isdigit() or (len(bits) == 4 and bits[3] != "crash"):
            raise ValueError(f"{FAULTS_ENV}: expected stage:item:n[:crash], got {part!r}")
        out[(bits[0], bits[1])] = (int(bits[2]), len(bits) == 4)
    return out


class ItemResult(NamedTuple):
    """What a worker sends back for one item: its output, wall and CPU seconds, or (``output``
    None) the exception's type and last line; and the messages logged while it ran."""

    output: StageOutput | None
    seconds: float
    reason: str | None = None
    detail: str = ""
    logs: tuple[WorkerRecord, ...] = ()
    node: str | None = None  # the Ray node the worker runs on (``node_id``)
    cpu_seconds: float | None = None  # the worker process's CPU time (all its threads) for the item


def node_id() -> str:
    """This process's Ray node: the first 12 hex digits of its node ID (as ``ray.nodes()`` has it)."""
    return ray.get_runtime_context().get_node_id()[:12]


def one_line(e: BaseException) -> str:
    """The last line of an exception's message (its type when it has none), at most 300 characters."""
    return (str(e).strip().splitlines() or [type(e).__name__])[-1][:300]


@ray.remote
class StageWorker:
    """Runs items of one declared stage (``graph.Stage``) for one run directory."""

    def __init__(self, stage: Stage, run_dir: str, cfg_json: str, faults: str = ""):
        self.stage, self.run_dir = stage, Path(run_dir)
        self.cfg = RunConfig.model_validate_json(cfg_json)
        self.faults = parse_faults(faults)

    def run(self, item_id: str, item, attempt: int) -> tuple[StageOutput, float, float]:
        """Do one item (an ``EpisodeItem`` or ``GroupItem``): its output, wall seconds and CPU
        seconds (this process, every thread: a renderer's worker threads count too, so the CPU
        time is the item's cost whatever else shares the machine). Raises whatever the stage raises."""
        n, crash = self.faults.get((self.stage.name, item_id), (0, False))
        if attempt <= n:
            if crash:
                os._exit(1)
            raise InjectedFault(f"injected fault in {self.stage.name} {item_id} (attempt {attempt})")
        t0, c0 = time.perf_counter(), time.process_time()
        out = self.stage.run(self.run_dir, self.cfg, item)
        return out, time.perf_counter() - t0, time.process_time() - c0

    def run_many(self, calls: list[tuple[str, object, int]]) -> list[ItemResult]:
        """Do each ``(item id, item, attempt)`` in turn (an item that raises does not stop the
        others): per item its ``ItemResult``, with what was logged while it ran."""
        out, node = [], node_id()
        for item_id, item, attempt in calls:
            with Capture() as cap:
                try:
                    res, seconds, cpu = self.run(item_id, item, attempt)
                    result = ItemResult(res, seconds, cpu_seconds=cpu)
                except Exception as e:  # noqa: BLE001 - the driver retries, then records the failure
                    full = no_space(e, Path(self.run_dir) / self.stage.folder)  # a file under it, where the error does not say which
                    result = ItemResult(None, 0.0, NO_SPACE, full) if full else ItemResult(None, 0.0, type(e).__name__, one_line(e))
            out.append(result._replace(logs=tuple(cap.records), node=node))
        return out

    def ping(self) -> str:
        """This worker's node (``node_id``): it answers once it is up."""
        return node_id()
