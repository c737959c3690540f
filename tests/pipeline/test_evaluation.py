"""Closed-loop evaluation on a tiny real run: records in the manifest, a table, a chart and a
report; seeds disjoint from training; the Wilson interval."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import torch

from anchordp3.logs import Capture
from anchordp3.pipeline.evaluation import EVAL_DIR, eval_seeds, wilson_interval
from anchordp3.pipeline.runner import LOG_FILE, RunOptions, run_pipeline
from anchordp3.pipeline.store import has_manifest, read_manifest
from anchordp3.pipeline.targets import run_evaluation, train_models
from anchordp3.schemas.evaluation import EvalOptions
from anchordp3.schemas.run import RunConfig, load_run_config
from anchordp3.schemas.training import MODELS, TrainingConfig
from tiny_models import tiny_data, tiny_training

DATA = tiny_data("tiny-eval", ["place_mouse"], "0-1")
TRAIN = tiny_training(3, 3, 3, loop={"log_interval_s": 5.0}, device="cpu")


@pytest.fixture(scope="module")
def trained_run(ray_session, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("evalrun")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        run_pipeline(RunConfig.model_validate(DATA), run, RunOptions(progress_interval=60))
        train_models(run, MODELS, TrainingConfig.model_validate(TRAIN))
    finally:
        torch.set_num_threads(before)
    return run


def test_wilson_interval():
    assert wilson_interval(0, 0) == (0.0, 1.0)
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and 0.2 < hi < 0.35
    lo, hi = wilson_interval(5, 10)
    assert lo < 0.5 < hi and abs((lo + hi) / 2 - 0.5) < 1e-9


def test_the_wilson_interval_always_holds_the_rate_so_error_bars_are_never_negative():
    for n in range(1, 201):
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            assert 0.0 <= lo <= k / n <= hi <= 1.0, (k, n)
    assert wilson_interval(10, 10)[1] == 1.0  # 0.9999999999999999 before: a negative error bar stopped a recipe


def test_eval_seeds_disjoint_from_training():
    cfg = RunConfig.model_validate(DATA)
    seeds = eval_seeds(cfg, 5)
    assert len(set(seeds)) == 5 and not set(seeds) & set(cfg.seed_list)


def test_evaluation_writes_records_and_reports(trained_run):
    opts = EvalOptions(episodes=2, workers=2, max_decisions=2)
    records = run_evaluation(trained_run, opts)
    out = trained_run / EVAL_DIR
    assert [(r["task"], r["seed"]) for r in records] == [("place_mouse", s) for s in eval_seeds(RunConfig.model_validate(DATA), 2)]
    for r in records:
        assert isinstance(r["success"], bool)
        assert 0 <= r["steps"] <= r["step_limit"] and r["decisions"] <= 2
        assert r["success"] or r["failure"] in ("layout_failure", "unstable", "no_points", "wrong_task", "step_limit", "max_decisions")
        assert r["instruction"] and r["predicted_task"]
    m = read_manifest(out)
    assert m.complete and m.counts.done == 2
    for item, rec in m.items.items():
        assert json.loads((out / rec.output).read_text())["seed"] == int(item.split("/")[1])
    table = pq.read_table(out / "episodes.parquet")
    assert table.num_rows == 2 and table.schema.field("success").type == "bool"
    assert (out / "success.png").read_bytes()[:4] == b"\x89PNG"
    report = (out / "report.md").read_text()
    assert "place_mouse" in report and "95 %" in report
    for r in records:  # the first two seeds of each task get a frame strip, linked from the report
        if r["failure"] not in ("layout_failure", "unstable"):
            strip = out / "strips" / "place_mouse" / f"{r['seed']:06d}.png"
            assert strip.read_bytes()[:4] == b"\x89PNG" and f"strips/place_mouse/{r['seed']:06d}.png" in report
    # a second call finds every episode done and redoes none
    with Capture() as cap:
        assert run_evaluation(trained_run, opts) == records
    assert any("2 already done" in r.message for r in cap.records)
    assert "2 already done" in (trained_run / LOG_FILE).read_text()  # and in the run's log file


def test_eval_cli(trained_run, tmp_path):
    from typer.testing import CliRunner

    from anchordp3.cli import app

    run_evaluation(trained_run, EvalOptions(episodes=2, workers=2, max_decisions=2))
    res = CliRunner().invoke(app, ["eval", "--run-dir", str(trained_run), "--episodes", "2", "--max-decisions", "2"])
    assert res.exit_code == 0, res.output
    assert "place_mouse" in res.output and "95% CI" in res.output
    print("\n" + (trained_run / EVAL_DIR / "report.md").read_text())
    res = CliRunner().invoke(app, ["eval", "--run-dir", str(tmp_path)])
    assert res.exit_code == 2 and "error:" in res.output


def test_eval_takes_any_models_tasks_seeds_and_folder_and_marks_training_seeds(trained_run, tmp_path):
    opts = EvalOptions(models=str(trained_run / "models"), tasks=("place_mouse",), seeds="train", out=tmp_path / "ev",
                       workers=1, max_decisions=1, strips=0)
    records = run_evaluation(None, opts)  # the run config is found beside the models folder
    assert [(r["seed"], r["seen"]) for r in records] == [(0, True), (1, True)]
    assert "on training seeds, the scenes the models were trained on (0-1 of 0-1)" in (tmp_path / "ev" / "report.md").read_text()
    assert not (trained_run / EVAL_DIR / "ev").exists()
    unseen = run_evaluation(trained_run, EvalOptions(seeds="1500", out=tmp_path / "ev2", workers=1, max_decisions=1))
    assert [(r["seed"], r["seen"]) for r in unseen] == [(1500, False)]
    assert "on seeds disjoint from training (training seeds 0-1; evaluation seeds 1500)" in (tmp_path / "ev2" / "report.md").read_text()
    with pytest.raises(ValueError, match="--tasks"):
        run_evaluation(trained_run, EvalOptions(tasks=("place_bell",), out=tmp_path / "ev3"))


def test_an_evaluation_folder_of_other_settings_is_refused_unless_forced_and_the_same_resumes(trained_run, tmp_path):
    out = tmp_path / "ev"
    first = run_evaluation(trained_run, EvalOptions(seeds="1500", out=out, workers=1, max_decisions=1, strips=0))
    again = run_evaluation(trained_run, EvalOptions(seeds="1500", out=out, workers=1, max_decisions=1, strips=0))
    assert again == first  # the same models and settings: resumed, nothing redone
    with pytest.raises(ValueError, match=r"--out: .* holds an evaluation of other models, settings or code \(config changed\).*--force"):
        run_evaluation(trained_run, EvalOptions(seeds="1500", out=out, workers=1, max_decisions=2, strips=0))
    assert (out / "report.md").is_file()  # refused: the earlier evaluation is still there
    forced = run_evaluation(trained_run, EvalOptions(seeds="1500", out=out, workers=1, max_decisions=2, strips=0, force=True))
    assert [r["seed"] for r in forced] == [1500]


def test_every_failed_episode_names_the_task_conditions_it_ended_without(trained_run, tmp_path):
    records = run_evaluation(trained_run, EvalOptions(seeds="1500,1501", out=tmp_path / "ev", workers=1, max_decisions=1, strips=0))
    names = {"over_pad", "on_pad", "released"}  # the place-on-scale tasks' conditions
    for r in records:
        unmet = set(filter(None, r["unmet"].split(",")))
        assert (not unmet) == r["success"] and unmet <= names, r
    assert "conditions unmet at the end" in (tmp_path / "ev" / "report.md").read_text()


def test_status_lists_the_run_s_models_and_evaluations_beside_its_data_stages(trained_run, tmp_path):
    from typer.testing import CliRunner

    from anchordp3.cli import app
    from anchordp3.pipeline.inspect import product_status

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    for d in run.glob("eval*"):  # what other tests evaluated in the shared run
        shutil.rmtree(d)
    run_evaluation(run, EvalOptions(seeds="1500", workers=1, max_decisions=1, strips=0))
    rows = {r.stage: r for r in product_status(run)}
    assert list(rows) == ["train segmenter", "train classifier", "train policy", "evaluate (eval)"]
    assert all(r.complete and not r.stale for r in rows.values())
    assert rows["evaluate (eval)"].done == 1 and rows["train policy"].folder == "models/policy"
    out = CliRunner().invoke(app, ["status", str(run)]).output
    assert "train policy" in out and "evaluate (eval)" in out and "write" in out
    # retraining the segmenter under the policy makes the policy (and the evaluation of the run's models) stale
    seg = run / "models" / "segmenter" / "model.pt"
    seg.write_bytes(seg.read_bytes() + b"\0")
    rows = {r.stage: r for r in product_status(run)}
    assert rows["train policy"].stale and rows["train policy"].changed == ["upstream segmenter"]
    assert rows["evaluate (eval)"].stale and not rows["train classifier"].stale


def test_an_episode_whose_worker_is_killed_starts_again_on_a_new_worker_and_ends_as_it_would_have(trained_run, tmp_path, monkeypatch):
    from anchordp3.pipeline.actors import FAULTS_ENV

    opts = dict(seeds="1500,1501", workers=1, max_decisions=2, strips=0)
    clean = run_evaluation(trained_run, EvalOptions(out=tmp_path / "clean", **opts))
    monkeypatch.setenv(FAULTS_ENV, "evaluate:place_mouse/001500:1:crash")  # the worker process exits with the episode's call in flight
    with Capture() as cap:
        crashed = run_evaluation(trained_run, EvalOptions(out=tmp_path / "crashed", **opts))
    assert any("worker 0 died with place_mouse/001500 in flight" in r.message for r in cap.records)
    assert any("place_mouse/001500: " in r.message and "attempt 2" in r.message for r in cap.records)
    drop = lambda rs: [{k: v for k, v in r.items() if k != "seconds"} for r in rs]  # noqa: E731
    assert drop(crashed) == drop(clean)
    m = read_manifest(tmp_path / "crashed")
    assert m.counts.done == len(clean) and m.complete


def test_an_episode_that_raises_is_retried_then_recorded_as_failed_and_the_others_complete(trained_run, tmp_path, monkeypatch):
    from anchordp3.pipeline.actors import FAULTS_ENV

    opts = dict(tasks=("place_mouse",), seeds="1500,1501,1502", workers=1, max_decisions=1, strips=0)
    clean = run_evaluation(trained_run, EvalOptions(out=tmp_path / "clean", **opts))
    monkeypatch.setenv(FAULTS_ENV, "evaluate:place_mouse/001500:1,evaluate:place_mouse/001501:9")  # once; always
    with Capture() as cap:
        got = run_evaluation(trained_run, EvalOptions(out=tmp_path / "faulty", **opts))
    drop = lambda rs: [{k: v for k, v in r.items() if k != "seconds"} for r in rs]  # noqa: E731
    assert drop(got) == drop([r for r in clean if r["seed"] != 1501])  # 1500 retried to the same record; 1501 left out
    m = read_manifest(tmp_path / "faulty")
    failed = m.items["place_mouse/001501"]
    assert failed.status == "failed" and failed.reason == "InjectedFault" and failed.attempts == 3 and not m.complete
    assert any("1 of 3 episodes failed with an error" in r.message for r in cap.records)
    monkeypatch.delenv(FAULTS_ENV)
    again = run_evaluation(trained_run, EvalOptions(out=tmp_path / "faulty", **opts))  # a rerun tries it again
    assert drop(again) == drop(clean) and read_manifest(tmp_path / "faulty").complete


def test_verify_checks_the_run_s_models_and_evaluations_too(trained_run, tmp_path):
    from anchordp3.pipeline.verify import repair_run, verify_run

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    for d in run.glob("eval*"):
        shutil.rmtree(d)
    run_evaluation(run, EvalOptions(seeds="1500", workers=1, max_decisions=1, strips=0))
    assert verify_run(run).ok
    (run / "models" / "policy" / "model.pt").write_bytes(b"not a model")
    episode = next((run / "eval" / "episodes").rglob("*.json"))
    episode.unlink()
    report = verify_run(run)
    assert sorted((p.stage, p.kind) for p in report.problems) == [("evaluate (eval)", "missing"), ("train policy", "corrupt")]
    assert "`anchordp3 train NAME --force`" in report.text() and "--repair" not in report.text()
    before, after = repair_run(run)  # no data to redo: nothing runs, the problems stay named
    assert before == after and len(after.problems) == 2


def test_shipped_models_are_small_and_decide_as_the_run_s_own(trained_run, tmp_path):
    from anchordp3.pipeline.shipping import SHIPPED_FILE, ship_models

    dest = tmp_path / "shipped"
    assert "shipped" in ship_models(trained_run, dest, command="anchordp3 experiment recipe tiny")
    for name in MODELS:
        assert (dest / name / "model.pt").stat().st_size <= (trained_run / "models" / name / "model.pt").stat().st_size
        assert (dest / name / "manifest.json").is_file()
    assert (dest / "run_config.yaml").is_file() and "recipe tiny" in (dest / SHIPPED_FILE).read_text()
    tasks = load_run_config(trained_run / "config.yaml").tasks
    assert f"Tasks ({len(tasks)}): {', '.join(tasks)}." in (dest / SHIPPED_FILE).read_text()  # what the folder does
    from anchordp3.stages.evaluate import EvalModels

    own, shipped = EvalModels(trained_run / "models"), EvalModels(dest)
    g = torch.Generator().manual_seed(0)
    points, state = torch.rand(256, 11, generator=g).numpy(), torch.rand(32, generator=g).numpy()
    a, b = own.anchors(points, state, 0, noise_seed=3), shipped.anchors(points, state, 0, noise_seed=3)
    assert abs(a - b).max() < 5e-3  # float16 weights: the same anchors within a few mm / mrad
    assert own.classify("put the mouse on the scale") == shipped.classify("put the mouse on the scale")
    theirs = run_evaluation(None, EvalOptions(models=str(dest), seeds="1500", out=tmp_path / "b", workers=1, max_decisions=2))
    assert [r["seed"] for r in theirs] == [1500] and theirs[0]["decisions"] <= 2
    with pytest.raises(FileNotFoundError, match="no trained"):
        ship_models(tmp_path / "empty-run", tmp_path / "x")


def test_shipped_models_can_be_shipped_again_deciding_with_fewer_ddim_steps(trained_run, tmp_path):
    from anchordp3.pipeline.shipping import SHIPPED_FILE, ship_models
    from anchordp3.stages.training_loop import load_checkpoint

    first, again = tmp_path / "first", tmp_path / "again"
    ship_models(trained_run, first, command="recipe tiny")
    own = load_checkpoint(first / "policy" / "model.pt")
    assert f"decides with {own['config']['scheduler']['num_inference_steps']} DDIM steps" in (first / SHIPPED_FILE).read_text()
    ship_models(first, again, command="recipe tiny, shipped again", ddim_steps=3)  # from a shipped folder, not a run
    fewer = load_checkpoint(again / "policy" / "model.pt")
    assert fewer["config"]["scheduler"]["num_inference_steps"] == 3 and "decides with 3 DDIM steps" in (again / SHIPPED_FILE).read_text()
    assert all(torch.equal(fewer["ema_state_dict"][k], v) for k, v in own["ema_state_dict"].items())  # the same weights
    for name in MODELS:
        assert (again / name / "manifest.json").read_bytes() == (first / name / "manifest.json").read_bytes()
    assert (again / "run_config.yaml").read_bytes() == (first / "run_config.yaml").read_bytes()
    from anchordp3.stages.evaluate import EvalModels

    assert EvalModels(again).policy.config.scheduler.num_inference_steps == 3


def test_a_truncated_model_file_is_refused_in_one_line_naming_it(trained_run, tmp_path):
    import shutil

    from typer.testing import CliRunner

    from anchordp3.cli import app

    broken = tmp_path / "models"
    shutil.copytree(trained_run / "models", broken)
    blob = (broken / "policy" / "model.pt").read_bytes()
    (broken / "policy" / "model.pt").write_bytes(blob[: len(blob) // 2])
    res = CliRunner().invoke(app, ["eval", "--run-dir", str(trained_run), "--models", str(broken), "--out", str(tmp_path / "ev")])
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "policy/model.pt" in lines[0] and "not a readable checkpoint" in lines[0]
    assert not has_manifest(tmp_path / "ev")


def test_a_watcher_sees_every_decision_before_it_is_carried_out_and_changes_nothing(trained_run):
    from anchordp3.pipeline.evaluation import eval_run_config, models_folder
    from anchordp3.stages.evaluate import EvalModels, evaluate_episode

    cfg = eval_run_config(trained_run, models_folder(trained_run, None), EvalOptions())
    models = EvalModels(trained_run / "models")
    seen = []

    def watch(ep, decision, points, pred):
        seen.append((decision, ep.steps, points.shape, pred.shape))

    watched = evaluate_episode("place_mouse", 5000, models, cfg, max_decisions=2, watch=watch)
    plain = evaluate_episode("place_mouse", 5000, models, cfg, max_decisions=2)
    assert [d for d, *_ in seen] == list(range(watched.decisions)) and watched.decisions == 2
    assert seen[0][1] == 0 and seen[1][1] > 0  # called before the first anchor was carried out, then after it
    assert seen[0][2] == (cfg.features.n_points, 11) and seen[0][3][1] == 32
    assert (watched.steps, watched.failure, watched.success) == (plain.steps, plain.failure, plain.success)


def test_the_draws_per_decision_are_a_setting_of_the_evaluation_eight_by_default(trained_run):
    from anchordp3.pipeline.evaluation import eval_run_config, evaluation_fingerprint, models_folder
    from anchordp3.pipeline.graph import BatchContext
    from anchordp3.schemas.evaluation import EvaluationConfig
    from anchordp3.stages.evaluate import EvalModels

    models_dir = models_folder(trained_run, None)
    ctx = BatchContext(trained_run, trained_run / EVAL_DIR)

    def fingerprint(**settings):
        return evaluation_fingerprint(ctx, eval_run_config(trained_run, models_dir, EvaluationConfig(**settings)))

    assert fingerprint() == fingerprint(samples=8)  # the default: the medoid of 8 draws (rung D17)
    assert fingerprint(samples=1) != fingerprint()
    g = torch.Generator().manual_seed(0)
    points, state = torch.rand(256, 11, generator=g).numpy(), torch.rand(32, generator=g).numpy()
    picked = EvalModels(models_dir, samples=4).anchors(points, state, 0, noise_seed=3)
    assert picked.shape == EvalModels(models_dir, samples=1).anchors(points, state, 0, noise_seed=3).shape
