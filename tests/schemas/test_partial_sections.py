"""A config section given in part keeps the rest of its own default, whichever loader reads it."""

from __future__ import annotations

from pathlib import Path

import yaml

from anchordp3.pipeline.training import load_training_config
from anchordp3.schemas.recipe import load_recipe_config
from anchordp3.schemas.run import PoolsConfig
from anchordp3.schemas.training import SegmenterTrainingConfig, TrainingConfig


def test_an_optimizer_given_in_part_keeps_the_segmenters_own_learning_rate_and_warm_up():
    own = SegmenterTrainingConfig().optim
    given = SegmenterTrainingConfig.model_validate({"optim": {"steps": 3000}}).optim
    assert given.steps == 3000
    assert (given.lr, given.weight_decay, given.warmup_steps, given.batch_size) == \
           (own.lr, own.weight_decay, own.warmup_steps, own.batch_size)
    assert given.lr == 1e-3  # not OptimizerConfig's bare 1e-4


def test_sections_are_overlaid_at_every_depth():
    cfg = TrainingConfig.model_validate({"classifier": {"optim": {"steps": 150}, "instructions": {"count": 40}},
                                         "policy": {"model": {"unet": {"kernel_size": 3}}}})
    default = TrainingConfig()
    assert cfg.classifier.optim.lr == default.classifier.optim.lr == 5e-5
    assert cfg.classifier.instructions.count == 40 and cfg.classifier.instructions.seed == default.classifier.instructions.seed
    assert cfg.policy.model.unet.kernel_size == 3
    assert cfg.policy.model.unet.down_dims == default.policy.model.unet.down_dims


def test_a_pool_given_in_part_keeps_its_own_cpu_share():
    pools = PoolsConfig.model_validate({"anchors": {"workers": 3}, "write": {"workers": 2}})
    assert (pools.anchors.workers, pools.anchors.cpus) == (3, 0.25)
    assert (pools.write.workers, pools.write.cpus) == (2, 0.5)


def test_the_recipe_and_train_config_read_the_same_training_section_alike(tmp_path):
    recipe = load_recipe_config(_repo_config("recipe.yaml"))
    section = tmp_path / "training.yaml"
    section.write_text(yaml.safe_dump(yaml.safe_load(_repo_config("recipe.yaml").read_text())["training"]))
    assert load_training_config(section) == recipe.training


def _repo_config(name: str) -> Path:
    return Path(__file__).resolve().parents[2] / "anchordp3" / "configs" / name
