"""The anchor diffusion policy: one observation frame -> the next H anchors (H x 32).

Observation: ``points (B, N, 12)`` (11 features + critical probability), ``state (B, 32)``,
``task_id (B,)`` (which point encoder, and with ``task_embedding`` which learned task vector, joins
the condition). With the object head (``config.objects``) the critical points' K clusters
(``models.objects``) add their own feature to the condition, and with its ``anchored_offsets`` the
offset of the object a
classifier picks per (slot, arm) is added to the denoiser's clean sample where it holds
end-effector positions (``anchored_shift``; the classifier learns which object each labelled anchor
lies by, ``gate_loss``). The task's own point encoder and the state MLP give the FiLM condition of one
shared conditional 1-D U-Net, which denoises the ``(B, H, 32)`` anchor sequence with diffusers'
``DDIMScheduler`` (DP3's settings: 100 training steps, squaredcos_cap_v2, clip_sample,
prediction_type ``sample``, 10 inference steps). Training loss: MSE over all H x 32 elements of the
prediction target (the clean anchors for ``sample``, the noise for ``epsilon``). Normalizers of
points, state and anchors live in the module's buffers, so they travel inside checkpoints.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from anchordp3.models.device import autocast
from anchordp3.models.encoders import StateEncoder, TaskConditionedEncoder
from anchordp3.models.kernels import fast_kernels
from anchordp3.models.normalizer import MinMaxNormalizer
from anchordp3.models.objects import (ObjectTokenEncoder, finger_yaw, held_tokens, nearest_branch, nearest_token_gates,
                                      object_tokens, pair_offsets, split_alike, token_features, token_gripper_offsets,
                                      token_heading, token_yaw, top_down_rot6)
from anchordp3.models.unet1d import ConditionalUnet1D
from anchordp3.schemas.state import ARMS, StateLayout
from anchordp3.schemas.tasks import task_id as registered_task_id
from anchordp3.schemas.training import DiffusionSchedulerConfig, PolicyConfig


def make_scheduler(config: DiffusionSchedulerConfig):
    """A diffusers ``DDIMScheduler`` with ``config``'s settings (eta = 0: deterministic steps)."""
    from diffusers import DDIMScheduler

    return DDIMScheduler(
        num_train_timesteps=config.num_train_timesteps,
        beta_schedule=config.beta_schedule,
        clip_sample=config.clip_sample,
        set_alpha_to_one=True,
        steps_offset=0,
        prediction_type=config.prediction_type,
    )


GATE_HIDDEN = 256  # anchor gating: width of the classifier's hidden layer
FIT_MIN_ANCHORS = 20  # labelled anchors a (task, offset, arm) needs before its yaw is fitted
FIT_CONCENTRATION = 0.95  # mean resultant length of 2 x (finger yaw - axis yaw) needed: a spread of about 9 degrees
HELD_FIT_CONCENTRATION = 0.8  # of (turn + held object's heading): a heading read half a turn off in under a tenth of frames
FIT_MIN_ANISOTROPY = 0.2  # objects rounder than this in a frame tell no axis; their anchors are not fitted on
YAW_BINS = 360  # one-degree bins of the expert's finger yaws, whose widest empty arc tells the branch it prefers
YAW_STRAY = 0.005  # a bin holding under this share of a fit's anchors counts as empty (a stray anchor splits no arc)


def preferred_yaw(counts: torch.Tensor) -> torch.Tensor:
    """The yaw the expert's grasps turn toward, from histograms ``counts (cells, YAW_BINS)`` of
    finger yaws over [0, 2π): the opposite of the widest run of (nearly) empty bins, circularly.
    An expert that takes of ``ψ`` and ``ψ + π`` the one nearer a preferred yaw p leaves the half
    circle around p + π empty, so its middle's opposite is p; a mean of the yaws would lean toward
    where the scenes put more of them (the phone's: 4.6° off), and grasps near the branch's edge
    would take the other half turn. ``(cells,)`` radians."""
    empty = counts < YAW_STRAY * counts.sum(-1, keepdim=True).clamp(min=1)
    twice = torch.cat([empty, empty], dim=-1).long()  # circular runs, unrolled once
    run = torch.zeros_like(twice)
    run[:, 0] = twice[:, 0]
    for i in range(1, twice.shape[1]):
        run[:, i] = (run[:, i - 1] + 1) * twice[:, i]
    length, end = run.max(-1)  # the widest empty run's length (bins) and its last bin
    middle = (end.float() - (length.float() - 1) / 2 + 0.5) * (2 * torch.pi / YAW_BINS)
    return torch.remainder(middle + torch.pi + torch.pi, 2 * torch.pi) - torch.pi


