"""Critical-object tokens: the segmented cloud's objects found, ordered and described the same way
wherever the scene, the point order or a stray mislabelled point."""

from __future__ import annotations

import math

import pytest
import torch
from pydantic import ValidationError

from anchordp3.models.encoders import append_critical_probability
from anchordp3.models.objects import (POSITION_SCALE, TOKEN_FEATURES, cluster_critical_points, nearest_branch, nearest_token_gates,
                                      object_tokens, pair_offsets, token_features, token_heading, token_yaw, top_down_rot6)
from anchordp3.models.policy import AnchorDiffusionPolicy
from anchordp3.schemas.state import ARMS, StateLayout
from anchordp3.schemas.training import PolicyConfig
from tests.models.test_policy_model import TINY, samples, stats_of

LAYOUT = StateLayout()


def head(base: PolicyConfig, **fields) -> PolicyConfig:
    """``base`` with its object head's ``fields`` set (the head added when it has none), validated."""
    objects = {**(base.objects.model_dump() if base.objects else {}), **fields}
    return PolicyConfig.model_validate({**base.model_dump(), "objects": objects})


def scene(seed: int = 0, stray: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A table of 400 points with a big critical blob (a scale, 150 points, at (0.2, 0.1)) and a
    small one (a mouse, 60 points, at (-0.1, -0.05)), optionally one stray critical point far away.
    Returns points (1, N, 12), state (1, 32) and the two true centroids (2, 3), big first."""
    g = torch.Generator().manual_seed(seed)
    table = torch.rand(400, 3, generator=g) * torch.tensor([0.8, 0.6, 0.0]) - torch.tensor([0.4, 0.3, -0.74])
    big = torch.randn(150, 3, generator=g) * 0.03 + torch.tensor([0.2, 0.1, 0.76])
    small = torch.randn(60, 3, generator=g) * 0.015 + torch.tensor([-0.1, -0.05, 0.76])
    xyz = [table, big, small]
    label = [torch.zeros(400), torch.ones(150), torch.ones(60)]
    if stray:
        xyz.append(torch.tensor([[0.38, -0.28, 0.74]]))
        label.append(torch.ones(1))
    xyz, label = torch.cat(xyz), torch.cat(label)
    feats = torch.cat([xyz, torch.rand(len(xyz), 8, generator=g)], dim=1)
    points = append_critical_probability(feats[None], label[None])
    state = torch.rand(1, 32, generator=g)
    truth = torch.stack([big.mean(0), small.mean(0)])
    return points, state, truth


def test_two_objects_are_found_largest_first() -> None:
    points, state, truth = scene()
    critical = points[..., -1] > 0.5
    assign, centres = cluster_critical_points(points[..., :3], critical, 2)
    torch.testing.assert_close(centres[0], truth, atol=2e-3, rtol=0)
    counts = torch.bincount(assign[0][critical[0]], minlength=2)
    assert counts.tolist() == [150, 60]


def test_a_stray_critical_point_does_not_seed_an_object() -> None:
    points, state, truth = scene(stray=True)
    _, centres = cluster_critical_points(points[..., :3], points[..., -1] > 0.5, 2)
    assert (centres[0] - truth).norm(dim=-1).max() < 0.01


def held_over_scale() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A scale's top (a 14 x 12 cm slab's upper face, the part under the object hidden) with a
    10 x 6 x 3 cm object held 1.5 cm above it, as the cameras see a place from above.
    Returns xyz (1, N, 3), critical (1, N) and the two true centroids (2, 3), scale first."""
    xs, ys = torch.meshgrid(torch.linspace(-0.07, 0.07, 29), torch.linspace(-0.06, 0.06, 25), indexing="ij")
    top = torch.stack([xs.flatten(), ys.flatten(), torch.full((xs.numel(),), 0.76)], dim=1)
    scale = top[(top[:, 0].abs() > 0.05) | (top[:, 1].abs() > 0.03)]  # the ring the object does not hide
    ox, oy = torch.meshgrid(torch.linspace(-0.05, 0.05, 21), torch.linspace(-0.03, 0.03, 13), indexing="ij")
    face = torch.stack([ox.flatten(), oy.flatten(), torch.full((ox.numel(),), 0.805)], dim=1)
    rim = face[(face[:, 0].abs() > 0.049) | (face[:, 1].abs() > 0.029)]
    obj = torch.cat([face, *(rim - torch.tensor([0.0, 0.0, dz]) for dz in (0.01, 0.02))])  # top and sides
    xyz = torch.cat([scale, obj])[None]
    return xyz, torch.ones(xyz.shape[:2], dtype=torch.bool), torch.stack([scale.mean(0), obj.mean(0)])


def test_counting_heights_over_keeps_an_object_held_over_the_scale_apart_from_it() -> None:
    xyz, critical, truth = held_over_scale()
    _, plain = cluster_critical_points(xyz, critical, 2)
    _, stretched = cluster_critical_points(xyz, critical, 2, z_weight=5.0)
    assert (plain[0] - truth).norm(dim=-1).max() > 0.02  # plain k-means cuts the pile in two across
    torch.testing.assert_close(stretched[0], truth, atol=1e-3, rtol=0)  # in metres, largest (the scale) first


def test_counting_heights_over_leaves_objects_side_by_side_as_they_were() -> None:
    points, _, truth = scene()
    critical = points[..., -1] > 0.5
    plain, stretched = (cluster_critical_points(points[..., :3], critical, 2, z_weight=w) for w in (1.0, 5.0))
    assert torch.equal(plain[0][critical], stretched[0][critical])  # the same objects
    torch.testing.assert_close(stretched[1][0], truth, atol=2e-3, rtol=0)


def test_the_policy_clusters_its_tokens_with_its_configured_height_weight() -> None:
    policy = AnchorDiffusionPolicy(head(TINY, tokens=2, z_weight=5.0))
    xyz, critical, _ = held_over_scale()
    feats = torch.cat([xyz, torch.rand(*xyz.shape[:2], 8, generator=torch.Generator().manual_seed(0))], dim=-1)
    batch = {**samples(1), "points": append_critical_probability(feats, critical.float())}
    policy.set_normalizers(stats_of(batch))
    points, state = batch["points"], batch["state"]
    expected = object_tokens(points, state, LAYOUT, 2, z_weight=5.0)
    assert not torch.equal(expected, object_tokens(points, state, LAYOUT, 2))
    torch.testing.assert_close(policy._condition(batch)[1], expected)
    with pytest.raises(ValidationError, match="token_z_weight"):
        TINY.model_validate({**TINY.model_dump(), "token_z_weight": 5.0})


def test_tokens_follow_the_scene_and_not_the_point_order() -> None:
    points, state, truth = scene()
    tokens = object_tokens(points, state, LAYOUT, 2)
    assert tokens.shape == (1, 2, TOKEN_FEATURES)
    torch.testing.assert_close(tokens[0, :, :3], truth * POSITION_SCALE, atol=2e-3, rtol=0)
    for k, arm in enumerate(ARMS):
        want = (truth - state[0, LAYOUT.ee_xyz(arm)]) * POSITION_SCALE
        torch.testing.assert_close(tokens[0, :, 3 + 3 * k:6 + 3 * k], want, atol=2e-3, rtol=0)
    torch.testing.assert_close(tokens[0, :, -1], torch.tensor([150 / 210, 60 / 210]))
    shuffled = points[:, torch.randperm(points.shape[1], generator=torch.Generator().manual_seed(3))]
    torch.testing.assert_close(object_tokens(shuffled, state, LAYOUT, 2), tokens, atol=1e-5, rtol=0)
    # the whole scene and robot moved together: positions shift, offsets from the grippers stay
    delta = torch.tensor([0.05, -0.03, 0.01])
    moved_points, moved_state = points.clone(), state.clone()
    moved_points[..., :3] += delta
    for arm in ARMS:
        moved_state[:, LAYOUT.ee_xyz(arm)] += delta
    moved = object_tokens(moved_points, moved_state, LAYOUT, 2)
    torch.testing.assert_close(moved[..., :3], tokens[..., :3] + delta * POSITION_SCALE, atol=1e-4, rtol=0)
    torch.testing.assert_close(moved[..., 3:], tokens[..., 3:], atol=1e-4, rtol=0)


def test_a_cloud_without_critical_points_gives_empty_tokens() -> None:
    points, state, _ = scene()
    points[..., -1] = 0.0
    assert object_tokens(points, state, LAYOUT, 3).abs().max() == 0


def test_the_policy_conditions_on_object_tokens_and_learns() -> None:
    config = head(TINY, tokens=2)
    assert config.cond_dim == TINY.cond_dim + config.objects.encoder_dim
    torch.manual_seed(0)
    policy = AnchorDiffusionPolicy(config)
    batch = samples(4)
    policy.set_normalizers(stats_of(batch))
    cond = policy.encode_observation(batch)
    assert cond.shape == (4, config.cond_dim)
    policy.compute_loss(batch, generator=torch.Generator().manual_seed(0)).backward()
    assert policy.object_encoder.net[0].weight.grad.abs().sum() > 0
    assert policy.predict(batch, generator=torch.Generator().manual_seed(1)).shape == (4, 8, 32)


def turned_scene(yaw: float, shift=(0.0, 0.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """One critical object, a 10 x 5 cm rectangle (a 20 x 10 grid of points) turned ``yaw`` radians
    about z and moved by ``shift`` (metres), on 300 table points: points (1, N, 12) and state (1, 32)."""
    g = torch.Generator().manual_seed(0)
    u, v = torch.meshgrid((torch.arange(20) + 0.5) / 20 - 0.5, (torch.arange(10) + 0.5) / 10 - 0.5, indexing="ij")
    local = torch.stack([u.reshape(-1) * 0.10, v.reshape(-1) * 0.05], dim=1)
    c, s = torch.cos(torch.tensor(yaw)), torch.sin(torch.tensor(yaw))
    xy = local @ torch.stack([torch.stack([c, s]), torch.stack([-s, c])]) + torch.tensor([-0.15, 0.05]) + torch.tensor(shift)
    obj = torch.cat([xy, torch.full((200, 1), 0.77)], dim=1)
    table = torch.rand(300, 3, generator=g) * torch.tensor([0.8, 0.6, 0.0]) - torch.tensor([0.4, 0.3, -0.74])
    xyz = torch.cat([table, obj])
    feats = torch.cat([xyz, torch.rand(len(xyz), 8, generator=g)], dim=1)
    label = torch.cat([torch.zeros(300), torch.ones(200)])
    return append_critical_probability(feats[None], label[None]), torch.rand(1, 32, generator=g)


def test_orientation_tells_an_object_from_its_mirror_image_where_the_spread_cannot() -> None:
    import math

    plus, state = turned_scene(math.radians(30))
    minus, _ = turned_scene(math.radians(-30))
    tp, tm = (object_tokens(p, state, LAYOUT, 1, orientation=True)[0, 0] for p in (plus, minus))
    assert tp.shape == (token_features(True),) and token_features(True) == TOKEN_FEATURES + 2
    torch.testing.assert_close(tp[:TOKEN_FEATURES][9:11], tm[:TOKEN_FEATURES][9:11], atol=2e-3, rtol=0)  # x, y spread alike
    # a 10 x 5 cm rectangle: second moments 1/12 of 0.01 and 0.0025 -> anisotropy 0.6 along its long axis
    want = 0.6 * torch.tensor([math.cos(math.radians(60)), math.sin(math.radians(60))])
    assert (tp[-2:] - want).abs().max() < 0.05
    assert (tm[-2:] - want * torch.tensor([1.0, -1.0])).abs().max() < 0.05
    # turned half a turn: the same axis; moved: the same orientation
    half, _ = turned_scene(math.radians(30) + math.pi, shift=(0.1, -0.04))
    torch.testing.assert_close(object_tokens(half, state, LAYOUT, 1, orientation=True)[0, 0, -2:], tp[-2:], atol=1e-4, rtol=0)
    # without the option the token is as before
    torch.testing.assert_close(object_tokens(plus, state, LAYOUT, 1)[0, 0], tp[:TOKEN_FEATURES])


def test_the_half_angle_turns_with_the_object_where_a_top_down_grasp_turns_its_fingers() -> None:
    """Over the whole range of an elongated object's axis, (cos θ, sin θ) is linear in the finger
    direction of a grasp across it (θ - 90°), which (cos 2θ, sin 2θ) is not: a linear fit on the
    half angle finds every grasp, one on the double angle misses by tens of degrees."""
    import math

    yaws = [math.radians(d) for d in range(-85, 90, 10)]
    tokens = torch.stack([object_tokens(turned_scene(y)[0], turned_scene(y)[1], LAYOUT, 1, orientation=True,
                                        half_angle=True)[0, 0] for y in yaws])
    assert tokens.shape[-1] == token_features(True, True) == TOKEN_FEATURES + 4
    double, half = tokens[:, -4:-2], tokens[:, -2:]
    torch.testing.assert_close(half / half.norm(dim=-1, keepdim=True),
                               torch.tensor([[math.cos(y), math.sin(y)] for y in yaws]), atol=1e-3, rtol=0)
    fingers = torch.tensor([[math.cos(y - math.pi / 2), math.sin(y - math.pi / 2)] for y in yaws])

    def worst_fit_degrees(x: torch.Tensor) -> float:
        design = torch.cat([x, torch.ones(len(x), 1)], dim=1).double()
        fit = design @ torch.linalg.lstsq(design, fingers.double()).solution
        return math.degrees(float(torch.atan2(fit[:, 1], fit[:, 0]).sub(torch.atan2(fingers[:, 1], fingers[:, 0]).double())
                                  .remainder(2 * math.pi).sub(math.pi).abs().sub(math.pi).abs().max()))

    assert worst_fit_degrees(half) < 3.0 and worst_fit_degrees(double) > 30.0
    # without it, the tokens are as before
    torch.testing.assert_close(object_tokens(*turned_scene(yaws[3]), LAYOUT, 1, orientation=True)[0, 0], tokens[3, :-2])
    with pytest.raises(ValidationError, match="half_angle: needs orientation"):
        head(TINY, tokens=2, half_angle=True)
    policy = AnchorDiffusionPolicy(head(TINY, tokens=2, orientation=True, half_angle=True))
    assert policy.object_encoder.net[0].in_features == 2 * token_features(True, True)


def test_the_policy_reads_object_orientation_only_with_tokens() -> None:
    config = head(TINY, tokens=2, orientation=True)
    policy = AnchorDiffusionPolicy(config)
    assert policy.object_encoder.net[0].in_features == 2 * token_features(True)
    batch = samples(4)
    policy.set_normalizers(stats_of(batch))
    assert policy.encode_observation(batch).shape == (4, config.cond_dim)
    with pytest.raises(ValidationError, match="object_orientation"):
        TINY.model_validate({**TINY.model_dump(), "object_orientation": True})


ANCHORED = head(TINY, tokens=2, anchored_offsets=True, gate_supervision=1.0, gate_radius=0.15)


def test_anchored_offsets_add_the_chosen_object_offsets_to_end_effector_positions_only() -> None:
    torch.manual_seed(0)
    policy = AnchorDiffusionPolicy(ANCHORED)
    points, state, truth = scene()
    batch = {**samples(1), "points": points, "state": state}
    policy.set_normalizers(stats_of(batch))
    cond, tokens = policy.encode_observation(batch), object_tokens(points, state, LAYOUT, 2)
    choice = policy.anchor_gates[-1].bias.view(8, len(ARMS), 3)  # per (slot, arm): none, object 0, object 1
    with torch.no_grad():
        choice.zero_()
        policy.anchor_gates[-1].weight.zero_()
        choice[..., 0] = 10.0  # no object anywhere: the plain policy
        assert policy.anchored_shift(policy.gates(cond), tokens).abs().max() == 0
        choice[0, 0, 2] = 20.0  # slot 0, left arm, the small object
    shift = policy.anchored_shift(policy.gates(cond), tokens) / policy.delta_normalizer.scale.view(8, 32)  # data units
    left = LAYOUT.ee_xyz("left")
    assert (shift[0, 0, left] - (truth[1] - state[0, left])).abs().max() < 0.01
    elsewhere = torch.ones(8, 32, dtype=torch.bool)
    elsewhere[0, left] = False
    assert shift[0][elsewhere].abs().max() == 0


def test_anchored_offsets_need_object_tokens_and_relative_sample_targets() -> None:
    with pytest.raises(ValidationError, match="anchored_offsets"):
        ANCHORED.model_validate({**ANCHORED.model_dump(), "target": "absolute"})
    with pytest.raises(ValidationError, match="anchored_offsets, gate_supervision: needs object_tokens"):  # the form configs had before the section
        TINY.model_validate({**TINY.model_dump(), "object_tokens": 0, "anchored_offsets": True, "gate_supervision": 1.0})


def moved_scenes(seeds: range) -> dict[str, torch.Tensor]:
    """Scenes whose small object lies anywhere in a 30 x 30 cm square, the left gripper at home
    (within 1 cm), labelled 'the left gripper to 10 cm above the object' in every slot: (points, state, anchors, task_id) as a dataset batch."""
    pts, states, anchors = [], [], []
    left = LAYOUT.ee_xyz("left")
    for s in seeds:
        points, state, truth = scene(s)
        d = (torch.rand(2, generator=torch.Generator().manual_seed(1000 + s)) - 0.5) * 0.3
        points[0, 550:610, :2] += d  # the small blob (rows 550-609)
        state[0, left] = torch.tensor([-0.3, -0.2, 1.0]) + 0.01 * torch.randn(3, generator=torch.Generator().manual_seed(s))  # at home
        target = state[0].clone()
        target[left] = truth[1] + torch.tensor([d[0], d[1], 0.10])
        pts.append(points[0]), states.append(state[0]), anchors.append(target.expand(8, 32))
    return {"points": torch.stack(pts), "state": torch.stack(states), "anchors": torch.stack(anchors),
            "task_id": torch.zeros(len(seeds), dtype=torch.long)}


def fitted(config, train: dict[str, torch.Tensor], steps: int) -> AnchorDiffusionPolicy:
    """A policy of ``config`` trained ``steps`` full-batch AdamW steps on ``train`` (seeded)."""
    torch.manual_seed(0)
    policy = AnchorDiffusionPolicy(config)
    policy.set_normalizers(stats_of(train))
    opt = torch.optim.AdamW(policy.parameters(), lr=2e-3)
    g = torch.Generator().manual_seed(0)
    for _ in range(steps):
        loss = policy.compute_loss(train, generator=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return policy


def test_anchored_offsets_find_the_pre_grasp_in_scenes_not_trained_on() -> None:
    train, test = moved_scenes(range(16)), moved_scenes(range(100, 108))
    errors = {}
    for name, config in (("tokens", head(TINY, tokens=2)), ("anchored", ANCHORED)):
        policy = fitted(config, train, 300)
        pred = policy.predict(test, generator=torch.Generator().manual_seed(1))
        left = LAYOUT.ee_xyz("left")
        errors[name] = float((pred[:, 0, left] - test["anchors"][:, 0, left]).norm(dim=-1).mean())
    assert errors["anchored"] < 0.03, errors  # metres: within 3 cm of the pre-grasp on unseen scenes
    assert errors["anchored"] < 0.5 * errors["tokens"], errors


def test_gate_targets_name_the_nearest_present_object_within_the_radius() -> None:
    points, state, truth = scene()
    tokens = object_tokens(points, state, LAYOUT, 2)  # big first, then small
    positions = torch.stack([truth[1] + torch.tensor([0.0, 0.0, 0.05]),  # 5 cm above the small one
                             truth[0] + torch.tensor([0.03, 0.0, 0.0]),   # beside the big one
                             torch.tensor([0.3, -0.3, 1.1])])             # far from both
    got = nearest_token_gates(positions.view(1, 3, 1, 3), tokens, radius=0.1)
    assert got[0, :, 0].tolist() == [[0.0, 1.0], [1.0, 0.0], [0.0, 0.0]]
    absent = tokens.clone()
    absent[:, 1] = 0  # the small object not found: the position beside it belongs to no object
    assert nearest_token_gates(positions[:1].view(1, 1, 1, 3), absent, radius=0.1).sum() == 0


def test_the_gates_choose_one_object_or_none_and_learn_which() -> None:
    train, test = moved_scenes(range(16)), moved_scenes(range(100, 108))
    fresh = AnchorDiffusionPolicy(ANCHORED)
    fresh.set_normalizers(stats_of(train))
    policy = fitted(ANCHORED, train, 150)
    with torch.no_grad():
        for model in (fresh, policy):
            gates = model.gates(model._condition(test)[0])
            assert set(gates.unique().tolist()) <= {0.0, 1.0} and gates.sum(-1).max() <= 1  # one-hot or none
        cond, tokens = policy._condition(test)
        gates = policy.gates(cond)
    assert (gates[:, :, 0] == torch.tensor([0.0, 1.0])).all()  # the left arm: by the small object, every slot
    assert (gates[:, :, 1] == 0).all()  # the right arm, resting: by none
    assert policy.first_gate_hits(test).all()  # what training logs as first_gate
    assert AnchorDiffusionPolicy(TINY).first_gate_hits(test) is None  # no anchored offsets: nothing to log


def test_anchored_offsets_train_on_the_labelled_objects() -> None:
    """In training the shift follows the labels (teacher forcing), not the untrained classifier's
    choice: the loss with the labels' shift equals ``compute_loss``'s diffusion part."""
    train = moved_scenes(range(4))
    torch.manual_seed(0)
    policy = AnchorDiffusionPolicy(head(ANCHORED, gate_supervision=1e-12))
    policy.set_normalizers(stats_of(train))
    with torch.no_grad():
        policy.anchor_gates[-1].bias.view(8, len(ARMS), 3)[:, 0] = torch.tensor([10.0, 0.0, 0.0])  # predicts "none"
        loss = policy.compute_loss(train, generator=torch.Generator().manual_seed(0))
        cond, tokens = policy._condition(train)
        labels = policy.gate_targets(tokens, train["anchors"], train["state"])
        assert labels[:, :, 0, 1].all() and not policy.gates(cond)[:, :, 0].any()
        g = torch.Generator().manual_seed(0)
        x0 = policy.to_target(train["anchors"], train["state"])
        noise = torch.randn(x0.shape, generator=g)
        steps = torch.randint(0, policy.noise_scheduler.config.num_train_timesteps, (4,), generator=g)
        pred = policy.unet(policy.noise_scheduler.add_noise(x0, noise, steps), steps, cond)
        expected = torch.nn.functional.mse_loss(pred + policy.anchored_shift(labels, tokens), x0)
    assert abs(float(loss) - float(expected)) < 1e-5


def test_anchored_offsets_need_their_classifier_loss_and_soft_gating_is_retired() -> None:
    with pytest.raises(ValidationError, match="gate_supervision"):
        head(ANCHORED, gate_supervision=0.0)
    flat = {**TINY.model_dump(), "object_tokens": 2, "anchored_offsets": True, "gate_supervision": 1.0}  # as checkpoints have it
    with pytest.raises(ValidationError, match="anchor_gating: 'soft' retired"):
        PolicyConfig.model_validate({**flat, "anchor_gating": "soft"})
    assert PolicyConfig.model_validate({**flat, "anchor_gating": "hard"}) == ANCHORED
    assert TINY.model_validate({**TINY.model_dump(), "anchor_gating": "soft"}) == TINY  # meant nothing without offsets


HELD = head(ANCHORED, held_offsets=True)


def held_scenes(seeds: range) -> dict[str, torch.Tensor]:
    """Scenes where the left gripper holds the small object (closed, its end effector 2 cm above
    the object's centroid and up to 2 cm off it in the table plane: where the object sits in the
    hand), the big object anywhere in a 20 x 20 cm square, labelled 'put the held object's centroid
    5 cm above the big object's' in every slot, as the expert places."""
    pts, states, anchors = [], [], []
    left, grip = LAYOUT.ee_xyz("left"), LAYOUT.gripper("left")
    for s in seeds:
        points, state, truth = scene(s)
        g = torch.Generator().manual_seed(2000 + s)
        d = (torch.rand(2, generator=g) - 0.5) * 0.2
        points[0, 400:550, :2] += d  # the big blob (rows 400-549)
        in_hand = torch.cat([(torch.rand(2, generator=g) - 0.5) * 0.04, torch.tensor([0.02])])
        state[0, left], state[0, grip] = truth[1] + in_hand, 0.3
        state[0, LAYOUT.gripper("right")] = 1.0
        target = state[0].clone()
        target[left] = truth[0] + torch.tensor([d[0], d[1], 0.05]) + in_hand
        pts.append(points[0]), states.append(state[0]), anchors.append(target.expand(8, 32))
    return {"points": torch.stack(pts), "state": torch.stack(states), "anchors": torch.stack(anchors),
            "task_id": torch.zeros(len(seeds), dtype=torch.long)}


def test_held_offsets_label_a_place_relative_to_the_object_in_the_closed_gripper() -> None:
    batch = held_scenes(range(1))
    policy = AnchorDiffusionPolicy(HELD)
    tokens = object_tokens(batch["points"], batch["state"], LAYOUT, 2)  # big (the target) first, the held small one second
    labels = policy.gate_targets(tokens, batch["anchors"], batch["state"])
    assert labels.shape == (1, 8, len(ARMS), 4)
    assert labels[0, :, 0].tolist() == [[0.0, 1.0, 0.0, 0.0]] * 8  # (big, held small): entry 0 * 2 + 1
    assert labels[0, :, 1].sum() == 0  # the right arm: by no object
    opened = {**batch, "state": batch["state"].clone()}
    opened["state"][0, LAYOUT.gripper("left")] = 1.0  # an open gripper holds nothing: the big object alone
    assert policy.gate_targets(tokens, opened["anchors"], opened["state"])[0, :, 0].tolist() == [[1.0, 0.0, 0.0, 0.0]] * 8
    table = pair_offsets(tokens)[0]  # (4, arms, 3) metres
    centroids = tokens[0, :, :3] / POSITION_SCALE
    torch.testing.assert_close(table[1, 0], centroids[0] - centroids[1])
    torch.testing.assert_close(table[0, 0], centroids[0] - batch["state"][0, LAYOUT.ee_xyz("left")], atol=1e-6, rtol=0)
    torch.testing.assert_close(table[3, 1], centroids[1] - batch["state"][0, LAYOUT.ee_xyz("right")], atol=1e-6, rtol=0)


DESTINATION = head(HELD, held_destination=True)


def carried_over_target() -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """The small object carried 10 cm above the big one (the left gripper closed 3 cm above the
    small object's centroid), labelled 'descend 4 cm': the anchor lies 1 cm from the carried
    object's centroid now and 9 cm from the target's. Returns the batch and its tokens."""
    points, state, truth = scene(0)
    lift = truth[0] + torch.tensor([0.01, 0.0, 0.10]) - truth[1]
    points[0, 550:610, :3] += lift  # the small blob (rows 550-609) over the big one
    left = LAYOUT.ee_xyz("left")
    state[0, left] = truth[1] + lift + torch.tensor([0.0, 0.0, 0.03])
    state[0, LAYOUT.gripper("left")], state[0, LAYOUT.gripper("right")] = 0.3, 1.0
    target = state[0].clone()
    target[left] -= torch.tensor([0.0, 0.0, 0.04])
    batch = {"points": points, "state": state, "anchors": target.expand(1, 8, 32).clone(), "task_id": torch.zeros(1, dtype=torch.long)}
    return batch, object_tokens(points, state, LAYOUT, 2, z_weight=5.0)


def test_held_destination_labels_a_place_by_its_target_not_by_the_carried_object() -> None:
    batch, tokens = carried_over_target()
    torch.testing.assert_close(tokens[0, 1, :3] / POSITION_SCALE, batch["points"][0, 550:610, :3].mean(0), atol=0.01, rtol=0)
    old = AnchorDiffusionPolicy(HELD).gate_targets(tokens, batch["anchors"], batch["state"])
    assert old[0, :, 0].tolist() == [[0.0, 0.0, 0.0, 1.0]] * 8  # nearest the anchor: the carried object itself
    new = AnchorDiffusionPolicy(DESTINATION).gate_targets(tokens, batch["anchors"], batch["state"])
    assert new[0, :, 0].tolist() == [[0.0, 1.0, 0.0, 0.0]] * 8  # (big, held small): the target minus the carried


def test_held_destination_labels_a_move_away_from_every_other_object_by_none() -> None:
    """Lifting the held object where no other object lies within gate_radius of where it goes:
    relative to the state (no gate), never to the carried object's own centroid."""
    batch, tokens = held_scenes(range(1)), None
    left = LAYOUT.ee_xyz("left")
    batch["anchors"] = batch["state"][:, None].expand(1, 8, 32).clone()
    batch["anchors"][0, :, left] += torch.tensor([-0.05, -0.05, 0.05])  # away from the big object
    tokens = object_tokens(batch["points"], batch["state"], LAYOUT, 2)
    assert AnchorDiffusionPolicy(DESTINATION).gate_targets(tokens, batch["anchors"], batch["state"])[0, :, 0].sum() == 0
    assert AnchorDiffusionPolicy(HELD).gate_targets(tokens, batch["anchors"], batch["state"])[0, :, 0, 3].all()


def test_held_destination_needs_held_offsets() -> None:
    with pytest.raises(ValidationError, match="held_destination"):
        head(ANCHORED, held_destination=True)


def first_left_errors(configs: dict, train: dict[str, torch.Tensor], test: dict[str, torch.Tensor],
                      axes: int = 3) -> dict[str, float]:
    """Each named config fitted on ``train`` (300 steps): the mean distance (metres) between its
    first predicted anchor's left end effector and the label on ``test``, over its first ``axes``
    coordinates (3: xyz, 2: the table plane)."""
    left = LAYOUT.ee_xyz("left")
    errors = {}
    for name, config in configs.items():
        pred = fitted(config, train, 300).predict(test, generator=torch.Generator().manual_seed(1))
        errors[name] = float((pred[:, 0, left][:, :axes] - test["anchors"][:, 0, left][:, :axes]).norm(dim=-1).mean())
    return errors


def test_held_offsets_place_where_the_object_sits_in_the_hand() -> None:
    """The place that follows from the in-hand offset: on unseen scenes, anchoring it to the held
    object beats anchoring it to the target alone."""
    errors = first_left_errors({"target": ANCHORED, "held": HELD}, held_scenes(range(16)), held_scenes(range(100, 108)))
    assert errors["held"] < 0.01, errors  # metres
    assert errors["held"] < 0.5 * errors["target"], errors


STAY = head(HELD, stay_radius=0.01)


def in_place_scenes(seeds: range) -> dict[str, torch.Tensor]:
    """Scenes where the left gripper stands open at the small object, up to 2 cm off its centroid
    in the table plane and 2 cm above it (where the expert brought it), the big object anywhere in a
    20 x 20 cm square, labelled 'close where you stand' in the first slot and 'lift 5 cm' after."""
    pts, states, anchors = [], [], []
    left, grip = LAYOUT.ee_xyz("left"), LAYOUT.gripper("left")
    for s in seeds:
        points, state, truth = scene(s)
        g = torch.Generator().manual_seed(3000 + s)
        points[0, 400:550, :2] += (torch.rand(2, generator=g) - 0.5) * 0.2  # the big blob moves
        state[0, left] = truth[1] + torch.cat([(torch.rand(2, generator=g) - 0.5) * 0.04, torch.tensor([0.02])])
        state[0, grip], state[0, LAYOUT.gripper("right")] = 1.0, 1.0
        close = state[0].clone()
        close[grip] = 0.0
        lift = close.clone()
        lift[left] = lift[left] + torch.tensor([0.0, 0.0, 0.05])
        pts.append(points[0]), states.append(state[0]), anchors.append(torch.stack([close] + [lift] * 7))
    return {"points": torch.stack(pts), "state": torch.stack(states), "anchors": torch.stack(anchors),
            "task_id": torch.zeros(len(seeds), dtype=torch.long)}


def test_an_anchor_in_place_is_labelled_relative_to_the_state_not_to_an_object() -> None:
    batch = in_place_scenes(range(1))
    tokens = object_tokens(batch["points"], batch["state"], LAYOUT, 2)  # big first, the small one second
    by_object = AnchorDiffusionPolicy(HELD).gate_targets(tokens, batch["anchors"], batch["state"])
    in_place = AnchorDiffusionPolicy(STAY).gate_targets(tokens, batch["anchors"], batch["state"])
    small = [0.0, 0.0, 0.0, 1.0]  # (small, small): entry 1 * 2 + 1, relative to the gripper
    assert by_object[0, 0, 0].tolist() == small and in_place[0, 0, 0].sum() == 0  # the close: by no object
    assert in_place[0, 1:, 0].tolist() == [small] * 7  # the lift moves 5 cm: still by the small object
    with pytest.raises(ValidationError, match="stay_radius"):
        TINY.model_validate({**TINY.model_dump(), "stay_radius": 0.01})


def test_a_close_in_place_stays_in_place_when_labelled_relative_to_the_state() -> None:
    """Predicted relative to the object, a close in place inherits the error of reading the
    gripper's offset from the object off the tokens; relative to the state it is 'do not move'."""
    errors = first_left_errors({"object": HELD, "state": STAY}, in_place_scenes(range(16)), in_place_scenes(range(100, 108)))
    assert errors["state"] < 0.005, errors  # metres
    assert errors["state"] < 0.5 * errors["object"], errors


CHOICE = head(ANCHORED, choice_offsets=True)


def test_choice_offsets_fit_each_tasks_constant_beside_the_picked_object_and_add_it() -> None:
    """Two tasks put the left gripper 5 cm to either side of the same object: one residual per
    (task, choice, arm) instead of their mean, fitted from the labelled anchors."""
    batch = moved_scenes(range(12))
    left = LAYOUT.ee_xyz("left")
    side = torch.tensor([0.05 if s % 2 else -0.05 for s in range(12)])
    batch["task_id"] = torch.tensor([s % 2 for s in range(12)])
    batch["anchors"][:, :, left.start] += side[:, None]
    policy = AnchorDiffusionPolicy(CHOICE)
    policy.set_normalizers(stats_of(batch))
    assert policy.fit_choices([batch]) == []  # no yaw without anchored_yaw
    small = 1  # the small object's token (the big one is first), picked by the left arm alone
    assert policy.choice_xyz.shape == (CHOICE.num_tasks, 2, len(ARMS), 3)
    torch.testing.assert_close(policy.choice_xyz[0, small, 0], torch.tensor([-0.05, 0.0, 0.10]), atol=2e-3, rtol=0)
    torch.testing.assert_close(policy.choice_xyz[1, small, 0], torch.tensor([0.05, 0.0, 0.10]), atol=2e-3, rtol=0)
    assert policy.choice_xyz[:, :, 1].abs().max() == 0 and policy.choice_xyz[2:].abs().max() == 0  # never picked
    tokens = object_tokens(batch["points"], batch["state"], LAYOUT, 2)
    labels = policy.gate_targets(tokens, batch["anchors"], batch["state"])
    shift = policy.anchored_shift(labels, tokens, batch["state"], batch["task_id"]) / policy.delta_normalizer.scale.view(8, 32)
    exact = batch["anchors"][:, :, left] - batch["state"][:, None, left]
    assert (shift[:, :, left] - exact).abs().max() < 0.01  # the label's offset and constant: the whole move
    with pytest.raises(ValueError, match="need the state and the task ids"):
        policy.anchored_shift(labels, tokens)
    with pytest.raises(ValidationError, match="choice_offsets: needs anchored_offsets"):
        head(TINY, tokens=2, choice_offsets=True)


YAW = head(TINY, tokens=1, orientation=True, anchored_offsets=True, gate_supervision=1.0, anchored_yaw=True)


def grasp_scenes(yaws: list[float], follow: bool = True) -> dict[str, torch.Tensor]:
    """The 10 x 5 cm object of ``turned_scene`` turned by each of ``yaws`` (radians), the left
    gripper pointing down at home (finger yaw -90°), labelled 'to 10 cm above the object, fingers
    across it' (finger yaw = object yaw - 90° on the branch nearest -90°, as the expert grasps) or,
    without ``follow``, with a finger yaw that has nothing to do with the object's."""
    pts, states, anchors = [], [], []
    left, rot = LAYOUT.ee_xyz("left"), LAYOUT.ee_rot6("left")
    for i, yaw in enumerate(yaws):
        points, state = turned_scene(yaw)
        state[0, left], state[0, rot] = torch.tensor([-0.3, -0.2, 1.0]), top_down_rot6(torch.tensor(-math.pi / 2))
        target = state[0].clone()
        target[left] = points[0, 300:, :3].mean(0) + torch.tensor([0.0, 0.0, 0.10])
        finger = nearest_branch(torch.tensor(yaw - math.pi / 2), torch.tensor(-math.pi / 2)) if follow \
            else torch.tensor(-math.pi / 2 + 1.2 * math.sin(7.0 * i))
        target[rot] = top_down_rot6(finger)
        pts.append(points[0]), states.append(state[0]), anchors.append(target.expand(8, 32))
    return {"points": torch.stack(pts), "state": torch.stack(states), "anchors": torch.stack(anchors),
            "task_id": torch.zeros(len(yaws), dtype=torch.long)}


def test_anchored_yaw_turns_a_grasps_wrist_with_the_objects_axis_where_the_expert_does() -> None:
    # twice as many scenes with the object turned right: a mean of the fingers' yaws would lean that way
    train = grasp_scenes([math.radians(d) for d in [*range(-85, 90, 10), *range(-80, -20, 10)]])
    policy = AnchorDiffusionPolicy(YAW)
    policy.set_normalizers(stats_of(train))
    rows = policy.fit_choices([train])
    assert [(r["task"], r["choice"], r["arm"]) for r in rows] == [(0, 0, "left")]
    assert abs(abs(rows[0]["offset_deg"]) - 90.0) < 2.0 and rows[0]["concentration"] > 0.99
    assert abs(math.degrees(float(policy.choice_yaw[0, 0, 0, 1])) + 90.0) < 2.0  # the branch the expert prefers: -90°
    unseen = grasp_scenes([math.radians(d) for d in (-88.0, -61.0, -3.0, 42.0, 77.0, 87.0)])  # not trained on, two by the branch's edge
    tokens = object_tokens(unseen["points"], unseen["state"], LAYOUT, 1, orientation=True)
    labels = policy.gate_targets(tokens, unseen["anchors"], unseen["state"])
    assert labels[:, :, 0, 0].all()
    shift = policy.anchored_shift(labels, tokens, unseen["state"], unseen["task_id"]) / policy.delta_normalizer.scale.view(8, 32)
    rot = LAYOUT.ee_rot6("left")
    exact = unseen["anchors"][:, :, rot] - unseen["state"][:, None, rot]
    assert (shift[:, :, rot] - exact).abs().max() < 0.03  # the wrist within about 2 degrees
    assert shift[:, :, LAYOUT.ee_rot6("right")].abs().max() == 0
    # where the expert's wrist does not follow the axis, no yaw is fitted and the rotation is the network's
    other = AnchorDiffusionPolicy(YAW)
    other.set_normalizers(stats_of(train))
    assert other.fit_choices([grasp_scenes([math.radians(d) for d in range(-85, 90, 10)], follow=False)]) == []
    assert (other.anchored_shift(labels, tokens, unseen["state"], unseen["task_id"])[:, :, rot] == 0).all()
    with pytest.raises(ValidationError, match="anchored_yaw: needs orientation"):
        head(ANCHORED, anchored_yaw=True)


def shoe_scene(heading: float, psi: float, seed: int) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """A shoe-like object (a 10 x 5 cm grid, its back 4 cm raised 3 cm: the heel's collar; toes along
    ``heading`` radians) held by the closed left gripper (top-down, finger yaw ``psi``, 2 cm above its
    centroid) somewhere near (-0.15, 0.05), and a flat 8 x 8 cm target at (0.15, 0.1), on 300 table
    points; labelled 'to 5 cm above the target, the shoe turned to +90°' (finger yaw ``psi + 90° -
    heading``), as the shoes' expert places. Returns the batch of one and the shoe's centroid (3,)."""
    g = torch.Generator().manual_seed(seed)
    u, v = torch.meshgrid((torch.arange(20) + 0.5) / 20 - 0.5, (torch.arange(10) + 0.5) / 10 - 0.5, indexing="ij")
    local = torch.stack([u.reshape(-1) * 0.10, v.reshape(-1) * 0.05], dim=1)
    c, s = math.cos(heading), math.sin(heading)
    centre = torch.tensor([-0.15, 0.05]) + (torch.rand(2, generator=g) - 0.5) * 0.1
    xy = local @ torch.tensor([[c, s], [-s, c]]) + centre
    shoe = torch.cat([xy, (0.77 + 0.03 * (local[:, :1] < -0.01)).float()], dim=1)
    a, b = torch.meshgrid(torch.linspace(-0.04, 0.04, 10), torch.linspace(-0.04, 0.04, 10), indexing="ij")
    target = torch.stack([a.reshape(-1) + 0.15, b.reshape(-1) + 0.1, torch.full((100,), 0.75)], dim=1)
    table = torch.rand(300, 3, generator=g) * torch.tensor([0.8, 0.6, 0.0]) - torch.tensor([0.4, 0.3, -0.74])
    xyz = torch.cat([table, shoe, target])
    label = torch.cat([torch.zeros(300), torch.ones(300)])
    points = append_critical_probability(torch.cat([xyz, torch.rand(len(xyz), 8, generator=g)], dim=1)[None], label[None])
    state = torch.rand(1, 32, generator=g)
    left, rot = LAYOUT.ee_xyz("left"), LAYOUT.ee_rot6("left")
    state[0, left] = shoe.mean(0) + torch.tensor([0.0, 0.0, 0.02])
    state[0, rot] = top_down_rot6(torch.tensor(psi))
    state[0, LAYOUT.gripper("left")], state[0, LAYOUT.gripper("right")] = 0.3, 1.0
    anchor = state[0].clone()
    anchor[left] = target.mean(0) + torch.tensor([0.0, 0.0, 0.05])
    anchor[rot] = top_down_rot6(torch.tensor(psi + math.pi / 2 - heading))
    return {"points": points, "state": state, "anchors": anchor.expand(1, 8, 32).clone(),
            "task_id": torch.zeros(1, dtype=torch.long)}, shoe.mean(0)


def shoe_batch(seeds: range) -> dict[str, torch.Tensor]:
    """``shoe_scene`` at headings over the whole circle and finger yaws over the wrist's range."""
    rows = [shoe_scene(math.radians(-175 + 37 * s % 360), math.radians(-150 + 53 * s % 300), s)[0] for s in seeds]
    return {k: torch.cat([r[k] for r in rows]) for k in rows[0]}


def test_the_heading_points_from_an_objects_tall_part_to_its_other_end_over_the_whole_circle() -> None:
    for d in range(-175, 180, 25):
        batch, _ = shoe_scene(math.radians(d), 0.0, d + 200)
        tokens = object_tokens(batch["points"], batch["state"], LAYOUT, 2, orientation=True, half_angle=True, heading=True)
        assert tokens.shape[-1] == token_features(True, True, True) == TOKEN_FEATURES + 6
        shoe = 0  # 200 points against the target's 100: the largest cluster first
        heading, anisotropy = token_heading(tokens)
        assert anisotropy[0, shoe] > 0.5
        assert abs(math.remainder(float(heading[0, shoe]) - math.radians(d), 2 * math.pi)) < math.radians(3)
        # the axis alone is the same line for the shoe turned half a turn
        axis, _ = token_yaw(tokens)
        assert abs(math.remainder(float(axis[0, shoe]) - math.radians(d), math.pi)) < math.radians(3)
    # without the option the token is as before
    plain = object_tokens(batch["points"], batch["state"], LAYOUT, 2, orientation=True, half_angle=True)
    torch.testing.assert_close(plain, tokens[..., :-2])
    with pytest.raises(ValidationError, match="heading: needs orientation"):
        head(ANCHORED, heading=True)


HEADING = head(HELD, orientation=True, heading=True, held_yaw=True)


def test_held_yaw_turns_the_held_object_to_the_heading_its_places_agree_on() -> None:
    train = shoe_batch(range(40))
    policy = AnchorDiffusionPolicy(HEADING)
    policy.set_normalizers(stats_of(train))
    rows = policy.fit_choices([train])
    assert [(r["kind"], r["task"], r["choice"], r["arm"]) for r in rows] == [("held", 0, 2, "left")]  # (target 1, held shoe 0): 1 x 2 + 0
    assert abs(rows[0]["offset_deg"] - 90.0) < 3.0 and rows[0]["concentration"] > 0.99
    unseen = shoe_batch(range(100, 106))
    tokens = policy._tokens(unseen, unseen["points"], unseen["state"])
    labels = policy.gate_targets(tokens, unseen["anchors"], unseen["state"])
    assert labels[:, :, 0, 2].all()
    shift = policy.anchored_shift(labels, tokens, unseen["state"], unseen["task_id"]) / policy.delta_normalizer.scale.view(8, 32)
    rot = LAYOUT.ee_rot6("left")
    exact = unseen["anchors"][:, :, rot] - unseen["state"][:, None, rot]
    assert (shift[:, :, rot] - exact).abs().max() < 0.06  # the wrist within about 3 degrees, over any heading
    # a gripper that holds nothing turns nothing
    opened = {**unseen, "state": unseen["state"].clone()}
    opened["state"][:, LAYOUT.gripper("left")] = 1.0
    assert (policy.anchored_shift(labels, tokens, opened["state"], unseen["task_id"])[:, :, rot] == 0).all()
    # places whose turn has nothing to do with the held object's heading fit nothing
    unrelated = shoe_batch(range(40))
    unrelated["anchors"][:, :, rot] = torch.stack([top_down_rot6(torch.tensor(1.1 * math.sin(3.0 * i))) for i in range(40)])[:, None]
    other = AnchorDiffusionPolicy(HEADING)
    other.set_normalizers(stats_of(unrelated))
    assert other.fit_choices([unrelated]) == []
    with pytest.raises(ValidationError, match="held_yaw: needs heading"):
        head(HELD, orientation=True, held_yaw=True)
