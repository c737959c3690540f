"""The data stages, declared once: ``DATA_GRAPH`` (rollout → anchors → render → features → write).

Each stage's item function is a thin adapter from the runner's typed item (``graph.EpisodeItem``,
``graph.GroupItem``) to the stage's plain function in ``anchordp3.stages``, returning its output
path, checksum and typed payload (``schemas.records``). The Ray actors in ``actors.py`` call them;
nothing here knows about Ray. Each adapter imports its stage's code when it first runs, so reading
the graph (``status``, ``inspect``) loads no simulator, geometry or dataset writer.
"""

from __future__ import annotations

from pathlib import Path

from anchordp3.dataset.files import file_sha256
from anchordp3.pipeline.graph import EpisodeItem, Graph, GroupItem, Stage, StageOutput
from anchordp3.schemas.dataset import ShardMember
from anchordp3.schemas.manifest import ItemRecord
from anchordp3.schemas.records import AnchorsInfo, FeaturesInfo, IndexInfo, RenderInfo, RolloutInfo, ShardInfo
from anchordp3.schemas.run import RunConfig
from anchordp3.stages.files import frames_file, plan_file


def _rollout(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    from anchordp3.stages.rollout import rollout

    d = stage_dir(run, "rollout")
    rec = rollout(item.task, item.seed, cfg.world(), cfg.preset, d)
    checksum = file_sha256(d / rec.arrays) if rec.arrays else None
    return StageOutput(rec.arrays, checksum, RolloutInfo(kept=rec.success, record=rec))


def _anchors(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    from anchordp3.stages.anchors import load_plan, run_anchors

    d = stage_dir(run, "anchors")
    rel = run_anchors(item.get(RolloutInfo).record, stage_dir(run, "rollout"), d, cfg.anchors)
    plan = load_plan(d / rel)
    return StageOutput(rel, file_sha256(d / rel),
                       AnchorsInfo(frames=len(plan), dagger=int(sum(k == "dagger" for k in plan.kind)), anchors=len(plan.anchor_t)))


def _render(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    from anchordp3.stages.render import run_render

    d = stage_dir(run, "render")
    rec = item.get(RolloutInfo).record
    plan = stage_dir(run, "anchors") / plan_file(rec.task, rec.seed)
    rel = run_render(rec, stage_dir(run, "rollout"), plan, d, cfg.world(), cfg.render, cfg.anchors)
    return StageOutput(rel, file_sha256(d / rel), RenderInfo())


def _release_frames(run: Path, cfg: RunConfig, rec: ItemRecord) -> StageOutput | None:
    """With ``render.keep_frames: false``, drop a featurised episode's images (the slim file's
    checksum and ``pruned`` go into the render record)."""
    if cfg.render.keep_frames or rec.payload(RenderInfo).pruned:
        return None
    from anchordp3.stages.render import prune_frames

    path = stage_dir(run, "render") / rec.output
    prune_frames(path)
    return StageOutput(rec.output, file_sha256(path), RenderInfo(pruned=True))


def _features(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    from anchordp3.stages.features import run_features

    d = stage_dir(run, "features")
    frames = stage_dir(run, "render") / frames_file(item.task, item.seed)
    rel = run_features(item.task, item.seed, frames, d, cfg.features)
    return StageOutput(rel, file_sha256(d / rel), FeaturesInfo())


def _shards(cfg: RunConfig, episodes) -> list[list[ShardMember]]:
    from anchordp3.stages.write import shard_plan

    return shard_plan(episodes, cfg.write)


def _write(run: Path, cfg: RunConfig, item: GroupItem) -> StageOutput:
    from anchordp3.stages.write import write_shard

    members, failed = [], []
    for m, ep in zip(item.members, item.episodes):
        text = ep.get(RolloutInfo).record.instruction if ep.inputs else ""
        members.append(m.model_copy(update={"instruction": text}))
        if not ep.ok:
            failed.append((m.task, m.seed))
    rec = write_shard(item.index, members, stage_dir(run, "features"), stage_dir(run, "write"), cfg.write,
                      tasks=sorted(set(cfg.tasks)), failed=failed)  # the plan's task list (write.plan_tasks)
    return StageOutput(rec.path, rec.checksum, ShardInfo(samples=rec.samples, shard=rec))


def _index(run: Path, cfg: RunConfig, records: list[ItemRecord]) -> StageOutput:
    from anchordp3.stages.write import finalize

    d = stage_dir(run, "write")
    info = finalize(d, [r.payload(ShardInfo).shard for r in records], cfg.write)
    return StageOutput("dataset.json", file_sha256(d / "dataset.json"),
                       IndexInfo(samples=info.counts.samples, episodes=info.counts.episodes))


INDEX_ITEM = "dataset"  # the write stage's last item: index, statistics, dataset.json


def _part(name: str):
    return lambda cfg: cfg.stage_config(name)


DATA_GRAPH = Graph((
    Stage("rollout", "rollout", _rollout, RolloutInfo, "anchordp3.stages.rollout", _part("rollout")),
    Stage("anchors", "anchors", _anchors, AnchorsInfo, "anchordp3.stages.anchors", _part("anchors"), needs=(RolloutInfo,)),
    Stage("render", "render", _render, RenderInfo, "anchordp3.stages.render", _part("render"), needs=(RolloutInfo,),
          release=_release_frames, gpu_share=True),
    Stage("features", "features", _features, FeaturesInfo, "anchordp3.stages.features", _part("features")),
    Stage("write", "dataset", _write, ShardInfo, "anchordp3.stages.write", _part("write"), needs=(RolloutInfo,),
          group=_shards, finish=_index, finish_item=INDEX_ITEM),
), former=(lambda cfg: {s: cfg.stage_config(s, layout=1) for s in ("rollout", "write")},))
DATA_STAGES: tuple[str, ...] = DATA_GRAPH.names
STAGE_DIRS = {s.name: s.folder for s in DATA_GRAPH.stages}


def stage_dir(run_dir: Path, stage: str) -> Path:
    """Folder of data stage ``stage`` in a run directory."""
    return Path(run_dir) / STAGE_DIRS[stage]
