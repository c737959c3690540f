"""Role tokens: the segmenter names each point's object role, and the policy's token j is role
j + 1's points, whatever the objects' sizes, places or the point order."""

from __future__ import annotations

import pytest
import torch
from pydantic import ValidationError

from anchordp3.models.encoders import append_critical_probability
from anchordp3.models.objects import POSITION_SCALE, object_tokens, split_alike
from anchordp3.models.policy import AnchorDiffusionPolicy
from anchordp3.models.segmenter import PointNet2Segmenter, SegmentationCounts, segmentation_loss
from anchordp3.schemas.state import StateLayout
from anchordp3.schemas.tasks import task_id
from anchordp3.schemas.training import ObjectHeadConfig, PolicyConfig, SegmenterConfig
from tests.models.test_object_tokens import head
from tests.models.test_policy_model import TINY, samples, stats_of
from tests.models.test_segmenter_model import SMALL

LAYOUT = StateLayout()


def blocks(seed: int, n: int = 300) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """A table with three equal 5 cm blocks at random places, told apart only by colour (red, green,
    blue: roles 1, 2, 3): points (1, N, 11), roles (1, N) uint8 and the three blocks' centroids."""
    g = torch.Generator().manual_seed(seed)
    table = torch.rand(n, 3, generator=g) * torch.tensor([0.8, 0.6, 0.0]) - torch.tensor([0.4, 0.3, -0.74])
    parts, roles, rgbs, centres = [table], [torch.zeros(n, dtype=torch.uint8)], [torch.full((n, 3), 0.5)], []
    for role, colour in enumerate(([0.9, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.9]), start=1):
        c = torch.rand(2, generator=g) * torch.tensor([0.6, 0.4]) - torch.tensor([0.3, 0.2])
        pts = torch.rand(80, 3, generator=g) * 0.05 + torch.tensor([c[0] - 0.025, c[1] - 0.025, 0.74])
        parts.append(pts)
        roles.append(torch.full((80,), role, dtype=torch.uint8))
        rgbs.append(torch.tensor(colour).expand(80, 3))
        centres.append(pts.mean(0))
    xyz, rgb = torch.cat(parts), torch.cat(rgbs)
    perm = torch.randperm(len(xyz), generator=g)
    feats = torch.cat([xyz, rgb, torch.zeros(len(xyz), 3), torch.full((len(xyz), 2), -11.5)], dim=1)
    return feats[perm][None].float(), torch.cat(roles)[perm][None], centres


def test_role_tokens_keep_each_object_in_its_place_whatever_the_order_of_points() -> None:
    points, roles, centres = blocks(0)
    full = append_critical_probability(points, (roles > 0).float())
    state = torch.zeros(1, 32)
    tokens = object_tokens(full, state, LAYOUT, 4, roles=roles)
    for j, centre in enumerate(centres):  # token j: role j + 1, the red, green and blue block
        torch.testing.assert_close(tokens[0, j, :3] / POSITION_SCALE, centre, atol=1e-5, rtol=0)
    assert tokens[0, 3].abs().sum() == 0  # role 4 (a target) is not in this scene: a zero token
    perm = torch.randperm(points.shape[1], generator=torch.Generator().manual_seed(1))
    again = object_tokens(full[:, perm], state, LAYOUT, 4, roles=roles[:, perm])
    torch.testing.assert_close(again, tokens)


def test_role_logits_train_by_cross_entropy_and_refuse_a_role_beyond_the_head() -> None:
    logits = torch.zeros(1, 3, 5)  # roles 1..4
    logits[0, 0, 0] = logits[0, 1, 2] = logits[0, 2, 4] = 6.0
    labels = torch.tensor([[0, 2, 4]], dtype=torch.uint8)
    assert float(segmentation_loss(logits, labels)) < 0.02
    counts = SegmentationCounts().add(logits, torch.tensor([[0, 2, 3]], dtype=torch.uint8))
    assert (counts.tp, counts.fp, counts.fn, counts.tn) == (2, 0, 0, 1)  # critical is any role
    assert counts.as_dict()["role_accuracy"] == 0.5  # the second object was given role 4, not its 3
    with pytest.raises(ValueError, match="segmenter.model.roles: 4.*role 255"):
        segmentation_loss(logits, torch.tensor([[0, 2, 255]], dtype=torch.uint8))


