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
