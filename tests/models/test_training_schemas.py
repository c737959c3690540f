"""Training configs: CPU defaults and the report preset validate; bad values are named errors."""

from __future__ import annotations

import pytest
import torch
from pydantic import BaseModel, ValidationError

from anchordp3.models.device import autocast, needs_grad_scaler, pick_device
from anchordp3.models.unet1d import ConditionalUnet1D
from anchordp3.schemas import training
from anchordp3.schemas.training import (
    TASK_NAMES,
    PolicyConfig,
    TrainingConfig,
    UNetConfig,
    model_task_ids,
    task_id,
    training_preset,
)


def _models(cfg: BaseModel):
    yield type(cfg)
    for name in type(cfg).model_fields:
        value = getattr(cfg, name)
        if isinstance(value, BaseModel):
            yield from _models(value)
        elif isinstance(value, tuple):
            for v in value:
                if isinstance(v, BaseModel):
                    yield from _models(v)


def test_presets_validate_and_every_field_is_described() -> None:
    cpu, report = training_preset("cpu"), training_preset("report")
    assert cpu == TrainingConfig()
    assert report.policy.model.unet.down_dims == (512, 1024, 2048)
    assert report.policy.optim.batch_size == 128
    for cls in set(_models(cpu)) | set(_models(report)):
        assert cls.model_config.get("extra") == "forbid", cls
        for name, field in cls.model_fields.items():
            assert field.description, f"{cls.__name__}.{name} has no description"
    assert TrainingConfig.model_validate_json(report.model_dump_json()) == report
    with pytest.raises(ValueError, match="unknown training preset"):
        training_preset("huge")


def test_dp3_defaults() -> None:
    cfg = TrainingConfig().policy
    s = cfg.model.scheduler
    assert (s.num_train_timesteps, s.num_inference_steps, s.beta_schedule, s.clip_sample, s.prediction_type) == (
        100, 10, "squaredcos_cap_v2", True, "sample")
    assert (cfg.ema.power, cfg.ema.max_value) == (0.75, 0.9999)
    assert (cfg.optim.lr, cfg.optim.betas, cfg.optim.weight_decay) == (1e-4, (0.95, 0.999), 1e-6)
    assert (cfg.model.horizon, cfg.model.action_dim, cfg.model.point_encoder.out_dim) == (8, 32, 192)
    assert cfg.model.point_encoder.in_channels == 12 and cfg.model.cond_dim == 192 + 64


def test_bad_values_name_the_field() -> None:
    with pytest.raises(ValidationError, match="down_dims"):
        UNetConfig(down_dims=(60, 128))
    with pytest.raises(ValidationError, match="extra"):
        PolicyConfig(horizont=8)
    with pytest.raises(ValidationError, match="feature_propagation"):
        training.SegmenterConfig(feature_propagation=((64,),))
    assert [task_id(t) for t in TASK_NAMES] == list(range(8))
    assert model_task_ids(sorted(TASK_NAMES)) == [TASK_NAMES.index(t) for t in sorted(TASK_NAMES)]
    with pytest.raises(ValueError, match="unknown task"):
        task_id("place_object_scale")


def test_unet_shapes_and_horizon_check() -> None:
    unet = ConditionalUnet1D(32, 40, UNetConfig(down_dims=(16, 32, 64), step_embed_dim=16))
    out = unet(torch.randn(2, 8, 32), torch.tensor([0, 99]), torch.randn(2, 40))
    assert out.shape == (2, 8, 32)
    assert unet(torch.randn(3, 16, 32), 5, torch.randn(3, 40)).shape == (3, 16, 32)
    with pytest.raises(ValueError, match="horizon 6"):
        unet(torch.randn(1, 6, 32), 0, torch.randn(1, 40))


def test_device_helpers_on_this_machine() -> None:
    device = pick_device("auto")
    assert device.type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert pick_device("cpu") == torch.device("cpu")
    with autocast("cpu"):
        assert not torch.is_autocast_enabled("cpu")
    assert not needs_grad_scaler("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="no CUDA device"):
            pick_device("cuda")
