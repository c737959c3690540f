"""Training the three models on a real (tiny) dataset: manifests and checksums, falling losses,
untouched encoders of absent tasks, checkpoint round trips, resume after a stop or a crash to the
same step and the same weights, up-to-date reruns, stale refusals, one-line CLI errors."""

from __future__ import annotations

import copy
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from typer.testing import CliRunner

from anchordp3.logs import Capture
from anchordp3.cli import app
from anchordp3.dataset.files import file_sha256
from anchordp3.dataset.reader import open_dataset
from anchordp3.models.device import seed_everything
from anchordp3.models.kernels import reference_kernels
from anchordp3.models.policy import AnchorDiffusionPolicy
from anchordp3.pipeline.runner import RunOptions, run_pipeline
from anchordp3.pipeline.store import read_manifest
from anchordp3.pipeline.runner import LOG_FILE
from anchordp3.pipeline.targets import train_models
from anchordp3.pipeline.training import load_training_config, model_dir
from anchordp3.schemas.training import MODELS
from anchordp3.pipeline.work import stage_dir
from anchordp3.schemas.records import ModelInfo
from anchordp3.schemas.run import RunConfig
from anchordp3.schemas.tasks import task_id
from anchordp3.schemas.training import TrainingConfig
from anchordp3.stages import training_loop
from anchordp3.stages.train_classifier import load_classifier
from anchordp3.stages.train_policy import CriticalChannel, PolicyJob, load_policy, train_policy
from anchordp3.stages.train_segmenter import SegmenterJob, load_segmenter
from anchordp3.stages.training_loop import load_checkpoint, read_metrics, run_training
from tiny_models import tiny_data, tiny_training

DATA = tiny_data("tiny-train", ["place_mouse", "place_bell"], "0-1")
TRAIN = tiny_training(40, 12, 40, val_predict_samples=8, loop={"log_interval_s": 0.5})  # tiny networks, a few dozen steps each


def tiny_cfg(steps: int | None = None, device: str = "auto", **loop) -> TrainingConfig:
    """``TRAIN`` with every model's steps and some loop settings replaced."""
    data = copy.deepcopy(TRAIN)
    for name in MODELS if steps else ():
        data[name]["optim"]["steps"] = steps
    data["loop"].update(loop)
    return TrainingConfig.model_validate({**data, "device": device})


