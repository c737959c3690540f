"""PointNet++ segmenter: grouping ops, output shape, metrics, and overfitting a structured scene."""

from __future__ import annotations

import pytest
import torch

from anchordp3.models.kernels import reference_kernels
from anchordp3.models.pointnet2_ops import (
    ball_query,
    farthest_point_sample,
    gather,
    square_distance,
    three_nn,
)
from anchordp3.models.segmenter import (
    PointNet2Segmenter,
    SegmentationCounts,
    segmentation_loss,
    segmentation_metrics,
)
from anchordp3.schemas.training import SegmenterConfig, SetAbstractionConfig

SMALL = SegmenterConfig(
    set_abstraction=(
        SetAbstractionConfig(npoint=96, radius=0.08, nsample=12, mlp=(32, 32)),
        SetAbstractionConfig(npoint=24, radius=0.2, nsample=12, mlp=(64, 64)),
    ),
    feature_propagation=((64,), (32, 32)),
    head_hidden=32,
)


def tabletop(batch: int, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Points (B, n, 11) of a table plane (z = 0.74) with a 6-10 cm box standing somewhere on it;
    labels (B, n) = 1 on the box's surface. Colours are random (uninformative); normals are exact."""
    g = torch.Generator().manual_seed(seed)
    clouds, labels = [], []
    for _ in range(batch):
        n_obj = n // 4
        table = torch.rand(n - n_obj, 3, generator=g) * torch.tensor([0.8, 0.5, 0.0]) + torch.tensor([-0.4, -0.25, 0.74])
        centre = torch.rand(2, generator=g) * torch.tensor([0.5, 0.3]) - torch.tensor([0.25, 0.15])
        half = 0.03 + 0.02 * torch.rand(3, generator=g)
        face = torch.randint(0, 5, (n_obj,), generator=g)  # 4 sides + top
        u = torch.rand(n_obj, 3, generator=g) * 2 - 1
        axis = torch.where(face < 4, face // 2, torch.full_like(face, 2))
        sign = torch.where(face < 4, (face % 2) * 2 - 1, torch.ones_like(face)).float()
        u[torch.arange(n_obj), axis] = sign
        box = u * half + torch.tensor([centre[0], centre[1], 0.74 + half[2]])
        normals = torch.zeros(n, 3)
        normals[: n - n_obj, 2] = 1.0
        normals[n - n_obj + torch.arange(n_obj), axis] = sign
        xyz = torch.cat([table, box])
        rgb = torch.rand(n, 3, generator=g)
        curv = torch.full((n, 2), -11.5)
        perm = torch.randperm(n, generator=g)
        clouds.append(torch.cat([xyz, rgb, normals, curv], dim=1)[perm])
        labels.append(torch.cat([torch.zeros(n - n_obj), torch.ones(n_obj)])[perm])
    return torch.stack(clouds).float(), torch.stack(labels)


def test_fps_is_deterministic_spread_and_unique() -> None:
    xyz = torch.rand(2, 300, 3, generator=torch.Generator().manual_seed(0))
    idx = farthest_point_sample(xyz, 40)
    assert idx.shape == (2, 40)
    assert torch.equal(idx, farthest_point_sample(xyz, 40))
    for b in range(2):
        assert len(set(idx[b].tolist())) == 40
    picked = gather(xyz, idx)
    d = square_distance(picked, picked) + torch.eye(40) * 10
    rand = xyz[:, :40]
    d_rand = square_distance(rand, rand) + torch.eye(40) * 10
    assert (d.amin(dim=(1, 2)) > d_rand.amin(dim=(1, 2))).all()  # FPS picks are farther apart than the first 40


def test_fps_on_the_cpu_picks_what_the_reference_loop_picks() -> None:
    g = torch.Generator().manual_seed(1)
    xyz = torch.rand(3, 500, 3, generator=g)
    xyz[2, 250:] = xyz[2, :250]  # a cloud of duplicated points, as FPS-repeated clouds are
    for n in (1, 64, 250, 400):
        fast = farthest_point_sample(xyz, n)
        with reference_kernels():
            loop = farthest_point_sample(xyz, n)
        assert torch.equal(fast[:2], loop[:2])
        assert torch.equal(gather(xyz, fast), gather(xyz, loop))  # duplicates: the same points, maybe the other copy


def test_ball_query_stays_in_radius_and_three_nn_weights_sum_to_one() -> None:
    xyz = torch.rand(1, 200, 3, generator=torch.Generator().manual_seed(1))
    centres = xyz[:, :10]
    groups = ball_query(0.15, 8, xyz, centres)
    assert groups.shape == (1, 10, 8)
    dist = (gather(xyz, groups) - centres.unsqueeze(2)).norm(dim=-1)
    assert (dist <= 0.15 + 1e-6).all()
    idx, w = three_nn(xyz, centres)
    assert idx.shape == w.shape == (1, 200, 3)
    torch.testing.assert_close(w.sum(-1), torch.ones(1, 200))
    assert (idx[0, :10, 0] == torch.arange(10)).all()  # a centroid's nearest coarse point is itself


def test_output_shape_and_metrics() -> None:
    torch.manual_seed(0)
    model = PointNet2Segmenter(SMALL)
    points, labels = tabletop(2, 160, seed=0)
    logits = model(points)
    assert logits.shape == (2, 160) and logits.dtype == torch.float32
    with pytest.raises(ValueError, match=r"\(B, N, 11\)"):
        model(points[..., :6])
    perfect = (labels * 20 - 10)
    assert segmentation_metrics(perfect, labels) == {"iou": 1.0, "precision": 1.0, "recall": 1.0}
    half = SegmentationCounts().add(torch.tensor([5.0, 5.0, -5.0, -5.0]), torch.tensor([1, 0, 1, 0]))
    assert (half.tp, half.fp, half.fn, half.tn) == (1, 1, 1, 1)
    assert half.iou == pytest.approx(1 / 3) and half.precision == 0.5 and half.recall == 0.5


def test_overfits_a_few_structured_scenes() -> None:
    torch.manual_seed(0)
    model = PointNet2Segmenter(SMALL)
    points, labels = tabletop(4, 256, seed=1)
    flat = points.reshape(-1, 11)
    model.set_normalizer({"min": flat.min(0).values, "max": flat.max(0).values})
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        loss = segmentation_loss(model(points), labels)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    model.eval()
    unseen_points, unseen_labels = tabletop(4, 256, seed=7)
    with torch.no_grad():
        seen = segmentation_metrics(model(points), labels)
        unseen = segmentation_metrics(model(unseen_points), unseen_labels)
    assert sum(losses[-5:]) / 5 < 0.3 * sum(losses[:5]) / 5, losses
    assert seen["iou"] > 0.9, seen
    assert unseen["iou"] > 0.8, unseen  # it learnt the structure, not the samples
    assert model.probabilities(points).shape == (4, 256)


def test_the_segmenter_learns_critical_or_not_from_role_labels():
    from anchordp3.models.segmenter import SegmentationCounts, segmentation_loss

    logits = torch.tensor([[4.0, -4.0, 4.0, 4.0]])
    roles = torch.tensor([[1, 0, 3, 255]], dtype=torch.uint8)  # an object, nothing, another object, the robot
    assert segmentation_loss(logits, roles) == segmentation_loss(logits, (roles > 0).to(torch.uint8))
    counts = SegmentationCounts().add(logits, roles)
    assert (counts.tp, counts.fp, counts.fn, counts.tn) == (3, 0, 0, 1)
