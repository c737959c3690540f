"""The declared stage graph and the generic runner over it, on a real Ray with synthetic stages:
episodes stop where a record says so, groups wait for their members, a stage added to a graph
runs with nothing else changed, and a finished run redoes nothing."""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest
from pydantic import Field
from ray import cloudpickle

from anchordp3.pipeline.graph import EpisodeItem, Graph, Stage, StageOutput
from anchordp3.pipeline.noop import NOOP_GROUP, NOOP_STOP_EVERY, NoopFinalInfo, NoopFirstInfo, NoopGroupInfo, NoopStepInfo, noop_graph
from anchordp3.pipeline.graph import fingerprints
from anchordp3.pipeline.runner import RunOptions, run_pipeline, stage_changes
from anchordp3.pipeline.store import read_manifest
from anchordp3.pipeline.work import DATA_GRAPH
from anchordp3.schemas.records import Payload, RolloutInfo
from anchordp3.schemas.run import PoolConfig, RunConfig

CFG = RunConfig(name="graph", tasks=["place_mouse", "place_bell"], seeds="0-39")


def _records(run: Path, graph: Graph, stage: str) -> dict:
    return read_manifest(run / graph[stage].folder).items


def test_the_data_graph_declares_the_five_stages_in_order():
    assert DATA_GRAPH.names == ("rollout", "anchors", "render", "features", "write")
    assert DATA_GRAPH.group_stage.name == "write" and DATA_GRAPH["render"].needs == (RolloutInfo,)
    assert DATA_GRAPH.producer(RolloutInfo) == "rollout" and DATA_GRAPH["write"].folder == "dataset"


def test_a_graph_that_needs_a_later_stage_or_groups_before_the_end_is_refused():
    first, step, group = noop_graph(2).stages
    with pytest.raises(ValueError, match="needs"):
        Graph((step, first, group))
    with pytest.raises(ValueError, match="last stage"):
        Graph((first, group, step))


def test_episodes_stop_where_a_record_says_and_groups_count_what_went_through(ray_session, tmp_path):
    graph = noop_graph(3)
    counts = run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60), graph=graph)
    n = 2 * 40
    stopped = {f"{t}/{s:06d}" for t in CFG.tasks for s in range(40) if s % NOOP_STOP_EVERY == 0}
    first = _records(tmp_path, graph, "noop0")
    assert len(first) == n and {i for i, r in first.items() if not r.payload(NoopFirstInfo).kept} == stopped
    for stage in ("noop1", "noop2"):
        recs = _records(tmp_path, graph, stage)
        assert set(recs) == set(first) - stopped  # the stopped episodes went no further
        assert all(r.payload(NoopStepInfo).seed == int(i.rsplit("/", 1)[1]) for i, r in recs.items())
    groups = _records(tmp_path, graph, "noop_group")
    final = groups.pop("final").payload(NoopFinalInfo)
    assert len(groups) == n // NOOP_GROUP and final.groups == len(groups) and final.episodes == n - len(stopped)
    assert sum(r.payload(NoopGroupInfo).episodes for r in groups.values()) == n - len(stopped)
    assert counts["noop2"]["done"] == n - len(stopped)
    before = {s: read_manifest(tmp_path / graph[s].folder).model_dump() for s in graph.names}
    run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60), graph=graph)  # finished: nothing redone
    assert {s: read_manifest(tmp_path / graph[s].folder).model_dump() for s in graph.names} == before


class TagInfo(Payload):
    tag: str = Field(description="What the added stage made of the first stage's payload.")


def _tag(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    (run / "tags").mkdir(exist_ok=True)
    (run / "tags" / f"{item.task}-{item.seed}.txt").write_text(f"seed {item.get(NoopFirstInfo).seed}")
    return StageOutput(f"{item.task}-{item.seed}.txt", None, TagInfo(tag=f"{item.task}:{item.seed}"))


def test_a_stage_added_to_a_graph_runs_with_nothing_else_changed(ray_session, tmp_path):
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the actors cannot import a test module
    first, step, group = noop_graph(2).stages
    tag = Stage("tag", "tags", _tag, TagInfo, __name__, lambda cfg: {}, needs=(NoopFirstInfo,), resources=PoolConfig(cpus=0.1))
    graph = Graph((first, tag, step, group))  # the one change: one more Stage in the list
    run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60), graph=graph)
    tags = _records(tmp_path, graph, "tag")
    assert len(tags) == 2 * 40 - 8 and tags["place_bell/000003"].payload(TagInfo).tag == "place_bell:3"
    assert (tmp_path / "tags" / "place_bell-3.txt").read_text() == "seed 3"
    assert set(_records(tmp_path, graph, "noop1")) == set(tags)  # the stage after it runs on what it passed on


