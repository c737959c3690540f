"""MinMaxNormalizer: [-1, 1] mapping, exact round trip, constant dimensions, state_dict round trip."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from anchordp3.models.normalizer import MinMaxNormalizer


def test_maps_limits_to_unit_interval_and_round_trips() -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.randn(100, 8, 32, generator=g) * torch.linspace(0.01, 5, 32) + torch.linspace(-3, 3, 32)
    norm = MinMaxNormalizer.fit(x)
    y = norm.normalize(x)
    assert y.shape == x.shape
    flat = y.reshape(-1, 32)
    torch.testing.assert_close(flat.min(0).values, -torch.ones(32), atol=1e-5, rtol=0)
    torch.testing.assert_close(flat.max(0).values, torch.ones(32), atol=1e-5, rtol=0)
    torch.testing.assert_close(norm.unnormalize(y), x, atol=1e-5, rtol=1e-5)


def test_constant_dimension_maps_to_zero_and_round_trips() -> None:
    x = torch.stack([torch.linspace(0, 1, 10), torch.full((10,), 0.7)], dim=1)
    norm = MinMaxNormalizer.from_stats({"min": x.min(0).values.numpy(), "max": x.max(0).values.tolist()})
    y = norm(x)
    assert torch.isfinite(y).all()
    torch.testing.assert_close(y[:, 1], torch.zeros(10))
    torch.testing.assert_close(norm.unnormalize(y), x)


def test_per_horizon_stats_are_reduced_and_state_dict_restores() -> None:
    lo = np.stack([np.full(4, -1.0), np.full(4, -2.0)])
    hi = np.stack([np.full(4, 3.0), np.full(4, 1.0)])
    norm = MinMaxNormalizer.from_stats({"min": lo, "max": hi})
    torch.testing.assert_close(norm.min, torch.full((4,), -2.0))
    torch.testing.assert_close(norm.max, torch.full((4,), 3.0))
    fresh = MinMaxNormalizer(4)
    assert not bool(fresh.fitted)
    fresh.load_state_dict(norm.state_dict())
    assert bool(fresh.fitted)
    x = torch.rand(5, 4) * 5 - 2
    torch.testing.assert_close(fresh(x), norm(x))


def test_bad_stats_are_clear_errors() -> None:
    with pytest.raises(ValueError, match="max < min"):
        MinMaxNormalizer.from_stats({"min": [1.0, 0.0], "max": [0.0, 1.0]})
    with pytest.raises(KeyError, match="'max'"):
        MinMaxNormalizer.from_stats({"min": [0.0]})
    with pytest.raises(ValueError, match="last axis"):
        MinMaxNormalizer(3).normalize(torch.zeros(2, 4))


def test_a_nearly_constant_dimension_is_not_stretched_past_the_minimum_range():
    import torch

    from anchordp3.models.normalizer import MinMaxNormalizer

    norm = MinMaxNormalizer(2)
    norm.set_limits(torch.tensor([0.0, 1.0]), torch.tensor([0.5, 1.0003]), min_range=0.05)
    y = norm(torch.tensor([[0.25, 1.00015], [0.5, 1.0003]]))
    assert torch.allclose(y[:, 0], torch.tensor([0.0, 1.0]), atol=1e-6)  # a wide dimension keeps its limits
    assert torch.allclose(y[:, 1], torch.tensor([0.0, 0.0003 / 0.05]), atol=1e-4)  # 0.0003 of span maps to 0.012, not 2
    assert torch.allclose(norm.unnormalize(y), torch.tensor([[0.25, 1.00015], [0.5, 1.0003]]), atol=1e-6)