def test_the_segmenter_learns_to_tell_alike_blocks_apart_by_their_role() -> None:
    torch.manual_seed(0)
    model = PointNet2Segmenter(SegmenterConfig.model_validate({**SMALL.model_dump(), "roles": 4}))
    scenes = [blocks(s) for s in range(6)]
    points, roles = torch.cat([p for p, _, _ in scenes]), torch.cat([r for _, r, _ in scenes])
    flat = points.reshape(-1, 11)
    model.set_normalizer({"min": flat.min(0).values, "max": flat.max(0).values})
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    for _ in range(60):
        loss = segmentation_loss(model(points), roles)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    unseen, unseen_roles, _ = blocks(99)
    prob, predicted = model.predict(unseen)
    assert prob.shape == predicted.shape == (1, unseen.shape[1]) and predicted.dtype == torch.uint8
    critical = unseen_roles > 0
    assert (predicted[critical] == unseen_roles[critical]).float().mean() > 0.9
    assert ((prob > 0.5) == critical).float().mean() > 0.9


def test_the_policy_takes_role_tokens_from_the_observation_and_needs_them() -> None:
    config = head(TINY, tokens=4, source="roles")
    torch.manual_seed(0)
    policy = AnchorDiffusionPolicy(config)
    batch = samples(4)
    policy.set_normalizers(stats_of(batch))
    with pytest.raises(KeyError, match="roles"):
        policy.encode_observation(batch)
    n = batch["points"].shape[1]
    batch["roles"] = (torch.arange(n) % 5).to(torch.uint8).expand(4, n)
    policy.compute_loss(batch, generator=torch.Generator().manual_seed(0)).backward()
    assert policy.object_encoder.net[0].weight.grad.abs().sum() > 0
    shuffled = dict(batch, roles=torch.roll(batch["roles"], 1, dims=1))
    assert not torch.equal(policy.encode_observation(batch), policy.encode_observation(shuffled))


def test_role_tokens_are_not_clustered_so_take_no_height_weight() -> None:
    assert ObjectHeadConfig(tokens=4, source="roles").source == "roles"
    with pytest.raises(ValidationError, match="z_weight"):
        ObjectHeadConfig(tokens=4, source="roles", z_weight=5.0)
    with pytest.raises(ValidationError, match="roles"):
        SegmenterConfig(roles=17)
    assert PolicyConfig.model_validate({"preset": "recipe", "objects": {"source": "roles", "z_weight": 1.0, "tokens": 4}}).objects.held_offsets


def test_a_policy_of_role_tokens_over_a_segmenter_without_enough_roles_is_refused_with_its_config() -> None:
    """Before any model trains: the training config itself names the segmenter field to set."""
    from anchordp3.schemas.training import TrainingConfig

    policy = {"model": {"preset": "recipe", "objects": {"source": "roles", "z_weight": 1.0, "tokens": 4}}}
    with pytest.raises(ValidationError, match=r"segmenter.model.roles: 2, but the policy's tokens are the segmenter's roles 1..4"):
        TrainingConfig.model_validate({"segmenter": {"model": {"roles": 2}}, "policy": policy})
    assert TrainingConfig.model_validate({"segmenter": {"model": {"roles": 4}}, "policy": policy})
    assert TrainingConfig.model_validate({"policy": {**policy, "label_channel": "ground_truth"}})  # the labels' roles


