"""``anchordp3 show``: a picture of a rendered or featurised frame, and one-line errors."""

from __future__ import annotations

from PIL import Image
from typer.testing import CliRunner

from anchordp3.cli import app

runner = CliRunner()


def test_show_draws_a_rendered_frame_with_images_and_clouds(staged, tmp_path):
    out = tmp_path / "frame.png"
    res = runner.invoke(app, ["show", str(staged["place_mouse"].frames), "--frame", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    img = Image.open(out)
    assert img.size[0] >= 1000 and img.size[1] >= 800


def test_show_finds_the_episode_in_a_run_directory(staged, tmp_path):
    root = staged["place_mouse"].root
    res = runner.invoke(app, ["show", str(root), "--episode", "place_mouse/0", "--out", str(tmp_path / "a.png")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["show", str(staged["stack_blocks_three"].features), "--out", str(tmp_path / "b.png")])
    assert res.exit_code == 0 and (tmp_path / "b.png").stat().st_size > 10_000


def test_show_rejects_a_bad_frame_index_and_a_foreign_file_in_one_line(staged, tmp_path):
    res = runner.invoke(app, ["show", str(staged["place_mouse"].frames), "--frame", "999", "--out", str(tmp_path / "x.png")])
    assert res.exit_code == 2 and "--frame" in res.output and len(res.output.strip().splitlines()) == 1
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not an archive")
    res = runner.invoke(app, ["show", str(junk), "--out", str(tmp_path / "y.png")])
    assert res.exit_code == 2 and "junk.npz" in res.output
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "y.png").exists()
