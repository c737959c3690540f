"""The same models on CUDA under autocast (skipped on machines without a GPU)."""

from __future__ import annotations

import pytest
import torch

from anchordp3.models.device import autocast, pick_device
from anchordp3.models.ema import ExponentialMovingAverage
from anchordp3.models.policy import AnchorDiffusionPolicy
from anchordp3.models.segmenter import PointNet2Segmenter, segmentation_loss

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def test_policy_trains_and_predicts_on_cuda_with_autocast() -> None:
    device = pick_device("auto")
    torch.manual_seed(0)
    policy = AnchorDiffusionPolicy().to(device)
    batch = {
        "points": torch.rand(4, 512, 12), "state": torch.rand(4, 32), "anchors": torch.rand(4, 8, 32),
        "task_id": torch.tensor([0, 1, 1, 7]),
    }
    policy.set_normalizers({"state": {"min": torch.zeros(32), "max": torch.ones(32)},
                            "anchors": {"min": torch.zeros(32), "max": torch.ones(32)},
                            "delta": {"min": -torch.ones(8, 32), "max": torch.ones(8, 32)}})
    ema = ExponentialMovingAverage(policy)
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-4)
    loss = policy.compute_loss(batch, generator=torch.Generator().manual_seed(0))
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    loss.backward()
    opt.step()
    ema.step(policy)
    out = ema.averaged_model.predict(batch, generator=torch.Generator().manual_seed(0))
    assert out.shape == (4, 8, 32) and out.device.type == "cuda" and out.dtype == torch.float32


def test_segmenter_runs_on_cuda_with_autocast() -> None:
    device = pick_device("auto")
    torch.manual_seed(0)
    model = PointNet2Segmenter().to(device)
    points = torch.rand(2, 1024, 11, device=device)
    with autocast(device):
        logits = model(points)
    loss = segmentation_loss(logits, torch.zeros(2, 1024, device=device))
    loss.backward()
    assert logits.shape == (2, 1024) and torch.isfinite(loss)
