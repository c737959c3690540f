"""Whole-scene translation augmentation: the cloud and every end-effector position move together,
joints and grippers do not."""

from __future__ import annotations

import torch

from anchordp3.models.augment import jitter_grippers, random_translation, translate_scene
from anchordp3.schemas.state import ARMS, StateLayout

L = StateLayout(6)


def test_translating_the_scene_moves_points_and_end_effectors_and_nothing_else():
    g = torch.Generator().manual_seed(0)
    points, state, anchors = torch.rand(2, 5, 12, generator=g), torch.rand(2, 32, generator=g), torch.rand(2, 8, 32, generator=g)
    delta = torch.tensor([[0.01, -0.02, 0.0], [0.0, 0.03, 0.005]])
    before = [points.clone(), state.clone(), anchors.clone()]
    p, s, a = translate_scene(points, state, anchors, delta, L)
    assert torch.allclose(p[..., :3] - points[..., :3], delta[:, None, :]) and torch.equal(p[..., 3:], points[..., 3:])
    moved = torch.zeros(32, dtype=torch.bool)
    for arm in ARMS:
        moved[L.ee_xyz(arm)] = True
        assert torch.allclose(s[:, L.ee_xyz(arm)] - state[:, L.ee_xyz(arm)], delta)
        assert torch.allclose(a[:, :, L.ee_xyz(arm)] - anchors[:, :, L.ee_xyz(arm)], delta[:, None, :].expand(2, 8, 3))
    assert torch.equal(s[:, ~moved], state[:, ~moved]) and torch.equal(a[..., ~moved], anchors[..., ~moved])
    assert all(torch.equal(x, y) for x, y in zip(before, (points, state, anchors)))  # inputs untouched


def test_random_translations_stay_inside_their_extent_and_repeat_with_the_seed():
    d = random_translation(1000, (0.03, 0.02, 0.0), torch.Generator().manual_seed(1))
    assert d.shape == (1000, 3) and (d.abs() <= torch.tensor([0.03, 0.02, 0.0]) + 1e-9).all() and d[:, 0].abs().max() > 0.025
    assert torch.equal(d, random_translation(1000, (0.03, 0.02, 0.0), torch.Generator().manual_seed(1)))


def test_jittering_the_grippers_moves_only_the_states_end_effector_positions():
    state = torch.rand(500, 32, generator=torch.Generator().manual_seed(2))
    out = jitter_grippers(state, 0.01, L, torch.Generator().manual_seed(3))
    moved = torch.zeros(32, dtype=torch.bool)
    for arm in ARMS:
        moved[L.ee_xyz(arm)] = True
    d = out - state
    assert torch.equal(d[:, ~moved], torch.zeros_like(d[:, ~moved]))
    assert abs(float(d[:, moved].std()) - 0.01) < 0.001 and abs(float(d[:, moved].mean())) < 0.001
    assert torch.equal(out, jitter_grippers(state, 0.01, L, torch.Generator().manual_seed(3)))
