"""Instruction classifier: offline loading of the packaged MiniLM, clear errors, a short fine-tune
that beats chance on held-out phrasing families."""

from __future__ import annotations

import os

import pytest
import torch

from anchordp3.models.classifier import (
    InstructionClassifier,
    accuracy,
    bundled_encoder_dir,
    classification_loss,
    resolve_weights_dir,
)
from anchordp3.models.instructions import generate_instructions
from anchordp3.schemas.tasks import TASK_NAMES
from anchordp3.schemas.training import ClassifierConfig, InstructionConfig


def test_bundled_weights_are_found_inside_site_packages() -> None:
    path = bundled_encoder_dir()
    assert "site-packages" in str(path) and path.name == "model"
    assert resolve_weights_dir(None) == path
    assert (path / "config.json").is_file()


def test_missing_weights_name_the_path(tmp_path) -> None:
    missing = tmp_path / "no-such-bert"
    with pytest.raises(FileNotFoundError, match=f"no Hugging Face checkpoint at {missing}"):
        resolve_weights_dir(missing)
    (tmp_path / "config.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match="no weights file at"):
        InstructionClassifier(ClassifierConfig(weights_dir=str(tmp_path)))


def test_short_fine_tune_beats_chance_on_held_out_families() -> None:
    assert os.environ.get("HF_HUB_OFFLINE") == "1"
    torch.manual_seed(0)
    clf = InstructionClassifier()
    bank = generate_instructions(InstructionConfig())
    train = bank.split("train")[::40]  # ~180 instructions, every task
    val = bank.split("val")[::20]  # ~140 instructions of phrasing families never trained on
    val_texts, val_y = [i.text for i in val], torch.tensor([i.task_id for i in val])
    tokens = clf.tokenize(val_texts[:3])
    assert tokens["input_ids"].shape == tokens["attention_mask"].shape and tokens["input_ids"].shape[0] == 3
    assert clf.logits(val_texts[:3]).shape == (3, len(TASK_NAMES))
    before = accuracy(clf.predict(val_texts), val_y)

    opt = torch.optim.AdamW(clf.parameter_groups(encoder_lr=1e-4, head_lr=3e-3, weight_decay=0.01))
    g = torch.Generator().manual_seed(0)
    clf.train()
    for _ in range(8):
        idx = torch.randint(len(train), (16,), generator=g).tolist()
        loss = classification_loss(clf.logits([train[i].text for i in idx]), torch.tensor([train[i].task_id for i in idx]))
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = accuracy(clf.predict(val_texts), val_y)
    print(f"classifier held-out-family accuracy: before {before:.3f}, after 8 steps {after:.3f} (chance {1 / len(TASK_NAMES):.3f})")
    assert clf.training  # predict restored the mode
    assert after > 0.5 and after > before + 0.3, (before, after)