def medoid(samples: torch.Tensor) -> torch.Tensor:
    """``samples (B, K, H, D)`` -> ``(B, H, D)``: per row, the sample whose summed Euclidean distance
    to the row's other samples (all H x D elements, normalised units) is least."""
    flat = samples.flatten(2)
    pick = torch.cdist(flat, flat).sum(-1).argmin(-1)  # (B,)
    return samples[torch.arange(len(samples), device=samples.device), pick]


class AnchorDiffusionPolicy(nn.Module):
    """Task-conditioned encoders + conditional U-Net diffusion over anchors.

    Batches (``compute_loss``) and observations (``predict``) are dicts of tensors:
    ``points (B, N, point_channels)`` float32, ``state (B, action_dim)`` float32, ``task_id (B,)``
    long, with role tokens ``roles (B, N)`` integer (each point's role, 0 none), and for training
    ``anchors (B, horizon, action_dim)`` float32, all in data units.
    """

    def __init__(self, config: PolicyConfig | None = None, mixed_precision: bool = True) -> None:
        super().__init__()
        self.config = config = config or PolicyConfig()
        self.mixed_precision = mixed_precision
        self.point_channels = config.point_encoder.in_channels
        self.layout = StateLayout.of_length(config.action_dim)
        self.point_encoder = TaskConditionedEncoder(config.num_tasks, config.point_encoder)
        self.state_encoder = StateEncoder(config.state_encoder)
        self.task_embedding = nn.Embedding(config.num_tasks, config.task_embedding) if config.task_embedding else None
        self.object_encoder = None
        self.objects = objects = config.objects  # the object head's settings, or None
        if objects is not None:
            self.object_encoder = ObjectTokenEncoder(objects.tokens, out_dim=objects.encoder_dim,
                                                     features=token_features(objects.orientation, objects.half_angle,
                                                                             objects.heading))
        self.unet = ConditionalUnet1D(config.action_dim, config.cond_dim, config.unet)
        self.point_normalizer = MinMaxNormalizer(self.point_channels)
        self.state_normalizer = MinMaxNormalizer(config.action_dim)
        self.anchor_normalizer = MinMaxNormalizer(config.action_dim)
        self.delta_normalizer = MinMaxNormalizer(config.horizon * config.action_dim)  # relative targets, per slot
        self.noise_scheduler = make_scheduler(config.scheduler)
        self.anchor_gates = None
        if objects is not None and objects.anchored_offsets:  # logits per (slot, arm): none or one offset
            self.anchor_gates = nn.Sequential(
                nn.Linear(config.cond_dim, GATE_HIDDEN), nn.Mish(),
                nn.Linear(GATE_HIDDEN, config.horizon * len(ARMS) * (objects.gate_choices + 1)))
        if objects is not None and objects.choice_offsets:  # (task, offset, arm) -> metres, fitted (fit_choices)
            self.register_buffer("choice_xyz", torch.zeros(config.num_tasks, objects.gate_choices, len(ARMS), 3))
        if objects is not None and objects.anchored_yaw:  # (task, offset, arm) -> yaw offset, preferred yaw, fitted (0/1)
            self.register_buffer("choice_yaw", torch.zeros(config.num_tasks, objects.gate_choices, len(ARMS), 3))
        if objects is not None and objects.held_yaw:  # (task, offset, arm) -> heading the held object is turned to, fitted (0/1)
            self.register_buffer("held_yaw", torch.zeros(config.num_tasks, objects.gate_choices, len(ARMS), 2))

    # ------------------------------------------------------------------------------ setup
    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def set_normalizers(self, stats: Mapping[str, Mapping[str, object]]) -> None:
        """Fit the normalizers from dataset statistics: ``{"state": {"min", "max"}, "anchors":
        {"min", "max"}, "points": {"min", "max"}}``. Anchor stats may be per dimension ``(32,)`` or
        per horizon slot ``(H, 32)`` (reduced over H). Point stats of 11 channels leave the 12th
        (critical probability, already in [0, 1]) mapped to [-1, 1] from [0, 1]; ``points`` is
        optional (identity when absent)."""
        for key, norm in (("state", self.state_normalizer), ("anchors", self.anchor_normalizer)):
            if key not in stats:
                raise KeyError(f"stats: missing {key!r} (need 'state' and 'anchors', optional 'points')")
            fitted = MinMaxNormalizer.from_stats(stats[key])
            norm.set_limits(fitted.min, fitted.max, self.config.normalizer_min_range)
        if self.config.target == "relative":
            if "delta" not in stats:
                raise KeyError("stats: missing 'delta' (min/max of anchors minus state, (H, D)), needed by relative targets")
            lo = torch.as_tensor(np.asarray(stats["delta"]["min"], dtype=np.float64)).reshape(-1)
            hi = torch.as_tensor(np.asarray(stats["delta"]["max"], dtype=np.float64)).reshape(-1)
            self.delta_normalizer.set_limits(lo, hi, self.config.normalizer_min_range)
        if "points" in stats:
            fitted = MinMaxNormalizer.from_stats(stats["points"])
            lo, hi = fitted.min, fitted.max
            if lo.numel() == self.point_channels - 1:
                lo, hi = torch.cat([lo, lo.new_zeros(1)]), torch.cat([hi, hi.new_ones(1)])
            self.point_normalizer.set_limits(lo, hi)

    # --------------------------------------------------------------------------- forward
    def encode_observation(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """obs (data units) -> FiLM condition (B, cond_dim): point feature, state feature, with the
        object head the critical-object tokens' feature, and with ``task_embedding`` the task's vector."""
        return self._condition(obs)[0]

    def _condition(self, obs: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor | None]:
        """obs -> (FiLM condition (B, cond_dim), object tokens (B, K, token features) or None)."""
        points, state, task_id = self._observation(obs)
        parts = [self.point_encoder(self.point_normalizer(points), task_id), self.state_encoder(self.state_normalizer(state))]
        tokens = None
        if self.object_encoder is not None:
            tokens = self._tokens(obs, points, state)
            parts.append(self.object_encoder(tokens.to(parts[0].dtype)))
        if self.task_embedding is not None:
            parts.append(self.task_embedding(task_id).to(parts[0].dtype))
        return torch.cat(parts, dim=-1), tokens

    def _tokens(self, obs: Mapping[str, torch.Tensor], points: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """The object head's tokens of ``obs`` (``models.objects.object_tokens`` with the head's settings)."""
        return object_tokens(points, state, self.layout, self.objects.tokens, orientation=self.objects.orientation,
                             z_weight=self.objects.z_weight, roles=self._roles(obs, points), half_angle=self.objects.half_angle,
                             heading=self.objects.heading)

    def gates(self, cond: torch.Tensor) -> torch.Tensor:
        """The anchored offsets' gates from ``cond (B, cond_dim)``: ``(B, H, arms, gate_choices)``
        float32, one per (horizon slot, arm in ``ARMS`` order, offset: an object token, or with
        ``held_offsets`` an (object, held object) pair, ``pair_offsets``): the one-hot of the
        classifier's choice (``gate_logits``), all zero where it chose no object."""
        return F.one_hot(self.gate_logits(cond).argmax(-1), self.objects.gate_choices + 1)[..., 1:].float()

    def gate_logits(self, cond: torch.Tensor) -> torch.Tensor:
        """The gating classifier: ``cond (B, cond_dim)`` -> logits ``(B, H, arms, 1 +
        gate_choices)`` over "no object" (class 0) and offset g (class g + 1)."""
        return self.anchor_gates(cond.float()).view(-1, self.config.horizon, len(ARMS), self.objects.gate_choices + 1)

    def anchored_shift(self, gates: torch.Tensor | None, tokens: torch.Tensor | None, state: torch.Tensor | None = None,
                       task_id: torch.Tensor | None = None) -> torch.Tensor | float:
        """What ``anchored_offsets`` adds to the denoiser's clean sample, ``(B, H, D)`` in normalised
        target units (0 without it): in arm a's end-effector xyz of slot h, ``sum_g gates[h, a, g] *
        offset_g`` (metres: ``centroid_k - ee_a`` per token, with ``held_offsets`` also ``centroid_k -
        centroid_j`` per pair, ``pair_offsets``; an absent object offers 0), for ``gates (B, H, arms,
        gate_choices)`` (``gates``, or the labels in training), scaled as the
        relative-target normaliser scales those dims. With ``choice_offsets`` each offset also adds
        its fitted constant, and with ``anchored_yaw`` an offset whose yaw was fitted sets arm a's
        rotation to the top-down one of its object's axis yaw plus the fitted offset, with ``held_yaw``
        a place's rotation to the one that turns the held object to the fitted heading
        (``fit_choices``), all per task: these need ``state (B, D)`` data units and ``task_id (B,)``
        model ids."""
        if gates is None or tokens is None:
            return 0.0
        h, d = self.config.horizon, self.config.action_dim
        shift = gates.new_zeros((gates.shape[0], h, d), dtype=torch.float32)
        offsets = pair_offsets(tokens) if self.objects.held_offsets else token_gripper_offsets(tokens.float())  # (B, G, arms, 3)
        rotations = None
        if self.objects.fits_choices:
            if state is None or task_id is None:
                raise ValueError("anchored_shift: choice_offsets, anchored_yaw and held_yaw need the state and the task ids")
            task_id = torch.as_tensor(task_id, device=offsets.device).long().reshape(-1)
            if self.objects.choice_offsets:
                offsets = offsets + self.choice_xyz[task_id]
            if self.objects.anchored_yaw or self.objects.held_yaw:
                rotations = self._anchored_rotations(tokens, state.float(), task_id)  # (B, G, arms, 6)
        for a, arm in enumerate(ARMS):
            shift[:, :, self.layout.ee_xyz(arm)] = torch.einsum("bhk,bkc->bhc", gates[:, :, a].float(), offsets[:, :, a])
            if rotations is not None:
                shift[:, :, self.layout.ee_rot6(arm)] = torch.einsum("bhk,bkc->bhc", gates[:, :, a].float(), rotations[:, :, a])
        return shift * self.delta_normalizer.scale.view(h, d).to(shift.dtype)

    def _choice_objects(self, device: torch.device) -> torch.Tensor:
        """The object each gate choice is placed by: ``(gate_choices,)`` token index (a pair's target object k)."""
        k = self.objects.tokens
        return torch.arange(self.objects.gate_choices, device=device) // (k if self.objects.held_offsets else 1)

    def _anchored_rotations(self, tokens: torch.Tensor, state: torch.Tensor, task_id: torch.Tensor) -> torch.Tensor:
        """``(B, gate_choices, arms, 6)``: per choice and arm, the fitted top-down rotation minus the arm's
        rotation now (``R[:3, :2]`` units), 0 where none applies: with ``held_yaw`` where it was fitted
        and the arm holds the pair's object (``_held_yaws``), else with ``anchored_yaw`` its object's
        axis yaw plus the fitted offset, where fitted and the object tells an axis in this frame
        (anisotropy above ``FIT_MIN_ANISOTROPY``, as in the fit; an absent object's is 0)."""
        yaw = tokens.new_zeros((tokens.shape[0], self.objects.gate_choices, len(ARMS)), dtype=torch.float32)
        use = torch.zeros_like(yaw)
        if self.objects.anchored_yaw:
            theta, anisotropy = token_yaw(tokens)  # (B, K)
            obj = self._choice_objects(tokens.device)
            fit = self.choice_yaw[task_id]  # (B, G, arms, 3): offset, preferred, fitted
            yaw = nearest_branch(theta[:, obj, None] + fit[..., 0], fit[..., 1])  # (B, G, arms)
            use = fit[..., 2] * (anisotropy[:, obj, None] > FIT_MIN_ANISOTROPY).float()
        if self.objects.held_yaw:
            held, ok = self._held_yaws(tokens, state)
            ok = ok * self.held_yaw[task_id][..., 1]
            yaw = torch.where(ok > 0, held + self.held_yaw[task_id][..., 0], yaw)
            use = torch.maximum(use, ok)
        now = torch.stack([state[:, self.layout.ee_rot6(arm)] for arm in ARMS], dim=1)  # (B, arms, 6)
        return (top_down_rot6(yaw) - now[:, None]) * use[..., None]

    def _held_yaws(self, tokens: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """For ``held_yaw``: per (pair choice g = (k, j), arm), the arm's finger yaw now less held object
        j's heading (``token_heading``), radians ``(B, G, arms)``: a place that turns j to heading c has
        its finger yaw at this plus c. And where that holds ``(B, G, arms)`` 0/1: the arm holds j
        (``held_tokens``, j != k), points straight down, and j tells an axis (anisotropy above
        ``FIT_MIN_ANISOTROPY``)."""
        k = self.objects.tokens
        grippers = torch.stack([state[:, self.layout.gripper(arm)] for arm in ARMS], dim=-1)
        holds = held_tokens(tokens, grippers)  # (B, arms, K)
        heading, anisotropy = token_heading(tokens)  # (B, K)
        psi, down = finger_yaw(torch.stack([state[:, self.layout.ee_rot6(arm)] for arm in ARMS], dim=1))  # (B, arms)
        choice = torch.arange(self.objects.gate_choices, device=tokens.device)
        target, j = choice // k, choice % k
        ok = holds[:, :, j].transpose(1, 2) * (target != j).float()[None, :, None]  # (B, G, arms)
        ok = ok * down[:, None, :].float() * (anisotropy[:, j] > FIT_MIN_ANISOTROPY).float()[..., None]
        return psi[:, None, :] - heading[:, j, None], ok

    @torch.no_grad()
    def fit_choices(self, batches) -> list[dict[str, float]]:
        """Fit ``choice_offsets`` and ``anchored_yaw`` on training batches (dicts as ``compute_loss``
        takes, with ``anchors``): per (task, offset g, arm) over the labelled anchors that take g
        (``gate_targets``, every horizon slot), the mean of the end-effector position less the offset
        (metres), and where the anchors point straight down at an object with an axis (anisotropy
        above ``FIT_MIN_ANISOTROPY``), the circular mean of their finger yaw less the axis yaw, modulo
        π (a parallel gripper closes alike turned half a turn), and the branch the expert takes
        (``preferred_yaw`` of their yaws); a yaw is used where ``FIT_MIN_ANCHORS`` agree within
        ``FIT_CONCENTRATION``. With ``held_yaw``, over the anchors of a pair (k, j) taken while the arm
        holds j (``_held_yaws``) and pointing straight down, the circular mean of their finger yaw less
        (the finger yaw now less j's heading): the heading j is turned to, used where
        ``FIT_MIN_ANCHORS`` agree within ``HELD_FIT_CONCENTRATION``.
        Returns one row per fitted yaw: kind ("axis" or "held"), task (model id), choice, arm, anchors,
        offset (deg: from the axis, or the held object's heading), concentration."""
        t, g, arms = self.config.num_tasks, self.objects.gate_choices, len(ARMS)
        cells = t * g * arms
        count, xyz = torch.zeros(cells), torch.zeros(cells, 3)
        n_yaw, double, heading = torch.zeros(cells), torch.zeros(cells, 2), torch.zeros(cells, YAW_BINS)
        n_held, turned = torch.zeros(cells), torch.zeros(cells, 2)
        obj = self._choice_objects(torch.device("cpu"))
        for batch in batches:  # the tokens alone: the encoders' condition is not needed
            points, state, task = self._observation(batch)
            tokens = self._tokens(batch, points, state).float().cpu()
            state, task = state.cpu(), task.cpu()
            anchors = torch.as_tensor(batch["anchors"], dtype=torch.float32).cpu()
            labels = self.gate_targets(tokens, anchors, state)  # (B, H, arms, G)
            offsets = pair_offsets(tokens) if self.objects.held_offsets else token_gripper_offsets(tokens)
            theta, anisotropy = token_yaw(tokens) if self.objects.anchored_yaw else (None, None)
            held, held_ok = self._held_yaws(tokens, state) if self.objects.held_yaw else (None, None)
            rows = torch.arange(len(tokens))[:, None]
            for a, arm in enumerate(ARMS):
                sel, choice = labels[:, :, a].sum(-1) > 0, labels[:, :, a].argmax(-1)  # (B, H)
                cells_of = (task[:, None] * g + choice) * arms + a  # (B, H) each anchor's (task, choice, arm)
                cell = cells_of[sel]
                delta = anchors[:, :, self.layout.ee_xyz(arm)] - state[:, None, self.layout.ee_xyz(arm)]
                count.index_add_(0, cell, torch.ones(len(cell)))
                xyz.index_add_(0, cell, (delta - offsets[rows, choice, a])[sel])
                if held is None and theta is None:
                    continue
                yaw, down = finger_yaw(anchors[:, :, self.layout.ee_rot6(arm)])
                if held is not None:
                    ok = sel & down & (held_ok[rows, choice, a] > 0)
                    turn = yaw - held[rows, choice, a]
                    n_held.index_add_(0, cells_of[ok], torch.ones(int(ok.sum())))
                    turned.index_add_(0, cells_of[ok], torch.stack([turn.cos(), turn.sin()], -1)[ok])
                if theta is None:
                    continue
                k = obj[choice]  # (B, H) the object each anchor lies by
                ok = sel & down & (anisotropy[rows, k] > FIT_MIN_ANISOTROPY)
                diff = 2 * (yaw - theta[rows, k])
                cell = cells_of[ok]
                n_yaw.index_add_(0, cell, torch.ones(len(cell)))
                double.index_add_(0, cell, torch.stack([diff.cos(), diff.sin()], -1)[ok])
                bins = (torch.remainder(yaw, 2 * torch.pi) / (2 * torch.pi) * YAW_BINS).long().clamp(max=YAW_BINS - 1)
                heading.index_put_((cell, bins[ok]), torch.ones(len(cell)), accumulate=True)
        mean = double / n_yaw.clamp(min=1)[:, None]
        concentration = mean.norm(dim=-1)
        fitted = (n_yaw >= FIT_MIN_ANCHORS) & (concentration >= FIT_CONCENTRATION)
        offset = torch.atan2(mean[:, 1], mean[:, 0]) / 2
        if self.objects.choice_offsets:
            self.choice_xyz.copy_((xyz / count.clamp(min=1)[:, None]).view(t, g, arms, 3))
        rows = []
        if self.objects.anchored_yaw:
            self.choice_yaw.copy_(torch.stack([offset, preferred_yaw(heading), fitted.float()], -1).view(t, g, arms, 3))
            rows += self._fit_rows("axis", fitted, n_yaw, offset, concentration)
        if self.objects.held_yaw:
            mean = turned / n_held.clamp(min=1)[:, None]
            concentration, offset = mean.norm(dim=-1), torch.atan2(mean[:, 1], mean[:, 0])
            fitted = (n_held >= FIT_MIN_ANCHORS) & (concentration >= HELD_FIT_CONCENTRATION)
            self.held_yaw.copy_(torch.stack([offset, fitted.float()], -1).view(t, g, arms, 2))
            rows += self._fit_rows("held", fitted, n_held, offset, concentration)
        return rows

    def _fit_rows(self, kind: str, fitted: torch.Tensor, anchors: torch.Tensor, offset: torch.Tensor,
                  concentration: torch.Tensor) -> list[dict]:
        """``fit_choices``' rows of the fitted cells (``(cells,)`` each, cell = (task x choice + g) x arms + a)."""
        g, arms = self.objects.gate_choices, len(ARMS)
        return [{"kind": kind, "task": int(i // (g * arms)), "choice": int(i // arms % g), "arm": ARMS[int(i % arms)],
                 "anchors": int(anchors[i]), "offset_deg": float(torch.rad2deg(offset[i])),
                 "concentration": float(concentration[i])} for i in torch.nonzero(fitted).flatten()]

    def compute_loss(self, batch: Mapping[str, torch.Tensor], generator: torch.Generator | None = None) -> torch.Tensor:
        """Diffusion training loss of one batch: MSE over all (B, H, action_dim) elements, plus the
        gates' loss (``gate_loss``) weighted by ``gate_supervision``.

        The diffusion noise and timesteps are drawn from ``generator`` (CPU) when given, so a
        seeded run is reproducible across devices. Runs under autocast on CUDA. With anchored
        offsets the offsets follow the labelled anchors' objects (teacher forcing)."""
        anchors = torch.as_tensor(batch["anchors"], device=self.device, dtype=torch.float32)
        self._check_anchors(anchors)
        state = torch.as_tensor(batch["state"], device=self.device, dtype=torch.float32)
        x0 = self.to_target(anchors, state)
        noise = torch.randn(x0.shape, generator=generator).to(self.device)
        steps = torch.randint(0, self.noise_scheduler.config.num_train_timesteps, (x0.shape[0],), generator=generator).to(self.device)
        noisy = self.noise_scheduler.add_noise(x0, noise, steps)
        with autocast(self.device, self.mixed_precision):
            cond, tokens = self._condition(batch)
            pred = self.unet(noisy, steps, cond)
        target = x0 if self.config.scheduler.prediction_type == "sample" else noise
        if self.anchor_gates is None or tokens is None:
            return F.mse_loss(pred.float(), target)
        labels = self.gate_targets(tokens, anchors, state)
        loss = F.mse_loss(pred.float() + self.anchored_shift(labels, tokens, state, batch["task_id"]), target)
        return loss + self.objects.gate_supervision * self.gate_loss(cond, labels)

    def gate_targets(self, tokens: torch.Tensor, anchors: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Which offset each labelled anchor takes: ``anchors (B, H, D)``, ``state (B, D)`` data units,
        ``tokens (B, K, features)`` -> ``(B, H, arms, gate_choices)`` float32 one-hot or zero: the
        object it lies by (``nearest_token_gates`` within ``gate_radius``) and, with ``held_offsets``,
        relative to the object the arm holds now (``held_tokens``) when that is another one; zero
        (no object) for an anchor within ``stay_radius`` of the arm's end effector now. With
        ``held_destination``, an arm holding object j is labelled by the object nearest where j
        would be (the anchor plus j's offset from the gripper now), j itself excluded: a place
        anchor lies by its target, not by the object it carries."""
        positions = torch.stack([anchors[:, :, self.layout.ee_xyz(arm)] for arm in ARMS], dim=2)  # (B, H, arms, 3)
        obj = self.objects
        if obj.held_offsets:
            grippers = torch.stack([state[:, self.layout.gripper(arm)] for arm in ARMS], dim=-1)
            held = held_tokens(tokens, grippers)  # (B, arms, K)
        if obj.held_destination:  # where the held object would be, by any object but itself
            grip = torch.einsum("bak,bkac->bac", held, token_gripper_offsets(tokens.float()))  # (B, arms, 3)
            near = nearest_token_gates(positions + grip[:, None], tokens, obj.gate_radius, exclude=held)
        else:
            near = nearest_token_gates(positions, tokens, obj.gate_radius)  # (B, H, arms, K)
        if obj.stay_radius:
            now = torch.stack([state[:, self.layout.ee_xyz(arm)] for arm in ARMS], dim=1)  # (B, arms, 3)
            moves = (positions - now[:, None]).norm(dim=-1) >= obj.stay_radius  # (B, H, arms)
            near = near * moves[..., None].to(near.dtype)
        if not obj.held_offsets:
            return near
        eye = torch.eye(tokens.shape[1], device=tokens.device)
        other = held[:, None, :, None, :] * (1 - eye)  # (B, 1, arms, K, K): holds j != k
        pick = other + eye * (1 - other.sum(-1, keepdim=True))  # (k, j): held j != k, else (k, k)
        return (near[..., None] * pick).flatten(-2)

    @torch.no_grad()
    def first_gate_hits(self, batch: Mapping[str, torch.Tensor]) -> torch.Tensor | None:
        """Whether the first slot's gates choose the labelled first anchor's object (``gate_targets``)
        for every arm: a batch with ``anchors`` -> ``(B,)`` bool; None without anchored offsets."""
        if self.anchor_gates is None:
            return None
        cond, tokens = self._condition(batch)
        anchors = torch.as_tensor(batch["anchors"], device=self.device, dtype=torch.float32)
        state = torch.as_tensor(batch["state"], device=self.device, dtype=torch.float32)
        labels = self.gate_targets(tokens, anchors, state)[:, 0]  # (B, arms, gate_choices)
        return (self.gates(cond)[:, 0].round() == labels).all(-1).all(-1)

    def gate_loss(self, cond: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """How far the gates are from the labelled anchors' offsets, ``targets (B, H, arms,
        gate_choices)`` (``gate_targets``): the cross-entropy of ``gate_logits`` against the class
        (0: no object, g + 1: offset g)."""
        classes = (targets.argmax(-1) + 1) * (targets.sum(-1) > 0)  # (B, H, arms)
        return F.cross_entropy(self.gate_logits(cond).flatten(0, 2), classes.flatten())

    @torch.no_grad()
    def predict(self, obs: Mapping[str, torch.Tensor], generator: torch.Generator | None = None,
                steps: int | None = None, samples: int = 1) -> torch.Tensor:
        """DDIM sampling of the next anchors. obs: points (B, N, C), state (B, action_dim),
        task_id (B,) -> anchors (B, horizon, action_dim) float32 in data units (unnormalised).

        The initial noise comes from ``generator`` (CPU) when given; the DDIM steps are
        deterministic, so the same generator seed gives the same anchors. ``steps``: DDIM steps
        (None: the config's ``scheduler.num_inference_steps``). ``samples``: anchor sequences
        drawn per observation (K, one encoder pass); with K > 1 the one returned is their medoid
        (``medoid``), a consensus that drops a stray sample yet stays one of the samples. Call on
        the EMA copy (``ExponentialMovingAverage.averaged_model``) in evaluation."""
        if samples < 1:
            raise ValueError(f"samples: {samples}, need at least 1")
        scheduler = self.noise_scheduler
        with autocast(self.device, self.mixed_precision):
            cond, tokens = self._condition(obs)
        b = cond.shape[0]
        if samples > 1:
            cond = cond.repeat_interleave(samples, 0)
            tokens = None if tokens is None else tokens.repeat_interleave(samples, 0)
        state = torch.as_tensor(obs["state"], device=self.device, dtype=torch.float32)
        gates = None if self.anchor_gates is None else self.gates(cond)
        task_id = torch.as_tensor(obs["task_id"], device=self.device).long().reshape(-1)
        shift = self.anchored_shift(gates, tokens, state.repeat_interleave(samples, 0), task_id.repeat_interleave(samples, 0))
        x = torch.randn((b * samples, self.config.horizon, self.config.action_dim), generator=generator).to(self.device)
        steps = self.config.scheduler.num_inference_steps if steps is None else steps
        if not 1 <= steps <= self.config.scheduler.num_train_timesteps:
            raise ValueError(f"ddim steps: {steps} outside 1..{self.config.scheduler.num_train_timesteps}")
        scheduler.set_timesteps(steps)  # CPU timesteps; the U-Net moves them
        with autocast(self.device, self.mixed_precision):  # every step's FiLM at once (the reference kernels: per step)
            table = self.unet.film_table(cond, scheduler.timesteps) if fast_kernels() else None
        for i, t in enumerate(scheduler.timesteps):
            with autocast(self.device, self.mixed_precision):
                out = self.unet(x, t, cond, film=None if table is None else [f[i] for f in table])
            x = scheduler.step(out.float() + shift, t, x).prev_sample
        if samples > 1:
            x = medoid(x.view(b, samples, *x.shape[1:]))
        return self.from_target(x, state)

    def to_target(self, anchors: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Anchors ``(B, H, D)`` in data units -> the normalised diffusion target ``(B, H, D)``:
        the anchors (``absolute``) or the anchors minus ``state (B, D)`` per horizon slot (``relative``)."""
        if self.config.target == "absolute":
            return self.anchor_normalizer(anchors)
        delta = (anchors - state[:, None, :]).reshape(len(anchors), -1)
        return self.delta_normalizer(delta).reshape(anchors.shape)

    def from_target(self, x: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Inverse of ``to_target``: ``x (B, H, D)`` normalised -> anchors in data units."""
        if self.config.target == "absolute":
            return self.anchor_normalizer.unnormalize(x)
        return self.delta_normalizer.unnormalize(x.reshape(len(x), -1)).reshape(x.shape) + state[:, None, :]

    # --------------------------------------------------------------------------- helpers
    def _observation(self, obs: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        for key in ("points", "state", "task_id"):
            if key not in obs:
                raise KeyError(f"observation: missing {key!r} (need points, state, task_id)")
        points = torch.as_tensor(obs["points"], device=self.device, dtype=torch.float32)
        state = torch.as_tensor(obs["state"], device=self.device, dtype=torch.float32)
        task_id = torch.as_tensor(obs["task_id"], device=self.device, dtype=torch.long).reshape(-1)
        if points.ndim != 3 or points.shape[-1] != self.point_channels:
            raise ValueError(f"points: expected (B, N, {self.point_channels}), got {tuple(points.shape)}")
        if state.ndim != 2 or state.shape != (points.shape[0], self.config.action_dim):
            raise ValueError(f"state: expected ({points.shape[0]}, {self.config.action_dim}), got {tuple(state.shape)}")
        return points, state, task_id

    def _roles(self, obs: Mapping[str, torch.Tensor], points: torch.Tensor) -> torch.Tensor | None:
        """``obs["roles"] (B, N)`` (each point's role, 0 none) where the object head's tokens are roles,
        the alike objects' split by position in the tasks that have them (``objects.alike``), else None.
        points: (B, N, C) data units, xyz metres first."""
        if self.objects.source != "roles":
            return None
        if obs.get("roles") is None:
            raise KeyError("observation: missing 'roles' (each point's role), needed by policy.model.objects.source 'roles'")
        roles = torch.as_tensor(obs["roles"], device=self.device)
        if not self.objects.alike:
            return roles
        roles, task = roles.long().clone(), torch.as_tensor(obs["task_id"], device=self.device).reshape(-1)
        for name, group in self.objects.alike.items():
            rows = task == registered_task_id(name)
            if rows.any():
                roles[rows] = split_alike(points[rows, :, :3].float(), roles[rows], group.roles, group.by)
        return roles

    def _check_anchors(self, anchors: torch.Tensor) -> None:
        want = (self.config.horizon, self.config.action_dim)
        if anchors.ndim != 3 or tuple(anchors.shape[1:]) != want:
            raise ValueError(f"anchors: expected (B, {want[0]}, {want[1]}), got {tuple(anchors.shape)}")
