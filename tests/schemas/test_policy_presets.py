"""The policy's two named presets and its object head as one optional section: ``report`` is the
report's model, ``recipe`` with the eight-task recipe's object head is what ships (the shipped
checkpoint's settings, field for field), a field beside a preset overrides it, and configs and
checkpoints of the earlier flat form read the same."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from pydantic import ValidationError

from anchordp3.schemas.recipe import load_recipe_config
from anchordp3.schemas.training import FLAT_OBJECT_FIELDS, PolicyConfig, TrainingConfig

ROOT = Path(__file__).resolve().parents[2]


def test_the_report_preset_is_the_point_encoder_alone_on_absolute_anchors():
    report = PolicyConfig(preset="report")
    assert report.objects is None and report.target == "absolute" and report.normalizer_min_range == 0
    assert report.cond_dim == report.point_encoder.out_dim + report.state_encoder.hidden_dim


def test_the_shipped_policy_is_what_the_eight_task_recipe_trains():
    shipped = torch.load(ROOT / "anchordp3" / "pretrained" / "policy" / "model.pt", weights_only=False)["config"]
    read = PolicyConfig.model_validate(shipped)
    recipe = load_recipe_config(ROOT / "configs" / "recipe_eight.yaml").training.policy.model
    assert recipe.preset == "recipe" and recipe.objects.source == "roles"
    assert recipe.model_copy(update={"scheduler": read.scheduler}) == read  # shipped with its own DDIM steps
    assert load_recipe_config(ROOT / "configs" / "recipe.yaml").training.policy.model.preset == "recipe"


def test_fields_beside_a_preset_override_it_and_sections_given_in_part_keep_the_rest():
    cfg = TrainingConfig.model_validate({"policy": {"model": {"preset": "recipe", "objects": {"tokens": 3}}}})
    objects = cfg.policy.model.objects
    assert objects.tokens == 3 and objects.anchored_offsets and objects.z_weight == 5.0
    plain = TrainingConfig.model_validate({"policy": {"model": {"preset": "recipe", "objects": None}}}).policy.model
    assert plain.objects is None and plain.target == "relative"
    with pytest.raises(ValidationError, match="preset"):
        PolicyConfig.model_validate({"preset": "fast"})


def test_the_object_head_s_earlier_flat_fields_read_into_its_section():
    flat = {"object_tokens": 2, "object_orientation": True, "token_z_weight": 5.0, "anchored_offsets": True,
            "gate_supervision": 0.1, "held_offsets": True, "held_destination": True, "stay_radius": 0.01}
    assert set(flat) <= set(FLAT_OBJECT_FIELDS)
    assert PolicyConfig.model_validate({**flat, "target": "relative"}).objects == PolicyConfig(preset="recipe").objects
    assert PolicyConfig.model_validate({"object_tokens": 0}).objects is None  # 0 was "no head"
