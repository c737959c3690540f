"""``anchordp3 demo`` wires data, training and evaluation together and ends with the success table
(here on a tiny config and tiny networks; the embedded demo takes minutes)."""

from __future__ import annotations

from anchordp3.logs import Capture
from anchordp3.pipeline.demo import PRETRAINED_EVAL_DIR, DemoOptions, demo_config, run_demo, shipped_models_present
from anchordp3.pipeline.evaluation import PRETRAINED_DIR, RUN_CONFIG_FILE
from anchordp3.schemas.run import RunConfig, load_run_config
from anchordp3.schemas.training import TrainingConfig
from tiny_models import tiny_data, tiny_training


def test_the_embedded_demo_covers_all_eight_tasks():
    cfg = demo_config()
    assert len(cfg.tasks) == 8 and demo_config("0").seed_list == [0]


def test_demo_runs_data_training_and_evaluation_and_prints_the_success_table(ray_session, tmp_path):
    cfg = RunConfig.model_validate(tiny_data("tiny-demo", ["place_bell"], "0-1"))
    training = TrainingConfig.model_validate(tiny_training(3, 3, 3, loop={"log_interval_s": 30.0, "cpu_threads": 1}, device="cpu"))
    opts = DemoOptions(max_decisions=2, pretrained_max_decisions=2, workers=1, training=training, pretrained_episodes=1)
    with Capture() as cap:
        report = run_demo(tmp_path, cfg, opts=opts)
    assert report == tmp_path / "eval" / "report.md" and report.is_file()
    out = "\n".join(r.message for r in cap.records)
    assert (tmp_path / "frame.png").is_file() and (tmp_path / "models" / "policy" / "model.pt").is_file()
    rows = out.splitlines()
    headers = [i for i, row in enumerate(rows) if "95% CI" in row]  # the demo's success table, then the shipped policy's
    assert rows[headers[0]].startswith("task") and rows[headers[0] + 2].startswith("place_bell")
    assert any(str(report) in row for row in rows[headers[0]:])
    if shipped_models_present():
        assert len(headers) == 2 and (tmp_path / PRETRAINED_EVAL_DIR / "report.md").is_file()
        shipped = load_run_config(PRETRAINED_DIR / RUN_CONFIG_FILE).tasks  # a row for each task the shipped models do
        assert {rows[headers[1] + 2 + i].split()[0] for i in range(len(shipped))} == set(shipped)
