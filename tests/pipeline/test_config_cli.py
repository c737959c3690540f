"""`config show|validate|schema`, and bad configs: one line naming the field, exit 2, nothing written.

No Ray and no simulation here: a bad config must be refused before anything starts.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from anchordp3.cli import app
from anchordp3.schemas.run import RunConfig, load_run_config

DEMO = Path(__file__).resolve().parents[2] / "configs" / "demo.yaml"
cli = CliRunner()


def one_error_line(res) -> str:
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: "), res.output
    return lines[0]


def test_show_prints_the_resolved_config_with_every_default():
    res = cli.invoke(app, ["config", "show", str(DEMO)])
    assert res.exit_code == 0, res.output
    shown = yaml.safe_load(res.output)
    assert RunConfig.model_validate(shown) == load_run_config(DEMO)
    assert set(shown) == set(RunConfig.model_fields)  # every field, defaults included
    assert shown["execution"]["max_attempts"] == 3 and len(shown["cameras"]["views"]) == 4


def test_validate_says_ok_for_the_shipped_configs():
    for name in ("demo.yaml", "full.yaml"):
        res = cli.invoke(app, ["config", "validate", str(DEMO.parent / name)])
        assert res.exit_code == 0, res.output
        assert res.output.startswith("OK")


def test_the_shipped_training_and_experiment_configs_load():
    from anchordp3.pipeline.training import load_training_config
    from anchordp3.schemas.experiment import load_experiment_config

    assert load_training_config(DEMO.parent / "training.yaml").loop.cpu_threads == 1  # beside other work
    assert load_training_config(DEMO.parent / "demo_training.yaml").loop.cpu_threads == 2  # the demo trains alone
    exp = load_experiment_config(DEMO.parent / "experiment.yaml")
    assert exp.run.anchors.plan == "anchors" and exp.run.anchors.dense.frame_stride == 3


@pytest.mark.parametrize("what, key", [("run", "tasks"), ("manifest", "items")])
def test_schema_is_json_schema_of_the_run_config_or_the_manifest(what, key):
    res = cli.invoke(app, ["config", "schema", "--what", what])
    assert res.exit_code == 0, res.output
    schema = json.loads(res.output)
    assert schema["type"] == "object" and key in schema["properties"]


def test_schema_of_something_unknown_is_an_error():
    assert "--what" in one_error_line(cli.invoke(app, ["config", "schema", "--what", "bogus"]))


BAD = [
    # (file text, what the error line must name)
    ("tasks: [place_mouse]\nbogus: 1\n", "bogus: Extra inputs are not permitted"),
    ("tasks: [place_mouse]\nfeatures: {n_points: 8}\n", "features.n_points: Input should be greater than or equal to 16"),
    ("tasks: [place_mouse]\nfeatures: {nope: 3}\n", "features.nope"),
    ("tasks: [place_mouse]\ncameras: {width: wide}\n", "cameras.width"),
    ("tasks: place_mouse\n", "tasks"),
    ("tasks: [place_mouse]\nseeds: '9-1'\n", "seeds"),
    ("tasks: [place_mouse]\nexecution: {pools: {render: {workers: 0}}}\n", "execution.pools.render.workers"),
    ("tasks: [place_mouse\n  b: :", "not valid YAML"),
    ("- just\n- a list\n", "expected a mapping"),
    (None, "no such config file"),
    (bytes(range(128, 256)) * 4, "not a text file"),  # random bytes, not UTF-8
]


@pytest.mark.parametrize("text, named", BAD)
@pytest.mark.parametrize("command", ["validate", "show", "run"])
def test_bad_config_is_one_line_naming_the_field_exit_2_nothing_written(tmp_path, text, named, command):
    cfg = tmp_path / "bad.yaml"
    if isinstance(text, bytes):
        cfg.write_bytes(text)
    elif text is not None:
        cfg.write_text(text)
    run_dir = tmp_path / "run"
    args = ["run", str(cfg), "--run-dir", str(run_dir)] if command == "run" else ["config", command, str(cfg)]
    line = one_error_line(cli.invoke(app, args))
    assert named in line
    if text is None or "YAML" in named or "mapping" in named or "text file" in named:
        assert str(cfg) in line  # file-level problems name the file
    assert not run_dir.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == (["bad.yaml"] if text is not None else [])


def test_validate_names_an_unknown_task_by_its_position(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("tasks: [place_mouse, place_mouse_pad]\n")
    assert "tasks.1: unknown task 'place_mouse_pad'" in one_error_line(cli.invoke(app, ["config", "validate", str(cfg)]))
