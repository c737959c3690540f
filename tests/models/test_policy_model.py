"""Anchor diffusion policy: overfitting, per-task encoder gradients, checkpoint round trip, EMA."""

from __future__ import annotations

import io

import pytest
import torch
from pydantic import ValidationError
import torch.nn.functional as F

from anchordp3.models.ema import ExponentialMovingAverage
from anchordp3.models.encoders import append_critical_probability
from anchordp3.models.optim import make_lr_schedule, make_optimizer
from anchordp3.models.kernels import reference_kernels
from anchordp3.models.unet1d import ConditionalUnet1D, SequenceConv1d, SequenceConvTranspose1d
from anchordp3.models.policy import AnchorDiffusionPolicy, medoid
from anchordp3.schemas.state import ARMS, StateLayout
from anchordp3.schemas.training import (
    OptimizerConfig,
    PointEncoderConfig,
    PolicyConfig,
    StateEncoderConfig,
    UNetConfig,
)

TINY = PolicyConfig(
    point_encoder=PointEncoderConfig(hidden_dim=32, out_dim=48),
    state_encoder=StateEncoderConfig(hidden_dim=16),
    unet=UNetConfig(down_dims=(32, 64, 128), step_embed_dim=32),
)


def samples(batch: int, n: int = 64, seed: int = 0, tasks: list[int] | None = None) -> dict[str, torch.Tensor]:
    """A batch shaped like the dataset's samples (points get the 12th channel appended)."""
    g = torch.Generator().manual_seed(seed)
    points = torch.rand(batch, n, 11, generator=g)
    prob = (torch.rand(batch, n, generator=g) > 0.7).float()
    return {
        "points": append_critical_probability(points, prob),
        "state": torch.rand(batch, 32, generator=g) * 2 - 0.5,
        "anchors": torch.rand(batch, 8, 32, generator=g) * 3 - 1,
        "task_id": torch.tensor(tasks if tasks is not None else [k % 8 for k in range(batch)]),
    }


def stats_of(batch: dict[str, torch.Tensor]) -> dict[str, dict[str, torch.Tensor]]:
    pts = batch["points"][..., :11].reshape(-1, 11)
    delta = batch["anchors"] - batch["state"][:, None, :]
    return {
        "state": {"min": batch["state"].min(0).values, "max": batch["state"].max(0).values},
        "anchors": {"min": batch["anchors"].amin(0), "max": batch["anchors"].amax(0)},  # (8, 32) per slot
        "points": {"min": pts.min(0).values, "max": pts.max(0).values},
        "delta": {"min": delta.amin(0), "max": delta.amax(0)},  # (8, 32): anchors minus state
    }


def make_policy(seed: int = 0, target: str = "relative") -> AnchorDiffusionPolicy:
    torch.manual_seed(seed)
    return AnchorDiffusionPolicy(TINY.model_copy(update={"target": target}))


def fitted_policy(batch: int = 2) -> tuple[AnchorDiffusionPolicy, dict[str, torch.Tensor]]:
    """``make_policy()`` in eval mode with normalizers fitted on ``samples(batch)``, and that
    batch's observation (points, state, task_id)."""
    policy = make_policy().eval()
    data = samples(batch)
    policy.set_normalizers(stats_of(data))
    return policy, {k: data[k] for k in ("points", "state", "task_id")}


def test_relative_targets_round_trip_and_make_a_fixed_offset_a_constant() -> None:
    policy = make_policy()
    batch = samples(6)
    offset = torch.linspace(-0.1, 0.1, 8 * 32).reshape(8, 32)
    batch["anchors"] = batch["state"][:, None, :] + offset  # every sample: the same move from where it is
    policy.set_normalizers(stats_of(batch))
    x = policy.to_target(batch["anchors"], batch["state"])
    assert torch.allclose(x, x[:1].expand_as(x), atol=1e-5)  # one target, wherever the robot is
    torch.testing.assert_close(policy.from_target(x, batch["state"]), batch["anchors"], atol=1e-5, rtol=0)


