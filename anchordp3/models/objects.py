"""Critical-object tokens: the segmented cloud summarised as K object clusters, for the policy.

The first move of a task (home to the pre-grasp) is decided by where one object lies. A
max-pooled point encoder has to learn to read that position off 1,024 points from a few dozen
scenes per task, and measured on the recipe's data it does not (9 cm off on unseen scenes), while
a linear fit on the centroids of the two critical clusters finds the pre-grasp within 0.3 cm. So
the policy can be given those clusters directly:

1. the critical points are those whose probability (the segmenter's, or the simulator's label)
   is above ``threshold``;
2. K seeds are picked deterministically among an even subsample of the points (at most
   ``SEED_CANDIDATES``), each the critical one that maximises ``density x distance to the seeds
   so far`` (density: critical neighbours within ``SEED_RADIUS``), so a stray mislabelled point
   never seeds a cluster;
3. a few Lloyd iterations (k-means) assign every critical point to its nearest centre, distances
   measured with heights stretched ``z_weight`` times: a held object carried over the scale is then
   one cluster and the scale another (plain k-means cuts the wide pile across instead, measured 3.6
   cm median centroid error in those states; ``z_weight`` 5: 0.35 cm, other states unchanged);
4. clusters are ordered by size, largest first, and each becomes a token of ``TOKEN_FEATURES``
   numbers: its centroid, its centroid's offset from each end effector, its spread, its top and its
   share of the critical points (positions in metres x ``POSITION_SCALE``); with ``orientation``,
   two more: the direction of its points' principal axis in the table plane (below).

The per-axis spread cannot tell an object turned +30 degrees from one turned -30 degrees, and the
yaw of an elongated object decides its grasp (a mouse grasped 30 degrees off is missed). The
orientation features are the cluster's xy second moments, ``((cxx - cyy), 2 cxy) / (cxx + cyy)``:
``anisotropy x (cos 2θ, sin 2θ)`` for a principal axis at yaw θ (π-periodic, as the axis is), zero
for a round object, turning by 2φ when the scene turns by φ and unchanged when it moves. With
``half_angle``, two more: the same axis as anisotropy x (cos θ, sin θ), which a top-down grasp's
finger direction follows linearly. With ``heading``, two more, the last: the axis as a direction,
anisotropy x (cos h, sin h) with h the branch of θ pointing away from the object's tall part (a
shoe's toe, away from its heel's collar; ``heading_axis``): where the axis is a line, this is an
arrow, which a place that turns the object to a heading needs.

Where the points carry roles (the segmenter's role head, or the simulator's labels: a point's
object's place in the task's ``critical_objects()``), steps 1-4 give way to the roles: token j is
role j + 1's points, in the same place in every frame and scene (k-means tokens of three alike
blocks come out in another order each time, ladder rung D3). Objects that look alike (three
bottles) get their roles at random from a segmenter, so their pooled points are clustered again and
ordered by their distance from another object (``split_alike``: from the dustbin).

Everything is batched tensor arithmetic (no randomness, no Python loop over samples), so it runs
inside the policy's forward pass, after augmentation, at training and at inference alike.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from anchordp3.schemas.state import ARMS, StateLayout

POSITION_SCALE = 2.0  # metres -> about [-1, 1] over the workspace, as the gripper offsets
SPREAD_SCALE = 10.0  # a cluster spread of 2-10 cm -> 0.2-1
HELD_RADIUS = 0.06  # metres: an object whose centroid lies this near a closed gripper is held by it
GRIPPER_CLOSED = 0.9  # normalised opening (1 open) below which a gripper counts as closed
SEED_RADIUS = 0.02  # metres: neighbours counted for a seed's density
SEED_CANDIDATES = 256  # points (an even subsample) considered as seeds
LLOYD_ITERATIONS = 6
TOKEN_FEATURES = 3 + 3 * len(ARMS) + 3 + 1 + 1
ORIENTATION_FEATURES = 2  # anisotropy x (cos 2θ, sin 2θ) of a cluster's principal axis in the table plane
HEADING_FEATURES = 2  # anisotropy x (cos h, sin h): the axis as an arrow away from the object's tall part
TOP_DOWN_TOLERANCE = 0.15  # rot6 entries: a pose within about 8 degrees of pointing straight down counts as top-down


def token_features(orientation: bool = False, half_angle: bool = False, heading: bool = False) -> int:
    """Numbers per object token: ``TOKEN_FEATURES``, plus ``ORIENTATION_FEATURES`` with ``orientation``,
    as many again with ``half_angle`` and ``HEADING_FEATURES`` with ``heading`` (both need ``orientation``)."""
    return (TOKEN_FEATURES + ORIENTATION_FEATURES * (int(orientation) + int(orientation and half_angle))
            + HEADING_FEATURES * int(orientation and heading))


def cluster_critical_points(xyz: torch.Tensor, critical: torch.Tensor, k: int,
                            z_weight: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """K-means of each cloud's critical points with deterministic, outlier-robust seeds.

    xyz: (B, N, 3) metres; critical: (B, N) bool; k >= 1; z_weight: heights count this many times
    over in every distance (seeds' density and spread, Lloyd's assignments; module docstring).
    Returns ``assign (B, N) long`` in [0, k) (meaningless where not critical) and ``centres (B, k, 3)``
    in metres, ordered by cluster size, largest first; an empty cluster's centre is its seed."""
    stretch = torch.tensor([1.0, 1.0, float(z_weight)], dtype=xyz.dtype, device=xyz.device)
    xyz = xyz * stretch
    b, n, _ = xyz.shape
    weight = critical.to(xyz.dtype)
    cand = torch.arange(0, n, -(-n // SEED_CANDIDATES), device=xyz.device)  # an even subsample, whatever the order
    cxyz, cw = xyz[:, cand], weight[:, cand]  # (B, m, 3), (B, m)
    near = (torch.cdist(cxyz, cxyz) < SEED_RADIUS).to(xyz.dtype)
    density = (near * cw[:, None, :]).sum(-1) * cw  # (B, m): 0 for non-critical candidates
    far = torch.full_like(density, 1.0)
    seeds = []
    for _ in range(k):
        pick = torch.argmax(density * far, dim=1)  # (B,)
        seed = cxyz[torch.arange(b), pick]  # (B, 3)
        seeds.append(seed)
        d = (cxyz - seed[:, None, :]).norm(dim=-1)
        far = d if len(seeds) == 1 else torch.minimum(far, d)
    centres = torch.stack(seeds, dim=1)  # (B, k, 3)
    for _ in range(LLOYD_ITERATIONS):
        assign = torch.cdist(xyz, centres).argmin(dim=-1)  # (B, N)
        onehot = torch.nn.functional.one_hot(assign, k).to(xyz.dtype) * weight[..., None]  # (B, N, k)
        count = onehot.sum(1)  # (B, k)
        mean = torch.einsum("bnk,bnc->bkc", onehot, xyz) / count.clamp(min=1)[..., None]
        centres = torch.where(count[..., None] > 0, mean, centres)
    assign = torch.cdist(xyz, centres).argmin(dim=-1)
    count = (torch.nn.functional.one_hot(assign, k).to(xyz.dtype) * weight[..., None]).sum(1)
    order = torch.sort(-count, dim=1, stable=True).indices  # (B, k), largest first
    rank = torch.argsort(order, dim=1)  # old cluster id -> its rank
    return torch.gather(rank, 1, assign), torch.gather(centres, 1, order[..., None].expand(-1, -1, 3)) / stretch


def split_alike(xyz: torch.Tensor, roles: torch.Tensor, alike: Sequence[int], by: int) -> torch.Tensor:
    """``roles`` with the points of the ``alike`` roles (objects that look alike, whose points a
    segmenter labels with any of their roles) pooled and split again by position: the pooled points'
    ``len(alike)`` clusters (``cluster_critical_points``) take the roles of ``alike`` in order of their
    centroid's distance in the table plane from the centroid of role ``by``'s points, nearest first
    (largest first where role ``by`` has no points; an empty cluster last).

    xyz: (B, N, 3) metres; roles: (B, N) integer, 0 none -> (B, N) long."""
    roles = roles.long()
    group = torch.tensor(list(alike), dtype=torch.long, device=roles.device)
    pooled = torch.isin(roles, group)
    k = len(group)
    assign, centres = cluster_critical_points(xyz, pooled, k)
    count = (torch.nn.functional.one_hot(assign, k) * pooled[..., None]).sum(1)  # (B, k)
    ref = roles == by
    centre = torch.einsum("bn,bnc->bc", ref.to(xyz.dtype), xyz) / ref.sum(1).clamp(min=1)[:, None].to(xyz.dtype)
    dist = (centres[..., :2] - centre[:, None, :2]).norm(dim=-1) * ref.any(1)[:, None]  # 0s keep the size order
    dist = torch.where(count > 0, dist, torch.full_like(dist, float("inf")))
    rank = torch.argsort(torch.sort(dist, dim=1, stable=True).indices, dim=1)  # cluster -> its place in the order
    return torch.where(pooled, group[torch.gather(rank, 1, assign)], roles)


def object_tokens(points: torch.Tensor, state: torch.Tensor, layout: StateLayout, k: int,
                  threshold: float = 0.5, orientation: bool = False, z_weight: float = 1.0,
                  roles: torch.Tensor | None = None, half_angle: bool = False, heading: bool = False) -> torch.Tensor:
    """The K critical-object tokens of each observation.

    points: (B, N, C) in data units, xyz (metres) first and the critical probability last;
    state: (B, D) in data units. Returns (B, k, token_features(orientation)) float32: per object
    its centroid, the centroid minus each arm's end effector (``ARMS`` order), the per-axis spread,
    the top (highest z) minus the centroid's z, all x their scales, its share of the critical
    points and, with ``orientation``, its principal axis in the table plane as anisotropy x
    (cos 2θ, sin 2θ) (module docstring), and with ``half_angle`` also anisotropy x (cos θ, sin θ)
    (``half_angle_axis``), and with ``heading`` last the axis as an arrow away from the object's tall
    part (``heading_axis``). The objects: without ``roles``, the k clusters of the
    points whose probability is above ``threshold``, largest first (``cluster_critical_points``,
    ``z_weight`` as there); with ``roles (B, N)`` integer (0 none), token j is the points of role
    j + 1, so each token keeps its object from frame to frame and scene to scene. An object
    without points gives a zero token."""
    xyz = points[..., :3].float()
    if roles is None:
        critical = points[..., -1] > threshold
        assign, _ = cluster_critical_points(xyz, critical, k, z_weight)
        member = torch.nn.functional.one_hot(assign, k).float() * critical[..., None].float()  # (B, N, k)
    else:
        roles = roles.to(xyz.device).long()
        critical = roles > 0
        member = (roles[..., None] == torch.arange(1, k + 1, device=xyz.device)).float()  # (B, N, k)
    count = member.sum(1)  # (B, k)
    safe = count.clamp(min=1)[..., None]
    centroid = torch.einsum("bnk,bnc->bkc", member, xyz) / safe
    own = torch.einsum("bnk,bkc->bnc", member, centroid)  # each point's own centroid (0 if not critical)
    spread = (torch.einsum("bnk,bnc->bkc", member, (xyz - own) ** 2) / safe).sqrt()
    top = torch.where(member.bool(), xyz[..., 2:3].expand(-1, -1, k), torch.full_like(member, -1e3)).amax(1)  # (B, k)
    ee = [state[:, None, layout.ee_xyz(arm)].float() for arm in ARMS]
    present = (count > 0).float()[..., None]
    parts = [
        centroid * POSITION_SCALE,
        *[(centroid - e) * POSITION_SCALE for e in ee],
        spread * SPREAD_SCALE,
        ((top - centroid[..., 2]) * SPREAD_SCALE)[..., None],
        (count / critical.float().sum(1, keepdim=True).clamp(min=1))[..., None],
    ]
    if orientation:
        axis = principal_axis(xyz - own, member, safe)
        parts += [axis, half_angle_axis(axis)] if half_angle else [axis]
        if heading:
            parts.append(heading_axis(xyz - own, member, (top - centroid[..., 2]) / 2, axis))
    return torch.cat(parts, dim=-1) * present


def principal_axis(centred: torch.Tensor, member: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """Each cluster's principal axis in the table plane: ``centred (B, N, 3)`` points minus their
    own cluster's centroid (metres), ``member (B, N, k)`` 0/1, ``count (B, k, 1)`` members (at
    least 1) -> ``(B, k, 2)``: ``((cxx - cyy), 2 cxy) / (cxx + cyy)`` of the xy second moments,
    i.e. anisotropy (0 round, 1 a line) x (cos 2θ, sin 2θ)."""
    x, y = centred[..., 0], centred[..., 1]
    moments = torch.stack([x * x, y * y, x * y], dim=-1)  # (B, N, 3)
    cxx, cyy, cxy = (torch.einsum("bnk,bnc->bkc", member, moments) / count).unbind(-1)
    total = (cxx + cyy).clamp(min=1e-10)
    return torch.stack([(cxx - cyy) / total, 2 * cxy / total], dim=-1)


def half_angle_axis(axis: torch.Tensor) -> torch.Tensor:
    """``axis (..., 2)`` = anisotropy x (cos 2θ, sin 2θ) (``principal_axis``) -> anisotropy x (cos θ,
    sin θ) with θ in (-90°, 90°]: the axis itself rather than its double angle. A finger yaw that
    turns with the object (θ + c) is then linear in it over the whole range, with its one jump at
    θ = ±90° where the axis's own branch cut lies (a phone lying at -89° and at +89° is the same
    phone, grasped by fingers half a turn apart)."""
    anisotropy = axis.norm(dim=-1, keepdim=True)
    theta = torch.atan2(axis[..., 1], axis[..., 0]) / 2
    return anisotropy * torch.stack([theta.cos(), theta.sin()], dim=-1)


def heading_axis(centred: torch.Tensor, member: torch.Tensor, cut: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """Each cluster's principal axis as an arrow pointing away from its tall part: ``centred (B, N,
    3)`` points minus their own cluster's centroid (metres), ``member (B, N, k)`` 0/1, ``cut (B, k)``
    metres above the centroid (half-way to the top), ``axis (B, k, 2)`` (``principal_axis``) ->
    ``(B, k, 2)`` anisotropy x (cos h, sin h), h = θ or θ + π: of the two, the one opposite the
    side where the points above ``cut`` lie along the axis (weighted by how far above). A shoe's
    collar rises at its heel, so h runs heel to toe (measured on the shoes' carries with the
    segmenter's roles: the right half turn in 96 % of frames, against 91 % from the correlation of
    height and position over all points). A flat or symmetric object's arrow is arbitrary."""
    anisotropy = axis.norm(dim=-1, keepdim=True)
    theta = torch.atan2(axis[..., 1], axis[..., 0]) / 2  # (B, k)
    u = torch.stack([theta.cos(), theta.sin()], dim=-1)  # (B, k, 2)
    weight = member * torch.relu(centred[..., 2:3] - cut[:, None, :])  # (B, N, k): 0 off the cluster
    along = torch.einsum("bnc,bkc->bnk", centred[..., :2], u)  # each point's position along each cluster's axis
    tall = (weight * along).sum(1)  # (B, k): > 0 where the tall part lies along +u
    return anisotropy * torch.where(tall > 0, -1.0, 1.0)[..., None] * u


def token_heading(tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each token's heading from its last ``HEADING_FEATURES`` (``heading_axis``; the tokens were made
    with ``heading``): ``tokens (B, k, features)`` -> the heading ``(B, k)`` radians in (-π, π] and
    the anisotropy ``(B, k)``."""
    arrow = tokens[..., -HEADING_FEATURES:].float()
    return torch.atan2(arrow[..., 1], arrow[..., 0]), arrow.norm(dim=-1)


def token_yaw(tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each token's principal axis in the table plane from its orientation features (``principal_axis``,
    right after the ``TOKEN_FEATURES``): ``tokens (B, k, token_features(orientation=True, ...))`` ->
    its yaw θ ``(B, k)`` radians in (-π/2, π/2] and its anisotropy ``(B, k)`` (0 round, 1 a line)."""
    axis = tokens[..., TOKEN_FEATURES:TOKEN_FEATURES + ORIENTATION_FEATURES].float()
    return torch.atan2(axis[..., 1], axis[..., 0]) / 2, axis.norm(dim=-1)


def finger_yaw(rot6: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The finger direction's yaw of end-effector rotations ``rot6 (..., 6)`` (``R[:3, :2]`` row-major,
    ``StateLayout.ee_rot6``) -> ``yaw (...)`` radians and whether the pose points straight down
    ``(...)`` bool (within about 8 degrees). A top-down pose of finger yaw ψ has ``R[:, 1] = (cos ψ,
    sin ψ, 0)`` and ``R[:, 0] = (-sin ψ, cos ψ, 0)`` (``top_down_rot6``)."""
    r00, r01, r10, r11, r20, r21 = rot6.float().unbind(-1)
    down = (r20.abs() < TOP_DOWN_TOLERANCE) & (r21.abs() < TOP_DOWN_TOLERANCE) & \
        ((r00 + r11).abs() < TOP_DOWN_TOLERANCE) & ((r10 - r01).abs() < TOP_DOWN_TOLERANCE)
    return torch.atan2(r11, r01), down


def top_down_rot6(yaw: torch.Tensor) -> torch.Tensor:
    """``yaw (...)`` radians -> the rotation ``(..., 6)`` (``R[:3, :2]`` row-major) of a pose pointing
    straight down with its fingers opening along ``(cos yaw, sin yaw, 0)``."""
    c, s = yaw.cos(), yaw.sin()
    zero = torch.zeros_like(c)
    return torch.stack([-s, c, c, s, zero, zero], dim=-1)


def nearest_branch(yaw: torch.Tensor, preferred: torch.Tensor) -> torch.Tensor:
    """Of the finger yaws ``yaw + n π`` (a parallel gripper closes alike at either), the one
    nearest ``preferred``, radians, elementwise."""
    return yaw + torch.pi * torch.round((preferred - yaw) / torch.pi)


def token_gripper_offsets(tokens: torch.Tensor) -> torch.Tensor:
    """Each token's centroid minus each arm's end effector, back in metres: ``tokens (B, k,
    token_features(orientation))`` -> ``(B, k, len(ARMS), 3)`` (0 for an absent object)."""
    return tokens[..., 3:3 + 3 * len(ARMS)].unflatten(-1, (len(ARMS), 3)) / POSITION_SCALE


def token_centroids(tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``tokens (B, k, features)`` -> each token's centroid ``(B, k, 3)`` metres and whether the
    object is present ``(B, k)`` bool (an absent object's token is all zeros)."""
    return tokens[..., :3] / POSITION_SCALE, tokens.abs().sum(-1) > 0


def nearest_token_gates(positions: torch.Tensor, tokens: torch.Tensor, radius: float,
                        exclude: torch.Tensor | None = None) -> torch.Tensor:
    """Which object each end-effector position belongs to, as gate targets: ``positions (B, H,
    arms, 3)`` metres, ``tokens (B, k, features)`` -> ``(B, H, arms, k)`` float32, 1 for the present
    token whose centroid lies nearest the position when it is within ``radius`` metres, else 0
    (a position far from every object, e.g. an arm resting at home, belongs to none).
    exclude: ``(B, arms, k)``, nonzero where an arm's positions may not belong to that token."""
    centroids, present = token_centroids(tokens.float())
    d = torch.cdist(positions.float().flatten(1, 2), centroids).unflatten(1, positions.shape[1:3])  # (B, H, arms, k)
    d = d.masked_fill(~present[:, None, None, :], float("inf"))
    if exclude is not None:
        d = d.masked_fill(exclude[:, None].bool(), float("inf"))
    near, which = d.min(-1)
    return torch.nn.functional.one_hot(which, tokens.shape[1]).float() * (near < radius)[..., None].float()


def held_tokens(tokens: torch.Tensor, grippers: torch.Tensor) -> torch.Tensor:
    """Which object each arm holds: ``tokens (B, k, features)``, ``grippers (B, arms)`` normalised
    openings (``ARMS`` order) -> ``(B, arms, k)`` float32, 1 for the present token whose centroid is
    nearest the arm's end effector when within ``HELD_RADIUS`` and the gripper is closed
    (below ``GRIPPER_CLOSED``), else 0."""
    offsets = token_gripper_offsets(tokens.float())  # (B, k, arms, 3)
    _, present = token_centroids(tokens.float())
    d = offsets.norm(dim=-1).transpose(1, 2).masked_fill(~present[:, None, :], float("inf"))  # (B, arms, k)
    near, which = d.min(-1)
    held = (near < HELD_RADIUS) & (grippers.float() < GRIPPER_CLOSED)
    return torch.nn.functional.one_hot(which, tokens.shape[1]).float() * held[..., None].float()


def pair_offsets(tokens: torch.Tensor) -> torch.Tensor:
    """The offsets that ``held_offsets`` gating chooses among: ``tokens (B, k, features)`` ->
    ``(B, k * k, arms, 3)`` metres, entry ``k_obj * k + j``: token ``k_obj``'s centroid minus the
    arm's end effector where ``j == k_obj``, minus held token ``j``'s centroid where ``j != k_obj``
    (the same for both arms; 0 where either object is absent)."""
    b, k = tokens.shape[:2]
    to_ee = token_gripper_offsets(tokens.float())  # (B, k, arms, 3)
    centroids, present = token_centroids(tokens.float())
    between = (centroids[:, :, None] - centroids[:, None, :]) * (present[:, :, None] & present[:, None, :])[..., None]  # (B, k, k, 3)
    table = between[:, :, :, None, :].expand(-1, -1, -1, to_ee.shape[2], -1).clone()  # (B, k, k, arms, 3)
    idx = torch.arange(k, device=tokens.device)
    table[:, idx, idx] = to_ee
    return table.reshape(b, k * k, to_ee.shape[2], 3)


class ObjectTokenEncoder(torch.nn.Module):
    """The K tokens (concatenated, largest cluster first) -> an MLP feature for the FiLM condition.

    tokens: (B, k, features) -> (B, out_dim); ``features`` is ``token_features(orientation)``."""

    def __init__(self, k: int, hidden_dim: int = 128, out_dim: int = 64, features: int = TOKEN_FEATURES) -> None:
        super().__init__()
        self.net = torch.nn.Sequential(
            torch.nn.Linear(k * features, hidden_dim), torch.nn.ReLU(inplace=True),
            torch.nn.Linear(hidden_dim, out_dim), torch.nn.LayerNorm(out_dim))
        self.out_dim = out_dim

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        return self.net(tokens.flatten(1))
