"""Training-time augmentation of policy samples that keeps them physically consistent.

``translate_scene`` moves the whole scene, robot included, by ``delta``: the cloud's xyz and the
end-effector positions of the state and of every label anchor shift together, while joint angles
and grippers stay as they are (a robot whose base moved with the scene makes the same motion).
The policy thus sees each demonstration at many nearby places and learns that where it grasps
follows where the object is, which a few dozen demonstrations alone do not pin down.

``jitter_grippers`` moves only the end-effector positions of the *state* (labels unchanged): the
policy sees itself a little off the demonstrated path and learns to reach the same anchor from
there, as in closed loop after an imprecise move (noise injection, as DART does at collection).
"""

from __future__ import annotations

import torch

from anchordp3.schemas.state import ARMS, StateLayout


def translate_scene(points: torch.Tensor, state: torch.Tensor, anchors: torch.Tensor, delta: torch.Tensor,
                    layout: StateLayout) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Shift ``points (B, N, C)`` (xyz first), ``state (B, D)`` and ``anchors (B, H, D)`` by
    ``delta (B, 3)`` metres. Returns new tensors; the inputs are left unchanged."""
    points, state, anchors = points.clone(), state.clone(), anchors.clone()
    points[..., :3] += delta[:, None, :]
    for arm in ARMS:
        xyz = layout.ee_xyz(arm)
        state[:, xyz] += delta
        anchors[:, :, xyz] += delta[:, None, :]
    return points, state, anchors


def random_translation(batch: int, extent: tuple[float, float, float], generator: torch.Generator | None = None) -> torch.Tensor:
    """Deltas ``(batch, 3)`` uniform in ``[-extent, extent]`` per axis, metres."""
    u = torch.rand((batch, 3), generator=generator) * 2 - 1
    return u * torch.tensor(extent, dtype=torch.float32)


def jitter_grippers(state: torch.Tensor, std: float, layout: StateLayout, generator: torch.Generator | None = None) -> torch.Tensor:
    """``state (B, D)`` with each arm's end-effector xyz moved by Gaussian noise of ``std`` metres
    per axis (joints and grippers unchanged). Returns a new tensor."""
    state = state.clone()
    for arm in ARMS:
        xyz = layout.ee_xyz(arm)
        state[:, xyz] += (torch.randn((len(state), 3), generator=generator) * std).to(state.device, state.dtype)
    return state
