"""``anchordp3 experiment recipe``: data, training, evaluation on unseen and on training seeds in
one resumable command, with its report (tiny config and networks here)."""

from __future__ import annotations

import json

from anchordp3.logs import Capture
from anchordp3.pipeline.recipe import run_recipe
from anchordp3.schemas.recipe import RecipeConfig
from tiny_models import tiny_data, tiny_training


def test_recipe_is_one_run_of_the_graph_through_both_evaluations_and_resumes_without_redoing(ray_session, tmp_path):
    cfg = RecipeConfig.model_validate({
        "run": tiny_data("tiny-recipe", ["place_mouse"], "0-1"),
        "training": tiny_training(3, 3, 3, loop={"log_interval_s": 30.0, "cpu_threads": 1}, device="cpu"),
        "eval": {"episodes": 1, "train_episodes": 1, "workers": 1, "max_decisions": 2},
    })
    results = run_recipe(tmp_path, cfg)
    assert results["episodes"] == 2 and results["samples"] > 0
    assert [r["episodes"] for r in results["unseen"]] == [1] and [r["episodes"] for r in results["train_seeds"]] == [1]
    assert set(results["models"]) == {"segmenter", "classifier", "policy"} and results["models"]["policy"]["steps"] == 3
    assert "first_cm" in results["models"]["policy"]["metrics"]
    for phase in ("data", "train", "eval", "eval-train"):
        assert results["seconds"][phase] > 0
    report = (tmp_path / "report.md").read_text()
    assert "place_mouse" in report and "unseen seeds" in report and "first anchor cm" in report
    assert (tmp_path / "run" / "eval" / "report.md").is_file() and (tmp_path / "run" / "eval" / "train" / "report.md").is_file()
    from anchordp3.pipeline.inspect import product_status

    rows = {r.stage: r for r in product_status(tmp_path / "run")}  # status shows both evaluations beside the models
    assert rows["evaluate (eval)"].complete and rows["evaluate (eval/train)"].done == 1
    assert json.loads((tmp_path / "results.json").read_text())["unseen"] == results["unseen"]
    with Capture() as cap:
        assert run_recipe(tmp_path, cfg)["unseen"] == results["unseen"]
    again = [r.message for r in cap.records]
    assert any("evaluate: 1 items (1 already done)" in line for line in again)
    assert any("train-policy: 1 items (1 already done)" in line for line in again)
    assert not any("redoing" in line for line in again)
