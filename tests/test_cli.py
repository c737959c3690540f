"""The command line: listing, rollouts, snapshots, and one-line errors with exit code 2."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from anchordp3.cli import app

runner = CliRunner()


def test_tasks_lists_every_task():
    from anchordp3.sim.tasks import TASKS

    res = runner.invoke(app, ["tasks"])
    assert res.exit_code == 0
    for name in TASKS:
        assert name in res.output


def test_rollout_prints_a_table_and_the_success_rate(tmp_path):
    res = runner.invoke(app, ["rollout", "blocks_ranking_rgb", "--seeds", "0-1", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "success 2/2" in res.output
    assert len(list(tmp_path.rglob("*.npz"))) == 2


@pytest.mark.parametrize(
    "args, field",
    [
        (["rollout", "no_such_task"], "task"),
        (["rollout", "stack_blocks_three", "--seeds", "9-1"], "--seeds"),
        (["rollout", "stack_blocks_three", "--preset", "wild"], "preset"),
        (["snapshot", "no_such_task"], "task"),
    ],
)
def test_bad_input_is_one_line_naming_the_field_with_exit_2(args, field, tmp_path):
    res = runner.invoke(app, args + (["--out", str(tmp_path / "x.png")] if args[0] == "snapshot" else []))
    assert res.exit_code == 2
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and field in lines[0]
    assert not (tmp_path / "x.png").exists()


def test_snapshot_writes_a_picture_of_four_views(tmp_path):
    from PIL import Image

    out = tmp_path / "views.png"
    res = runner.invoke(app, ["snapshot", "stack_blocks_three", "--seed", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    img = Image.open(out)
    assert img.size[0] == 2 * 320 and img.size[1] >= 2 * 240


# ------------------------------------------------------------------- bad input files: one line, exit 2
@pytest.mark.parametrize("model, keep", [("segmenter", 0), ("classifier", 10), ("policy", 0.5)])  # bytes kept, or a fraction
def test_a_truncated_model_file_given_to_eval_is_one_line_naming_it(tmp_path, model, keep):
    """``anchordp3 eval --models DIR`` (a real process: nothing else may reach stderr) with one
    model file cut short: one line naming that file, exit 2, nothing evaluated."""
    import shutil
    import subprocess
    import sys

    from anchordp3.pipeline.evaluation import PRETRAINED_DIR

    models = tmp_path / "models"
    shutil.copytree(PRETRAINED_DIR, models)
    path = models / model / "model.pt"
    blob = path.read_bytes()
    path.write_bytes(blob[: int(len(blob) * keep) if isinstance(keep, float) else keep])
    res = subprocess.run([sys.executable, "-m", "anchordp3.cli", "eval", "--models", str(models), "--out", str(tmp_path / "ev"),
                          "--episodes", "1"], capture_output=True, text=True, timeout=300)
    lines = [line for line in (res.stdout + res.stderr).splitlines() if line.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stdout + res.stderr
    assert lines[0].startswith("error: ") and f"{model}/model.pt" in lines[0] and "not a readable checkpoint" in lines[0]
    assert not (tmp_path / "ev").exists()


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("command", [["config", "validate"], ["run"], ["experiment", "recipe"]])
def test_a_config_file_of_random_bytes_is_one_line_naming_it(tmp_path, seed, command):
    import random

    cfg = tmp_path / "random.yaml"
    cfg.write_bytes(random.Random(seed).randbytes(4096))
    extra = {"run": ["--run-dir", str(tmp_path / "run")], "experiment": ["--out", str(tmp_path / "out")]}.get(command[0], [])
    res = runner.invoke(app, [*command, str(cfg), *extra])
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert str(cfg) in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["random.yaml"]
