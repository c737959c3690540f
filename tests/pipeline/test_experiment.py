"""The anchors-vs-dense experiment: the dense arm's render budget, and both arms end to end."""

from __future__ import annotations

import json

import pytest
import yaml
from typer.testing import CliRunner

from anchordp3.cli import app
from anchordp3.pipeline.experiment import dense_arm, dense_frame_count, dense_seed_count, rendered_frames, run_experiment
from anchordp3.pipeline.store import read_manifest
from anchordp3.pipeline.work import stage_dir
from anchordp3.schemas.experiment import ExperimentConfig, load_experiment_config
from anchordp3.schemas.records import RolloutInfo
from anchordp3.schemas.run import RunConfig
from tiny_models import tiny_data, tiny_training



def test_dense_seed_count_takes_the_seed_prefix_nearest_to_the_budget():
    steps = {("a", 0): 30, ("b", 0): 30, ("a", 1): 60, ("b", 1): 31, ("a", 2): 90}  # ("b", 2) was not kept
    assert dense_frame_count(31, 3) == 11
    # cumulative dense frames: seed 0 → 10 + 10 = 20, seed 1 → 20 + 20 + 11 = 51, seed 2 → 51 + 30 = 81
    count = lambda budget: dense_seed_count(["a", "b"], [0, 1, 2], steps, budget=budget, stride=3)  # noqa: E731
    assert [count(b) for b in (35, 36, 66, 67, 200)] == [1, 2, 2, 3, 3]  # 35 is as near 20 as 51, 66 as 51 as 81: the fewer
    assert count(5) == 1  # never empty


def test_dense_arm_is_the_same_run_with_the_dense_plan_on_a_seed_prefix():
    cfg = RunConfig.model_validate(tiny_data("x", ["place_mouse"], "3,5-7"))
    dense = dense_arm(cfg, 2)
    assert dense.seed_list == [3, 5] and dense.anchors.plan == "dense" and dense.name == "x-dense"
    assert dense_arm(cfg, 4).seeds == "3,5-7"  # written as ranges, as the report shows them
    assert dense.cameras == cfg.cameras and dense.features == cfg.features


def test_a_bad_experiment_config_names_the_file_and_field(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"run": tiny_data("x", ["place_mouse"], "0"), "eval": {"episodes": 0}}))
    with pytest.raises(ValueError, match=r"bad.yaml: eval.episodes"):
        load_experiment_config(bad)
    bad.write_text(yaml.safe_dump({"run": tiny_data("x", ["place_mouse"], "0", anchors={"plan": "dense"})}))
    with pytest.raises(ValueError, match=r"run.anchors.plan"):
        load_experiment_config(bad)
    res = CliRunner().invoke(app, ["experiment", "anchors-vs-dense", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "missing.yaml" in res.output and not (tmp_path / "o").exists()


def test_the_recipe_experiment_is_the_recipe_as_its_anchors_arm_evaluated_as_the_recipe_evaluates():
    from pathlib import Path

    from anchordp3.schemas.recipe import load_recipe_config

    configs = Path(__file__).resolve().parents[2] / "configs"
    exp, recipe = load_experiment_config(configs / "experiment_recipe.yaml"), load_recipe_config(configs / "recipe.yaml")
    assert exp.run == recipe.run and exp.training == recipe.training
    opts, same = exp.eval.target(first_seed=1199), recipe.eval.target(first_seed=1199)
    for field in ("episodes", "workers", "max_decisions", "through", "samples", "ddim_steps", "first_seed"):
        assert getattr(opts, field) == getattr(same, field), field
    assert opts.ddim_steps == 5


def test_the_experiment_runs_both_arms_at_the_same_render_budget(ray_session, tmp_path):
    cfg = ExperimentConfig.model_validate({
        "run": tiny_data("avd", ["place_mouse"], "0-3", anchors={"dagger": {"fraction": 0.2}, "dense": {"frame_stride": 12}}),
        "training": tiny_training(3, 3, 3, loop={"log_interval_s": 30.0, "cpu_threads": 1}, device="cpu"),
        "eval": {"episodes": 1, "workers": 1, "max_decisions": 2, "ddim_steps": 2},
    })
    results = run_experiment(tmp_path, cfg)
    a, d = results["arms"]["anchors"], results["arms"]["dense"]
    # the dense arm renders about as much as the anchors arm, on fewer trajectories (a prefix of its seeds)
    assert 1 <= d["trajectories"] < a["trajectories"] and 0.5 * a["frames"] <= d["frames"] <= 1.5 * a["frames"]
    assert results["trajectories_per_budget_ratio"] == pytest.approx(
        (a["trajectories"] / a["frames"]) / (d["trajectories"] / d["frames"]))
    frames = rendered_frames(tmp_path / "dense")
    steps = {k: r.payload(RolloutInfo).record.steps for k, r in read_manifest(stage_dir(tmp_path / "dense", "rollout")).items.items()}
    assert all(n == dense_frame_count(steps[f"{t}/{s:06d}"], 12) for (t, s), n in frames.items())
    # both arms trained and evaluated on the same seeds
    seeds = {arm: [json.loads(p.read_text())["seed"] for p in sorted((tmp_path / arm / "eval" / "episodes").rglob("*.json"))]
             for arm in ("anchors", "dense")}
    assert seeds["anchors"] == seeds["dense"] and len(seeds["anchors"]) == 1
    for arm in ("anchors", "dense"):
        assert set(results["arms"][arm]["seconds"]) == {"data", "train", "eval"}
        assert (tmp_path / arm / "models" / "policy" / "model.pt").is_file()
    report = (tmp_path / "report.md").read_text()
    assert "Trajectories per render budget" in report and "place_mouse" in report
    assert (tmp_path / "comparison.png").read_bytes()[:4] == b"\x89PNG"
    assert json.loads((tmp_path / "results.json").read_text()) == json.loads(json.dumps(results))
    # re-running resumes: nothing left to do, the same outcome, phase times only grow
    again = run_experiment(tmp_path, cfg)
    assert again["arms"]["dense"]["seeds"] == d["seeds"] and again["arms"]["anchors"]["success"] == a["success"]
    assert all(again["arms"][arm]["seconds"][ph] >= results["arms"][arm]["seconds"][ph]
               for arm in ("anchors", "dense") for ph in ("data", "train", "eval"))