def test_a_run_fingerprinted_under_a_former_config_layout_is_restamped_not_redone(ray_session, tmp_path):
    first, step, group = noop_graph(2).stages
    old_part = lambda cfg: {"tasks": cfg.tasks, "layout": 1}  # noqa: E731
    old = Graph((replace(first, config=old_part), step, group))
    run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60), graph=old)
    before = {s: read_manifest(tmp_path / old[s].folder) for s in old.names}
    new = Graph((first, step, group), former=(lambda cfg: {"noop0": old_part(cfg)},))
    assert stage_changes(CFG, tmp_path, Graph((first, step, group))) != {}  # without the former layout: stale
    assert stage_changes(CFG, tmp_path, new) == {}  # with it: the same outputs
    run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60), graph=new)  # no --force needed
    after = {s: read_manifest(tmp_path / new[s].folder) for s in new.names}
    fps = fingerprints(CFG, new)
    for s in new.names:
        assert after[s].items == before[s].items  # nothing redone
        assert after[s].fingerprint == fps[s] != before[s].fingerprint  # re-stamped for the new layout
    other = CFG.model_copy(update={"tasks": ["place_mouse"]})  # another config is no former layout of this one
    assert "config" in stage_changes(other, tmp_path, new)["noop0"]


class MadeInfo(Payload):
    unconsumed: int = Field(ge=0, description="Outputs made but not yet consumed when this item started.")


def _make(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    made, used = run / "made", run / "used"
    made.mkdir(exist_ok=True)
    used.mkdir(exist_ok=True)
    unconsumed = len({p.name for p in made.iterdir()} - {p.name for p in used.iterdir()})
    time.sleep(0.05)  # an item per actor call (no batching)
    (made / f"{item.task}-{item.seed}").touch()
    return StageOutput(None, None, MadeInfo(unconsumed=unconsumed))


def _consume(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    time.sleep(0.2)  # four times slower than the stage before it
    (run / "used" / f"{item.task}-{item.seed}").touch()
    return StageOutput(None, None, NoopStepInfo(seed=item.seed))


def test_a_stage_with_transient_outputs_stays_a_few_items_ahead_of_its_consumer(ray_session, tmp_path):
    """A stage whose outputs are released once consumed (the render stage's frames) waits while its
    consumer has two calls per actor queued: its unconsumed outputs stay bounded (their disk)."""
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    light = PoolConfig(workers=1, cpus=0.1)
    make = Stage("make", "make", _make, MadeInfo, __name__, lambda cfg: {}, resources=light, release=lambda run, cfg, rec: None)
    consume = Stage("consume", "consume", _consume, NoopStepInfo, __name__, lambda cfg: {}, resources=light)
    graph = Graph((make, consume, noop_graph(1).stages[-1]))
    cfg = CFG.model_copy(update={"seeds": "0-9"})
    run_pipeline(cfg, tmp_path, RunOptions(progress_interval=60), graph=graph)
    made = _records(tmp_path, graph, "make")
    assert len(made) == 20 and len(_records(tmp_path, graph, "consume")) == 20
    cap = cfg.execution.in_flight_per_worker
    assert max(r.payload(MadeInfo).unconsumed for r in made.values()) <= 2 * cap + 1


class CountInfo(Payload):
    n: int = Field(description="The item's number.")


def _count(run: Path, cfg: RunConfig, item) -> StageOutput:
    """A batch stage's item: writes its number into the stage folder."""
    (item.folder / f"{item.id}.txt").write_text(item.id)
    return StageOutput(f"{item.id}.txt", None, CountInfo(n=int(item.id)))


def _count_report(ctx, cfg: RunConfig, records: dict) -> None:
    (ctx.folder / "report.txt").write_text(",".join(sorted(records)))


def _fixed(fp: str):
    from anchordp3.schemas.manifest import Fingerprint

    return lambda ctx, cfg: Fingerprint(code_version="0", code_hash="", config_hash=fp, upstream={})


def _batch(name: str, fp: str = "a", in_driver: bool = False, after: tuple[str, ...] = ("noop_group",)) -> Stage:
    return Stage(name, name, _count, CountInfo, __name__, lambda cfg: {}, items=lambda cfg: [f"{i}" for i in range(6)],
                 after=after, fingerprint=_fixed(fp), wanted=lambda cfg: True, report=_count_report,
                 in_driver=in_driver, resources=PoolConfig(workers=2, cpus=0.1))


def test_batch_stages_follow_the_data_through_the_same_runner_with_retries_resume_and_force(ray_session, tmp_path, monkeypatch):
    from anchordp3.logs import Capture
    from anchordp3.pipeline.actors import FAULTS_ENV
    from anchordp3.pipeline.store import StaleStageError

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    first, step, group = noop_graph(2).stages
    graph = Graph((first, step, group, _batch("counted"), _batch("local", in_driver=True, after=("counted",))))
    assert graph.targets(CFG) == graph.names and graph.batch_stages[0].name == "counted"
    monkeypatch.setenv(FAULTS_ENV, "counted:3:1,counted:4:1:crash")  # one item raises once, one kills its worker once
    with Capture() as cap:
        counts = run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60), graph=graph)
    monkeypatch.delenv(FAULTS_ENV)
    assert counts["counted"]["done"] == 6 and counts["local"]["done"] == 6 and counts["noop_group"]["done"] > 0
    recs = _records(tmp_path, graph, "counted")
    assert recs["3"].attempts == 2 and recs["4"].status == "done" and recs["5"].payload(CountInfo).n == 5
    assert (tmp_path / "counted" / "report.txt").read_text() == "0,1,2,3,4,5"
    assert any("worker" in r.message and "died with" in r.message for r in cap.records)
    with Capture() as cap:  # resumed: nothing redone
        run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60, stages=("counted", "local")), graph=graph)
    assert any("counted: 6 items (6 already done)" in r.message for r in cap.records)
    changed = Graph((first, step, group, _batch("counted", fp="b"), _batch("local", in_driver=True, after=("counted",))))
    with pytest.raises(StaleStageError, match="counted.*--force"):
        run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60, stages=("counted",)), graph=changed)
    run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60, stages=("counted",), force=True), graph=changed)
    assert read_manifest(tmp_path / "counted").complete and _records(tmp_path, changed, "counted")["3"].attempts == 1