@pytest.mark.parametrize("length", [8, 2, 1])  # 2 and 1: the outer taps of kernel 5 only meet the padding
@pytest.mark.parametrize("kernel, stride, padding", [(5, 1, 2), (3, 2, 1), (1, 1, 0)])
def test_cpu_inference_convolution_matches_torchs(kernel, stride, padding, length) -> None:
    torch.manual_seed(0)
    conv = SequenceConv1d(16, 24, kernel, stride=stride, padding=padding)
    x = torch.randn(3, 16, length)
    with torch.no_grad():
        fast = conv(x)  # the unfolded matrix product
        conv.freeze()
        conv(x)
        again = conv(x)  # the sliced weight kept by freeze
    torch.testing.assert_close(fast, F.conv1d(x, conv.weight, conv.bias, stride, padding), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(again, fast, atol=1e-6, rtol=1e-6)  # the same weights (memory alignment moves MKL rounding)


def test_the_convolutions_sliced_weight_follows_a_changed_weight() -> None:
    conv = SequenceConv1d(4, 6, 5, padding=2)
    x = torch.randn(1, 4, 2)
    with torch.no_grad():
        conv(x)
        conv.weight.data.mul_(2.0)  # as an EMA update does: through .data, unseen by the version counter
        torch.testing.assert_close(conv(x), F.conv1d(x, conv.weight, conv.bias, 1, 2), atol=1e-5, rtol=1e-5)


def test_a_frozen_convolution_thaws_when_trained_or_loaded() -> None:
    conv, other = SequenceConv1d(4, 6, 5, padding=2), SequenceConv1d(4, 6, 5, padding=2)
    x = torch.randn(1, 4, 2)
    for thaw in (lambda: conv.load_state_dict(other.state_dict()), lambda: conv.train().eval()):
        conv.freeze()
        with torch.no_grad():
            conv(x)  # keeps the sliced weight
            conv.weight.mul_(2.0)  # not allowed while frozen: it would go unseen...
            thaw()  # ...but loading or training thaws it
            torch.testing.assert_close(conv(x), F.conv1d(x, conv.weight, conv.bias, 1, 2), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("length", [1, 2, 4])
@pytest.mark.parametrize("kernel, stride, padding", [(4, 2, 1), (3, 2, 1), (5, 1, 2)])
def test_cpu_inference_transposed_convolution_matches_torchs(kernel, stride, padding, length) -> None:
    torch.manual_seed(0)
    conv = SequenceConvTranspose1d(12, 10, kernel, stride=stride, padding=padding)
    x = torch.randn(2, 12, length)
    with torch.no_grad():
        fast = conv(x)  # one matrix product and a fold
    torch.testing.assert_close(fast, F.conv_transpose1d(x, conv.weight, conv.bias, stride, padding), atol=1e-5, rtol=1e-5)


def test_the_unet_step_from_its_film_table_matches_the_step_from_the_condition() -> None:
    torch.manual_seed(0)
    unet = ConditionalUnet1D(32, 40, TINY.unet).eval()
    x, cond, steps = torch.randn(2, 8, 32), torch.randn(2, 40), torch.tensor([90, 60, 30, 0])
    with torch.no_grad():
        table = unet.film_table(cond, steps)
        assert [tuple(f.shape) for f in table] == [(4, 2, 2 * b.conv1.block[0].out_channels) for b in unet.film_blocks()]
        for i, t in enumerate(steps):
            torch.testing.assert_close(unet(x, t, None, film=[f[i] for f in table]), unet(x, t, cond), atol=1e-5, rtol=1e-5)


def test_unet_inference_matches_the_reference_kernels() -> None:
    torch.manual_seed(0)
    unet = ConditionalUnet1D(32, 40, TINY.unet).eval()
    x, cond = torch.randn(2, 8, 32), torch.randn(2, 40)
    with torch.no_grad():
        fast = unet(x, torch.tensor([3, 70]), cond)
        with reference_kernels():
            reference = unet(x, torch.tensor([3, 70]), cond)
    torch.testing.assert_close(fast, reference, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(unet(x, torch.tensor([3, 70]), cond).detach(), reference)  # training: torch's own conv


def test_sampling_with_the_fast_kernels_gives_the_reference_kernels_anchors() -> None:
    policy = make_policy().eval()
    batch = samples(2)
    policy.set_normalizers(stats_of(batch))
    obs = {k: batch[k] for k in ("points", "state", "task_id")}
    fast = policy.predict(obs, generator=torch.Generator().manual_seed(0))  # FiLM table, sliced taps, folds
    with reference_kernels():
        reference = policy.predict(obs, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(fast, reference, atol=1e-4, rtol=1e-4)


def test_fewer_ddim_steps_can_be_asked_for_at_decision_time() -> None:
    policy, obs = fitted_policy(2)
    three = policy.predict(obs, generator=torch.Generator().manual_seed(0), steps=3)
    assert three.shape == (2, 8, 32)
    assert not torch.equal(three, policy.predict(obs, generator=torch.Generator().manual_seed(0)))  # the config's 10
    with pytest.raises(ValueError, match="ddim steps"):
        policy.predict(obs, steps=0)


def test_the_medoid_is_the_sample_nearest_the_others_and_ignores_a_stray_one() -> None:
    base = torch.zeros(2, 1, 1)
    rows = torch.stack([torch.cat([base + 0.0, base + 0.1, base + 0.3, base + 9.0, base + 0.2]),  # the stray pulls the mean to 1.92
                        torch.cat([base - 5.0, base + 1.0, base + 1.2, base + 1.1, base + 1.3])])  # (2 rows, 5 samples, 1, 1)
    torch.testing.assert_close(medoid(rows), torch.tensor([[[0.2]], [[1.1]]]))


def test_several_samples_per_decision_return_the_medoid_of_the_single_samples_with_the_same_noise() -> None:
    policy, obs = fitted_policy(2)
    one = {k: v[1:] for k, v in obs.items()}
    four = {k: v.repeat_interleave(4, 0) for k, v in one.items()}
    singles = policy.predict(four, generator=torch.Generator().manual_seed(3))  # one per noise draw, (4, 8, 32)
    picked = policy.predict(one, generator=torch.Generator().manual_seed(3), samples=4)
    assert picked.shape == (1, 8, 32)
    assert any(torch.allclose(picked[0], s, atol=1e-5) for s in singles)
    assert not all(torch.allclose(singles[0], s, atol=1e-5) for s in singles[1:])  # the samples do differ
    both = policy.predict(obs, generator=torch.Generator().manual_seed(3), samples=4)
    assert both.shape == (2, 8, 32)
    first = policy.predict(obs, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(first, policy.predict(obs, generator=torch.Generator().manual_seed(3), samples=1))
    with pytest.raises(ValueError, match="samples"):
        policy.predict(obs, samples=0)


def test_retired_levers_read_as_before_when_off_and_are_refused_when_on() -> None:
    """Configs and checkpoints made while the ladder's unkept levers existed: a lever at its "off"
    value reads as today's config, any other value is one error naming the rung."""
    from anchordp3.schemas.training import PolicyTrainingConfig

    old = {**TINY.model_dump(), "gripper_points": False, "residual_scale": 1.0, "anchor_gating": "soft",
           "point_encoder": {**TINY.point_encoder.model_dump(), "keypoints": 0},
           "scheduler": {**TINY.scheduler.model_dump(), "init_noise_scale": 1.0}}
    assert PolicyConfig.model_validate(old) == TINY
    for bad, name in (({"gripper_points": True}, "gripper_points"), ({"residual_scale": 0.25}, "residual_scale"),
                      ({"point_encoder": {**old["point_encoder"], "keypoints": 16}}, "keypoints"),
                      ({"scheduler": {**old["scheduler"], "init_noise_scale": 0.0}}, "init_noise_scale")):
        with pytest.raises(ValidationError, match=f"{name}: retired .*rung"):
            PolicyConfig.model_validate({**old, **bad})
    assert PolicyTrainingConfig.model_validate({"augment_translation": [0, 0, 0], "augment_state_noise": 0}) == PolicyTrainingConfig()
    with pytest.raises(ValidationError, match="augment_translation: retired"):
        PolicyTrainingConfig.model_validate({"augment_translation": [0.05, 0.05, 0.01]})


@pytest.mark.parametrize("target", ["absolute", "relative"])
def test_loss_falls_when_overfitting_a_handful_of_samples(target) -> None:
    policy = make_policy(target=target)
    batch = samples(8)
    policy.set_normalizers(stats_of(batch))
    opt = make_optimizer(policy.parameters(), OptimizerConfig(lr=2e-3, warmup_steps=10))
    sched = make_lr_schedule(opt, OptimizerConfig(lr=2e-3, warmup_steps=10), total_steps=150)
    ema = ExponentialMovingAverage(policy)
    g = torch.Generator().manual_seed(0)
    losses = []
    for _ in range(150):
        loss = policy.compute_loss(batch, generator=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        ema.step(policy)
        losses.append(loss.item())
    first, last = sum(losses[:10]) / 10, sum(losses[-10:]) / 10
    assert last < 0.35 * first, (first, last)
    pred = ema.averaged_model.predict(batch, generator=torch.Generator().manual_seed(1))
    assert pred.shape == (8, 8, 32)
    spread = (batch["anchors"] - batch["anchors"].mean(0)).abs().mean()
    assert (pred - batch["anchors"]).abs().mean() < 0.6 * spread  # sampling finds the memorised anchors (0.4 seen)


def test_only_the_active_tasks_encoders_receive_gradient() -> None:
    policy = make_policy()
    batch = samples(4, tasks=[2, 5, 2, 5])
    policy.compute_loss(batch, generator=torch.Generator().manual_seed(0)).backward()
    for k, enc in enumerate(policy.point_encoder.encoders):
        grads = [p.grad for p in enc.parameters()]
        if k in (2, 5):
            assert all(gr is not None and gr.abs().sum() > 0 for gr in grads), k
        else:
            assert all(gr is None or not gr.any() for gr in grads), k
    assert all(p.grad is not None for p in policy.unet.parameters())


def test_a_task_embedding_tells_the_action_expert_the_task_where_the_encoders_see_alike_features() -> None:
    """With every task's point encoder giving the same feature (here: the same weights), the
    condition differs between tasks only through the task's learned vector, and the loss trains it."""
    config = TINY.model_copy(update={"task_embedding": 8})
    assert config.cond_dim == TINY.cond_dim + 8
    torch.manual_seed(0)
    policy = AnchorDiffusionPolicy(config)
    for enc in policy.point_encoder.encoders[1:]:
        enc.load_state_dict(policy.point_encoder.encoders[0].state_dict())
    batch = samples(2, tasks=[3, 4])
    batch = {**batch, "points": batch["points"][:1].expand(2, -1, -1), "state": batch["state"][:1].expand(2, -1)}
    policy.set_normalizers(stats_of(batch))
    cond = policy.encode_observation(batch)
    torch.testing.assert_close(cond[0, :-8], cond[1, :-8])
    assert not torch.allclose(cond[0, -8:], cond[1, -8:])
    policy.compute_loss(batch, generator=torch.Generator().manual_seed(0)).backward()
    grad = policy.task_embedding.weight.grad
    assert grad[3].abs().sum() > 0 and grad[4].abs().sum() > 0 and grad[0].abs().sum() == 0
    assert AnchorDiffusionPolicy(TINY).task_embedding is None  # off: the report's condition


def test_mixed_task_batch_matches_per_sample_encoding() -> None:
    policy = make_policy().eval()
    batch = samples(5, tasks=[7, 0, 3, 0, 7])
    with torch.no_grad():
        together = policy.point_encoder(batch["points"], batch["task_id"])
        alone = torch.cat([policy.point_encoder.encoders[int(k)](batch["points"][i : i + 1]) for i, k in enumerate(batch["task_id"])])
    torch.testing.assert_close(together, alone)


def test_checkpoint_round_trip_gives_identical_predictions() -> None:
    policy = make_policy(seed=3)
    batch = samples(3, seed=4)
    policy.set_normalizers(stats_of(batch))
    buffer = io.BytesIO()
    torch.save(policy.state_dict(), buffer)
    buffer.seek(0)
    restored = make_policy(seed=99)
    restored.load_state_dict(torch.load(buffer, weights_only=True))
    obs = {k: batch[k] for k in ("points", "state", "task_id")}
    a = policy.predict(obs, generator=torch.Generator().manual_seed(7))
    b = restored.predict(obs, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b)
    assert bool(restored.anchor_normalizer.fitted) and bool(restored.point_normalizer.fitted)
    c = restored.predict(obs, generator=torch.Generator().manual_seed(8))
    assert not torch.equal(a, c)


def test_ema_update_moves_the_averaged_weights() -> None:
    policy = make_policy()
    ema = ExponentialMovingAverage(policy)
    assert ema.decay(0) == 0.0 and ema.decay(1) == 0.0
    assert 0.0 < ema.decay(10) < ema.decay(1000) <= 0.9999
    opt = torch.optim.SGD(policy.parameters(), lr=0.1)
    policy.compute_loss(samples(4), generator=torch.Generator().manual_seed(0)).backward()
    opt.step()
    ema.optimization_step.fill_(10)
    before = [p.clone() for p in ema.averaged_model.parameters()]
    d = ema.step(policy)
    moved = [not torch.equal(b, p) for b, p in zip(before, ema.averaged_model.parameters())]
    assert 0.0 < d < 1.0 and any(moved)
    names = [n for n, _ in ema.averaged_model.named_parameters()]
    w_old = before[names.index("unet.final.1.weight")]
    w_model, w_avg = policy.unet.final[1].weight, ema.averaged_model.unet.final[1].weight
    torch.testing.assert_close(w_avg, d * w_old + (1 - d) * w_model)
    assert not any(p.requires_grad for p in ema.averaged_model.parameters())


def test_bad_inputs_are_clear_errors() -> None:
    policy = make_policy()
    batch = samples(2)
    with pytest.raises(ValueError, match=r"points: expected \(B, N, 12\)"):
        policy.predict({**batch, "points": batch["points"][..., :11]})
    with pytest.raises(ValueError, match=r"anchors: expected \(B, 8, 32\)"):
        policy.compute_loss({**batch, "anchors": batch["anchors"][:, :4]})
    with pytest.raises(ValueError, match="task_id"):
        policy.compute_loss({**batch, "task_id": torch.tensor([0, 8])})