@pytest.fixture(scope="module")
def train_yaml(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "training.yaml"
    path.write_text(yaml.safe_dump(TRAIN))
    return path


@pytest.fixture(scope="module")
def run_dir(ray_session, tmp_path_factory) -> Path:
    """A finished tiny data run (2 tasks x 2 seeds, 256 points)."""
    run = tmp_path_factory.mktemp("run")
    run_pipeline(RunConfig.model_validate(DATA), run, RunOptions(progress_interval=60))
    return run


@pytest.fixture(scope="module")
def trained(run_dir, train_yaml):
    """``train_models`` of all three models, with the progress lines it said."""
    with Capture() as cap:
        results = train_models(run_dir, MODELS, load_training_config(train_yaml))
    return run_dir, results, [r.message for r in cap.records]


def test_train_all_writes_each_model_with_its_manifest(trained):
    run, results, lines = trained
    assert [(t.name, t.status) for t in results] == [(m, "trained") for m in MODELS]
    want = {"segmenter": {"loss", "iou", "precision", "recall"}, "classifier": {"loss", "accuracy"},
            "policy": {"loss", "anchor_mse", "first_cm", "first_deg", "first_rad"}}
    dataset_sum = file_sha256(stage_dir(run, "write") / "dataset.json")
    for name in MODELS:
        d = model_dir(run, name)
        m = read_manifest(d)
        assert m.stage == f"train-{name}" and m.complete and m.counts.done == 1
        rec = m.items[name]
        assert rec.status == "done" and rec.output == "model.pt"
        assert rec.checksum == file_sha256(d / "model.pt")
        per_task = {k for k in rec.payload(ModelInfo).metrics if "/" in k}  # first_cm/<task>, first_deg/<task>, first_rad/<task>
        assert set(rec.payload(ModelInfo).metrics) - per_task == want[name] and rec.payload(ModelInfo).steps == TRAIN[name]["optim"]["steps"]
        assert all(k.split("/")[0] in ("first_cm", "first_deg", "first_rad") for k in per_task)
        assert rec.payload(ModelInfo).checkpoint == f"models/{name}/model.pt"
        assert m.fingerprint.upstream.get("dataset") == (None if name == "classifier" else dataset_sum)
        assert (d / "loss.png").read_bytes()[:4] == b"\x89PNG"
        assert list((d / "tensorboard").glob("events.out.tfevents.*"))
        assert (d / "training.yaml").is_file() and not (d / "checkpoints").exists()
        rows = read_metrics(d / "metrics.csv")
        assert {int(r["step"]) for r in rows if r["metric"] == "loss" and r["split"] == "train"} == set(range(1, rec.payload(ModelInfo).steps + 1))
        assert any(r["split"] == "val" for r in rows)
    policy = read_manifest(model_dir(run, "policy"))
    assert policy.items["policy"].payload(ModelInfo).critical_channel == "segmenter"
    assert policy.fingerprint.upstream["segmenter"] == read_manifest(model_dir(run, "segmenter")).items["segmenter"].checksum
    assert any("steps/s" in line and "ETA" in line for line in lines)
    assert any("the segmenter's pass: sample" in line and "samples/s" in line for line in lines)  # before the policy's steps
    assert "policy: done in" in (run / LOG_FILE).read_text()  # the run's training log holds the same lines
    assert 0.0 <= read_manifest(model_dir(run, "segmenter")).items["segmenter"].payload(ModelInfo).metrics["iou"] <= 1.0


def test_training_losses_fall(trained):
    run = trained[0]
    for name in MODELS:
        losses = [float(r["value"]) for r in read_metrics(model_dir(run, name) / "metrics.csv")
                  if r["split"] == "train" and r["metric"] == "loss"]
        k = max(2, len(losses) // 5)
        assert sum(losses[-k:]) / k < 0.85 * sum(losses[:k]) / k, (name, losses)


def test_policy_leaves_the_encoders_of_absent_tasks_untouched(trained):
    run = trained[0]
    cfg = tiny_cfg()
    seed_everything(cfg.seed)
    init = AnchorDiffusionPolicy(cfg.policy.model).state_dict()
    ckpt = load_checkpoint(model_dir(run, "policy") / "model.pt")
    present = {task_id(t) for t in DATA["tasks"]}
    for weights in (ckpt["state_dict"], ckpt["ema_state_dict"]):
        for k in range(cfg.policy.model.num_tasks):
            keys = [n for n in init if n.startswith(f"point_encoder.encoders.{k}.")]
            same = all(torch.equal(weights[n], init[n]) for n in keys)
            assert same == (k not in present), (k, same)


def test_checkpoints_load_back_to_identical_outputs(trained, tmp_path):
    run = trained[0]
    data = open_dataset(stage_dir(run, "write"))
    cfg = tiny_cfg(steps=3)
    cpu = torch.device("cpu")
    batch = next(iter(training_loop.eval_batches(PolicyJob(data, cfg, cpu, CriticalChannel("ground_truth")).val_ds, 4)))

    seg = SegmenterJob(data, cfg, cpu)
    res = run_training(seg, tmp_path / "seg", cfg.loop, "fp")
    seg.model.eval()
    assert torch.equal(seg.model(batch["points"]), load_segmenter(res.model_path)(batch["points"]))

    pol = PolicyJob(data, cfg, cpu, CriticalChannel("ground_truth"))
    res = run_training(pol, tmp_path / "pol", cfg.loop, "fp")
    obs = pol.observation(batch)
    loaded = load_policy(res.model_path)
    own = pol.ema.averaged_model.state_dict()
    assert all(torch.equal(own[k], v) for k, v in loaded.state_dict().items())
    with reference_kernels():  # PyTorch's own kernels: bit for bit
        want = pol.ema.averaged_model.predict(obs, generator=torch.Generator().manual_seed(3))
        got = loaded.predict(obs, generator=torch.Generator().manual_seed(3))
    assert torch.equal(want, got) and want.shape == (4, 8, 32)
    fast = [m.predict(obs, generator=torch.Generator().manual_seed(3)) for m in (pol.ema.averaged_model, loaded)]
    torch.testing.assert_close(fast[0], fast[1], atol=1e-5, rtol=1e-5)  # the CPU kernels' small products: alignment decides rounding

    clf_dir = model_dir(run, "classifier")
    clf = load_classifier(clf_dir / "model.pt")
    from anchordp3.models.instructions import generate_instructions

    texts, labels = generate_instructions(cfg.classifier.instructions).texts_and_labels("val")
    accuracy = int((clf.predict(texts).cpu() == torch.tensor(labels)).sum()) / len(labels)
    assert accuracy == pytest.approx(read_manifest(clf_dir).items["classifier"].payload(ModelInfo).metrics["accuracy"], abs=1e-9)


def test_the_policys_fitted_choice_offsets_and_yaws_travel_in_its_checkpoint(trained, tmp_path):
    data = open_dataset(stage_dir(trained[0], "write"))
    raw = copy.deepcopy(TRAIN)
    raw["policy"]["optim"]["steps"] = 3
    raw["policy"]["model"].update(preset="recipe", objects={"choice_offsets": True, "anchored_yaw": True,
                                                             "heading": True, "held_yaw": True})
    cfg = TrainingConfig.model_validate({**raw, "device": "cpu"})
    with Capture() as cap:
        job = PolicyJob(data, cfg, torch.device("cpu"), CriticalChannel("ground_truth"))
    assert any("per-choice offsets fitted on" in r.message for r in cap.records)
    fitted = job.model.choice_xyz.clone()
    assert fitted.abs().sum() > 0  # the mice's and bells' pre-grasps lie beside their objects
    res = run_training(job, tmp_path / "pol", cfg.loop, "fp")
    loaded = load_policy(res.model_path)
    assert torch.equal(loaded.choice_xyz, fitted) and torch.equal(loaded.choice_yaw, job.model.choice_yaw)
    assert torch.equal(loaded.held_yaw, job.model.held_yaw) and loaded.objects.heading


def test_stopped_or_crashed_training_resumes_to_the_same_step_and_weights(trained, tmp_path, monkeypatch):
    run = trained[0]
    data = open_dataset(stage_dir(run, "write"))
    cfg = tiny_cfg(steps=8, checkpoint_every=2, eval_every=3)
    cpu, ch = torch.device("cpu"), CriticalChannel("ground_truth")
    ref = train_policy(data, cfg, tmp_path / "ref", cpu, ch, "fp")

    stopped = train_policy(data, cfg, tmp_path / "stop", cpu, ch, "fp", stop_at=3)
    assert not stopped.finished and stopped.step == 3 and (tmp_path / "stop/checkpoints/last.pt").is_file()
    resumed = train_policy(data, cfg, tmp_path / "stop", cpu, ch, "fp")
    assert resumed.finished and (resumed.resumed_from, resumed.step) == (3, 8)

    calls = {"n": 0}
    real_step = PolicyJob.train_step

    def crash_at_six(self, batch):
        calls["n"] += 1
        if calls["n"] == 6:
            raise RuntimeError("simulated crash")
        return real_step(self, batch)

    monkeypatch.setattr(PolicyJob, "train_step", crash_at_six)
    with pytest.raises(RuntimeError, match="simulated crash"):
        train_policy(data, cfg, tmp_path / "crash", cpu, ch, "fp")
    monkeypatch.setattr(PolicyJob, "train_step", real_step)
    crashed = train_policy(data, cfg, tmp_path / "crash", cpu, ch, "fp")
    assert (crashed.resumed_from, crashed.step) == (4, 8)  # last periodic checkpoint
    rows = [r for r in read_metrics(tmp_path / "crash/metrics.csv") if r["split"] == "train" and r["metric"] == "loss"]
    assert [int(r["step"]) for r in rows] == list(range(1, 9))  # rows of the lost steps 5 were dropped

    want = load_checkpoint(ref.model_path)
    for r in (resumed, crashed):
        got = load_checkpoint(r.model_path)
        for key in ("state_dict", "ema_state_dict"):
            assert all(torch.equal(want[key][n], got[key][n]) for n in want[key]), key
        assert got["metrics"] == want["metrics"]


def test_pipeline_stop_then_rerun_resumes_and_stale_models_are_refused(trained, train_yaml, tmp_path):
    src = trained[0]
    run = tmp_path / "run"
    shutil.copytree(src, run, ignore=shutil.ignore_patterns("classifier", ".lock"))
    shutil.rmtree(model_dir(run, "segmenter"))
    cfg = load_training_config(train_yaml)
    first = train_models(run, ["segmenter"], cfg, stop_at={"segmenter": 10})
    assert first[0].status == "stopped" and not read_manifest(model_dir(run, "segmenter")).complete
    again = train_models(run, ["segmenter"], cfg)
    assert again[0].status == "trained" and again[0].record.payload(ModelInfo).resumed_from == 10
    assert again[0].record.payload(ModelInfo).steps == TRAIN["segmenter"]["optim"]["steps"]
    # same config, same dataset, same code: the weights match the uninterrupted run's
    assert load_checkpoint(model_dir(run, "segmenter") / "model.pt")["step"] == 40
    ref = load_checkpoint(model_dir(src, "segmenter") / "model.pt")["state_dict"]
    got = load_checkpoint(model_dir(run, "segmenter") / "model.pt")["state_dict"]
    assert all(torch.equal(ref[n], got[n]) for n in ref)

    with pytest.raises(ValueError, match="different training config; pass --force"):
        train_models(run, ["segmenter"], load_training_config(train_yaml, steps=5))
    forced = train_models(run, ["segmenter"], load_training_config(train_yaml, steps=5), force=True)
    assert forced[0].status == "trained" and forced[0].record.payload(ModelInfo).steps == 5
    with pytest.raises(ValueError, match="different segmenter"):  # the policy's channel came from the old one
        train_models(run, ["policy"], cfg)


def test_what_training_would_refuse_late_is_refused_before_anything_trains(trained, train_yaml, tmp_path):
    src = trained[0]
    run = tmp_path / "run"
    shutil.copytree(src, run, ignore=shutil.ignore_patterns(".lock"))
    cfg = load_training_config(train_yaml)
    # a policy on a run without a segmenter: 'auto' would silently take the simulator's masks
    shutil.rmtree(model_dir(run, "segmenter"))
    with pytest.raises(ValueError, match="label_channel 'auto': .* no trained segmenter"):
        train_models(run, ["policy"], cfg)
    # train all would retrain the segmenter, then refuse the policy trained on the old one: refused first
    policy_before = (model_dir(run, "policy") / "model.pt").read_bytes()
    with pytest.raises(ValueError, match="trained on the segmenter this call trains anew; pass --force"):
        train_models(run, ["segmenter", "classifier", "policy"], cfg)
    assert not model_dir(run, "segmenter").exists()  # nothing was trained
    assert (model_dir(run, "policy") / "model.pt").read_bytes() == policy_before
    # a changed config of the last model is refused before the first one trains
    shutil.copytree(model_dir(src, "segmenter"), model_dir(run, "segmenter"))
    changed = load_training_config(train_yaml).model_copy(update={"policy": cfg.policy.model_copy(update={"val_predict_samples": 3})})
    with pytest.raises(ValueError, match=r"models/policy: trained with a different training config; pass --force"):
        train_models(run, ["segmenter", "classifier", "policy"], changed)


def test_cli_train_reports_up_to_date_models_and_bad_input_in_one_line(trained, train_yaml, tmp_path):
    run = trained[0]
    cli = CliRunner()
    ok = cli.invoke(app, ["train", "all", "--run-dir", str(run), "--config", str(train_yaml)])
    assert ok.exit_code == 0, ok.output
    assert ok.stdout.count("up-to-date") == 3 and "accuracy" in ok.stdout

    bad = tmp_path / "bad.yaml"
    cases = {
        "policy.optim.lr": {"policy": {"optim": {"lr": -1}}},
        "segmenter.model.nope": {"segmenter": {"model": {"nope": 1}}},
    }
    for field, content in cases.items():
        bad.write_text(yaml.safe_dump(content))
        r = cli.invoke(app, ["train", "policy", "--run-dir", str(run), "--config", str(bad)])
        assert r.exit_code == 2 and r.stderr.startswith("error: ") and field in r.stderr and r.stderr.count("\n") == 1, r.stderr
    for args, text in (
        (["--device", "gpu"], "device"),
        (["--preset", "huge"], "unknown training preset"),
        (["--config", str(tmp_path / "missing.yaml")], "no such training config"),
    ):
        r = cli.invoke(app, ["train", "segmenter", "--run-dir", str(run), *args])
        assert r.exit_code == 2 and text in r.stderr and r.stderr.count("\n") == 1, r.stderr
    r = cli.invoke(app, ["train", "segmenter", "--run-dir", str(tmp_path / "nowhere")])
    assert r.exit_code == 2 and "not a run directory" in r.stderr


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_segmenter_and_policy_train_on_cuda_with_mixed_precision(trained, tmp_path):
    run = trained[0]
    data = open_dataset(stage_dir(run, "write"))
    cfg = tiny_cfg(steps=4, device="cuda")
    cuda = torch.device("cuda")
    for job in (SegmenterJob(data, cfg, cuda), PolicyJob(data, cfg, cuda, CriticalChannel("ground_truth"))):
        res = run_training(job, tmp_path / job.name, cfg.loop, "fp")
        assert res.finished and all(torch.isfinite(torch.tensor(v)) for v in res.metrics.values())


def test_the_first_anchors_rotation_error_is_the_angle_between_the_rotations():
    from anchordp3.models.objects import top_down_rot6
    from anchordp3.stages.train_policy import rotation_error_deg

    yaws = torch.tensor([-1.5, 0.0, 0.4, 3.0])
    true = top_down_rot6(yaws).numpy()
    turned = top_down_rot6(yaws + torch.tensor([0.0, 0.5236, -0.1745, 3.1416])).numpy()
    assert rotation_error_deg(true, true) == pytest.approx([0.0] * 4, abs=1e-4)
    assert rotation_error_deg(turned, true) == pytest.approx([0.0, 30.0, 10.0, 180.0], abs=0.01)
    assert rotation_error_deg(turned * 1.7 + 0.01, true) == pytest.approx([0.0, 30.0, 10.0, 180.0], abs=1.5)  # off the manifold
