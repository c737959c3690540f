"""Messages go through standard logging: bare lines for people on the console, other libraries'
warnings kept off it but in the log file, and what a Ray worker logs while it does an item
reaches the driver's log named by stage and item. A worker that cannot start stops the run."""

from __future__ import annotations

import importlib
import io
import logging
import sys
import warnings
from pathlib import Path

import pytest
from pydantic import Field
from ray import cloudpickle

from anchordp3.logs import Capture, console, replay, to_file
from anchordp3.pipeline.graph import EpisodeItem, Graph, Stage, StageOutput
from anchordp3.pipeline.noop import noop_graph
from anchordp3.pipeline.runner import LOG_FILE, RunAborted, RunOptions, run_pipeline
from anchordp3.schemas.records import Payload
from anchordp3.schemas.run import PoolConfig, RunConfig

CFG = RunConfig(name="logs", tasks=["place_mouse"], seeds="0-5")
ours = logging.getLogger("anchordp3.tests")


@pytest.fixture
def console_text():
    """The console handler writing into a string (restored to stderr after the test)."""
    out = io.StringIO()
    console(logging.INFO, out)
    yield out
    console(logging.INFO)


def test_the_console_shows_our_messages_bare_and_warnings_prefixed_not_other_libraries_warnings(console_text, tmp_path):
    with to_file(tmp_path / "a.log") as path:
        ours.info("rollout: 3/10 done")
        ours.warning("render: 2 frames had no points")
        logging.getLogger("some.library").warning("a deprecation nobody here can act on")
        warnings.warn("a Python warning from a library", DeprecationWarning, stacklevel=1)
        ours.debug("not shown at INFO")
    shown = console_text.getvalue().splitlines()
    assert shown == ["rollout: 3/10 done", "warning: render: 2 frames had no points"]
    logged = path.read_text()
    assert "INFO anchordp3.tests: rollout: 3/10 done" in logged and "a deprecation nobody here can act on" in logged
    assert "not shown" not in logged
    ours.info("after the block")
    assert "after the block" not in path.read_text()  # the file handler is gone with its block


def test_quiet_keeps_warnings_and_drops_progress(tmp_path):
    out = io.StringIO()
    console(logging.WARNING, out)
    try:
        ours.info("step 5/10")
        ours.warning("checkpoint was stale")
    finally:
        console(logging.INFO)
    assert out.getvalue().splitlines() == ["warning: checkpoint was stale"]


def test_captured_records_replay_with_where_they_came_from(console_text):
    with Capture() as cap:
        ours.info("scene settled after %d steps", 40)
        logging.getLogger("other").info("an INFO of another library is not kept")
    assert [r.message for r in cap.records] == ["scene settled after 40 steps"]
    replay(cap.records, "render place_mouse/000003")
    assert console_text.getvalue().splitlines()[-1] == "render place_mouse/000003: scene settled after 40 steps"


class ChatInfo(Payload):
    seed: int = Field(description="The episode's seed.")


def _chatty(run: Path, cfg: RunConfig, item: EpisodeItem) -> StageOutput:
    log = logging.getLogger("anchordp3.stages.chatty")
    log.info("looked at seed %d", item.seed)
    if item.seed == 3:
        log.warning("seed %d has a tilted object", item.seed)
    return StageOutput(None, None, ChatInfo(seed=item.seed))


def test_what_workers_log_reaches_the_driver_log_named_by_stage_and_item(ray_session, tmp_path):
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the actors cannot import a test module
    first, step, group = noop_graph(2).stages
    chatty = Stage("chatty", "chatty", _chatty, ChatInfo, __name__, lambda cfg: {}, resources=PoolConfig(cpus=0.1))
    graph = Graph((first, chatty, step, group))
    with Capture() as cap:
        run_pipeline(CFG, tmp_path, RunOptions(progress_interval=60), graph=graph)
    text = (tmp_path / LOG_FILE).read_text()
    assert "WARNING anchordp3.stages.chatty: chatty place_mouse/000003: seed 3 has a tilted object" in text
    assert "chatty place_mouse/000005: looked at seed 5" in text  # seed 0 stopped at the first stage
    assert "chatty place_mouse/000000" not in text
    assert "noop_group:" in text or "done" in text  # the driver's own progress lines are there too
    assert any(r.message.endswith("seed 3 has a tilted object") for r in cap.records)  # and on the console


def test_a_stage_whose_workers_cannot_start_stops_the_run_with_the_reason(ray_session, tmp_path):
    (tmp_path / "only_here.py").write_text(
        "from anchordp3.pipeline.graph import StageOutput\n"
        "def run(run_dir, cfg, item):\n    return StageOutput(None, None, None)\n")
    sys.path.insert(0, str(tmp_path))  # the driver imports it; the workers cannot
    try:
        module = importlib.import_module("only_here")
        first, step, group = noop_graph(2).stages
        lost = Stage("lost", "lost", module.run, ChatInfo, "only_here", lambda cfg: {}, resources=PoolConfig(cpus=0.1))
        with pytest.raises(RunAborted, match="stage lost: its worker could not start"):
            run_pipeline(CFG, tmp_path / "run", RunOptions(progress_interval=60), graph=Graph((first, lost, step, group)))
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("only_here", None)


def test_the_console_follows_stderr_when_it_is_swapped_and_closed(monkeypatch, capsys):
    console(logging.INFO)
    first = io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    ours.info("to the first")
    first.close()  # as an in-process CLI runner closes the stream it swapped in
    second = io.StringIO()
    monkeypatch.setattr(sys, "stderr", second)
    ours.info("to the second")
    assert second.getvalue() == "to the second\n"