def bottles(seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Three alike bottles (7 cm wide, 60 points each) at random, well apart places and a dustbin
    (role 4) at (-0.2, 0.12): xyz (1, N, 3) metres, roles (1, N) as a segmenter gives them (each
    bottle point one of roles 1-3 at random: it cannot tell alike bottles apart) and each point's
    bottle (0-2, -1 not a bottle)."""
    g = torch.Generator().manual_seed(seed)
    parts, roles, which = [], [], []
    while True:
        centres = torch.rand(3, 2, generator=g) * torch.tensor([0.5, 0.3]) - torch.tensor([0.15, 0.15])
        if torch.pdist(centres).min() > 0.12:
            break
    for i, c in enumerate(centres):
        parts.append(torch.rand(60, 3, generator=g) * torch.tensor([0.07, 0.07, 0.15]) + torch.tensor([*(c - 0.035), 0.74]))
        roles.append(torch.randint(1, 4, (60,), generator=g))
        which.append(torch.full((60,), i))
    parts.append(torch.rand(80, 3, generator=g) * 0.1 + torch.tensor([-0.25, 0.07, 0.74]))
    roles.append(torch.full((80,), 4))
    which.append(torch.full((80,), -1))
    parts.append(torch.rand(100, 3, generator=g) * torch.tensor([0.8, 0.6, 0.0]) - torch.tensor([0.4, 0.3, -0.74]))
    roles.append(torch.zeros(100, dtype=torch.long))
    which.append(torch.full((100,), -1))
    return torch.cat(parts)[None], torch.cat(roles)[None], torch.cat(which)


@pytest.mark.parametrize("seed", range(5))
def test_alike_objects_take_their_roles_by_distance_from_the_object_that_orders_them(seed) -> None:
    xyz, roles, which = bottles(seed)
    split = split_alike(xyz, roles, (1, 2, 3), by=4)
    bin_xy = xyz[0, roles[0] == 4, :2].mean(0)
    order = torch.argsort(torch.stack([(xyz[0, which == i, :2].mean(0) - bin_xy).norm() for i in range(3)]))
    for role, bottle in enumerate(order.tolist(), start=1):  # the bottle nearest the bin is role 1, ...
        assert (split[0, which == bottle] == role).all()
    assert torch.equal(split[0, which < 0], roles[0, which < 0])  # the bin and the table keep theirs
    perm = torch.randperm(xyz.shape[1], generator=torch.Generator().manual_seed(seed))
    assert torch.equal(split_alike(xyz[:, perm], roles[:, perm], (1, 2, 3), by=4), split[:, perm])


def test_a_policy_splits_alike_objects_only_in_their_task() -> None:
    config = head(TINY, tokens=4, source="roles", alike={"put_bottles_dustbin": {"roles": [1, 2, 3], "by": 4}})
    torch.manual_seed(0)
    policy = AnchorDiffusionPolicy(config)
    xyz, roles, which = bottles(0)
    points = torch.cat([xyz, torch.zeros(1, xyz.shape[1], 8)], dim=-1).expand(2, -1, -1)
    obs = {"points": points, "roles": roles.expand(2, -1), "task_id": torch.tensor([task_id("put_bottles_dustbin"), task_id("place_mouse")])}
    got = policy._roles(obs, points)
    assert torch.equal(got[0], split_alike(xyz, roles, (1, 2, 3), by=4)[0])  # the bottles: by position
    assert torch.equal(got[1], roles[0])  # another task's roles as the segmenter gave them
    for bad, field in [({"place_nothing": {"roles": [1, 2], "by": 3}}, "unknown task"),
                       ({"put_bottles_dustbin": {"roles": [1, 2, 3], "by": 5}}, "roles up to 4"),
                       ({"put_bottles_dustbin": {"roles": [1, 2], "by": 2}}, "'by' \\(2\\) not among them")]:
        with pytest.raises(ValidationError, match=field):
            ObjectHeadConfig(tokens=4, source="roles", alike=bad)
    with pytest.raises(ValidationError, match="alike: needs source 'roles'"):
        ObjectHeadConfig(tokens=4, alike={"put_bottles_dustbin": {"roles": [1, 2, 3], "by": 4}})