def test_a_batch_stage_waits_for_its_inputs_and_batch_stages_come_last():
    first, step, group = noop_graph(2).stages
    with pytest.raises(ValueError, match="batch stages come after"):
        Graph((first, _batch("counted"), step, group))
    with pytest.raises(ValueError, match="comes after"):
        Graph((first, step, group, _batch("counted", after=("nowhere",))))


def test_a_run_config_s_sections_choose_what_a_run_does(tmp_path):
    from anchordp3.pipeline.products import GRAPH

    data = ("rollout", "anchors", "render", "features", "write")
    assert GRAPH.targets(CFG) == data
    trained = RunConfig.model_validate({**CFG.model_dump(mode="json"), "training": {}, "evaluation": {"train_episodes": 2}})
    assert GRAPH.targets(trained) == data + ("train-segmenter", "train-classifier", "train-policy", "evaluate", "evaluate-train")
    with pytest.raises(ValueError, match="train-policy needs the run config's training section"):
        run_pipeline(CFG, tmp_path / "run", RunOptions(stages=("train-policy",)))
    assert not (tmp_path / "run").exists()  # refused before anything was made


def _counted(run: Path, key: str) -> None:
    """Append one line to ``runs.txt`` per execution of an item (``key``)."""
    with open(run / "runs.txt", "a") as f:
        f.write(key + "\n")


def _first_counted(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    _counted(run, f"first {item.task}/{item.seed}")
    return StageOutput(None, None, NoopFirstInfo(seed=item.seed, kept=True))


def _step_counted(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    _counted(run, f"step {item.task}/{item.seed}")
    return StageOutput(None, None, NoopStepInfo(seed=item.seed))


def _group_counted(run: Path, cfg: RunConfig, item) -> StageOutput:
    _counted(run, f"group {item.index}")
    return StageOutput(None, None, NoopGroupInfo(episodes=sum(ep.ok for ep in item.episodes)))


def test_a_change_to_one_task_s_code_makes_that_task_s_items_again_and_keeps_the_others(ray_session, tmp_path, monkeypatch):
    import anchordp3.pipeline.graph as graph_module

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    first, step, group = noop_graph(2).stages
    graph = Graph((replace(first, run=_first_counted), replace(step, run=_step_counted), replace(group, run=_group_counted)))
    hashes = {"place_mouse": "mouse-1", "place_bell": "bell-1"}  # as task_hashes reads each task's module
    real = graph_module.stage_hashes
    monkeypatch.setattr(graph_module, "stage_hashes", lambda entries, tasks, root=None: (real(entries, tasks, root)[0], {t: hashes[t] for t in tasks}))
    cfg = CFG.model_copy(update={"seeds": "0-19"})  # bell 0-19, then mouse 0-19: groups of 16 are bell, bell+mouse, mouse
    run_pipeline(cfg, tmp_path, RunOptions(progress_interval=60), graph=graph)
    first_runs = (tmp_path / "runs.txt").read_text().splitlines()
    assert len(first_runs) == 2 * 40 + 3
    final = _records(tmp_path, graph, "noop_group")["final"]

    hashes["place_bell"] = "bell-2"  # the bell's expert changed
    assert stage_changes(cfg, tmp_path, graph) == {s: ["task place_bell"] for s in graph.names}
    run_pipeline(cfg, tmp_path, RunOptions(progress_interval=60), graph=graph)  # no --force needed
    again = (tmp_path / "runs.txt").read_text().splitlines()[len(first_runs):]
    assert sorted(again) == sorted([f"first place_bell/{s}" for s in range(20)] + [f"step place_bell/{s}" for s in range(20)]
                                   + ["group 0", "group 1"])
    assert stage_changes(cfg, tmp_path, graph) == {}
    groups = _records(tmp_path, graph, "noop_group")
    assert groups["final"].payload(NoopFinalInfo) == final.payload(NoopFinalInfo)  # finished again, the same
    assert all(read_manifest(tmp_path / graph[s].folder).complete for s in graph.names)

    hashes["place_mouse"] = "mouse-2"
    run_pipeline(cfg, tmp_path, RunOptions(progress_interval=60, keep_outputs=True), graph=graph)  # kept as made
    assert len((tmp_path / "runs.txt").read_text().splitlines()) == len(first_runs) + len(again)
    assert stage_changes(cfg, tmp_path, graph) == {}
