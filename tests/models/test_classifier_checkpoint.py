"""The classifier's model.pt holds only what fine-tuning changed; the rest loads from the encoder
its package ships, and the loaded classifier is the trained one."""

from __future__ import annotations

import torch

from anchordp3.schemas.training import TrainingConfig
from anchordp3.stages.train_classifier import load_classifier, train_classifier


def test_a_classifier_tuning_its_top_layer_ships_only_that_layer_and_loads_back_equal(tmp_path):
    cfg = TrainingConfig.model_validate({"device": "cpu", "classifier": {
        "instructions": {"count": 64}, "tune_layers": 1, "optim": {"steps": 2, "batch_size": 8, "warmup_steps": 1}}})
    result = train_classifier(cfg, tmp_path, torch.device("cpu"))
    ckpt = torch.load(result.model_path, weights_only=False)
    keys = list(ckpt["state_dict"])
    assert ckpt["partial_state_dict"] and "head.weight" in keys
    assert all(k.startswith(("head.", "encoder.encoder.layer.5.", "encoder.pooler.")) for k in keys), keys
    assert not any("embeddings" in k or "layer.0." in k for k in keys)
    model = load_classifier(result.model_path)
    for k, v in ckpt["state_dict"].items():
        assert torch.equal(model.state_dict()[k], v)
    texts = ["pick up the bell and put it on the scale", "stack the three blocks"]
    assert model.predict(texts).shape == (2,)
