"""Anchor stage: anchor (keypose) timesteps of a kept episode and its frame plan.

Anchors are the terminal states of the expert's atomic operations. They come either from the
expert's own operation tags (``symbolic``) or, for demonstrations without operation labels, from
motion alone (``kinematic``: where the robot comes to rest and starts moving again, a gripper
motion included). The 32-d label of anchor ``t`` is the measured state ``states[t]`` with the
grippers as commanded by ``actions[t - 1]`` (a gripper closed on an object is commanded 0 while its
fingers rest apart).

The frame plan draws ``frames_per_interval`` random steps inside each interval
``[a_{i-1}, a_i)`` between consecutive anchors (``a_{-1} = 0``); each frame is labelled with the
next H anchors ``a_i, a_{i+1}, …`` padded with the last. A share of them also gets a DAgger frame
at the same step: the arm is sent to a wrong pose (near its next target, or over a wrong object),
observed, and restored; its label is the same correct next anchors.

The dense baseline (``plan: dense``, DP3 on RoboTwin) instead takes a frame every
``dense.frame_stride`` control steps, labelled with the next H commanded actions ``actions[t],
actions[t + s], …`` (``s = dense.action_stride``, padded with the last): each label is the 32-d
state reached after that command, with its joints and grippers as commanded. No DAgger frames.

Output per episode: ``plans/<task>/<seed:06d>.parquet``, one row per frame (see ``PLAN_COLUMNS``),
with the anchor list in the file's metadata.
"""

from __future__ import annotations

import io
import json
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from anchordp3.schemas.episode import EpisodeRecord
from anchordp3.schemas.stages import AnchorsConfig, KinematicTagConfig
from anchordp3.schemas.state import ARMS, StateLayout
from anchordp3.stages.files import atomic_write_bytes, plan_file
from anchordp3.stages.rollout import load_episode

PLAN_COLUMNS = {
    "task": "task name",
    "seed": "episode seed",
    "frame": "frame index within the episode's plan",
    "t": "control step observed (state index)",
    "kind": "expert, rest (at rest at the previous anchor) or dagger",
    "next_anchor": "index of the first label anchor in the episode's anchor list",
    "next_names": "keypose names of the H label anchors, comma-separated",
    "anchors": "H x 32 label states, row-major, float32",
    "dagger_mode": "near_target or wrong_affordance (DAgger frames only)",
    "dagger_arm": "arm sent to the wrong pose (DAgger frames only)",
    "dagger_seed": "seed of the perturbation draws (DAgger frames only)",
}


@dataclass(frozen=True)
class Anchors:
    """An episode's anchors: ``t (A,) int64`` state indices, keypose ``names``, moving ``arms``
    (left, right or both) and ``states (A, 32) float64`` labels."""

    t: np.ndarray
    names: list[str]
    arms: list[str]
    states: np.ndarray


def anchor_states(states: np.ndarray, actions: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Labels of anchors at steps ``t``: ``states[t]`` with grippers from ``actions[t - 1]``.

    states: (T + 1, D) measured; actions: (T, J) commanded; t: (A,) ints in 1..T. Returns (A, D)."""
    layout = StateLayout.of_length(states.shape[-1])
    out = states[t].astype(np.float64).copy()
    for arm in ARMS:
        g = layout.gripper(arm)
        out[:, g] = actions[np.maximum(t - 1, 0), g]
    return out


def horizon_indices(start: int, horizon: int, n: int, stride: int = 1) -> np.ndarray:
    """Indices ``start, start + stride, …`` (``horizon`` of them) into a sequence of ``n``, padded
    with the last: the label positions of a frame. Returns (horizon,) int64."""
    return np.minimum(start + stride * np.arange(horizon), n - 1)


def commanded_states(states: np.ndarray, actions: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Dense labels: the state ``states[s + 1]`` reached by command ``actions[s]``, with every
    joint and gripper as commanded. steps: (L,) ints in 0..T-1. Returns (L, D) float64."""
    layout = StateLayout.of_length(states.shape[-1])
    out = states[steps + 1].astype(np.float64).copy()
    out[:, :layout.joint_dim] = actions[steps, :layout.joint_dim]
    return out


def kinematic_anchors(states: np.ndarray, actions: np.ndarray | None = None,
                      cfg: KinematicTagConfig = KinematicTagConfig()) -> np.ndarray:
    """Anchor steps from motion alone (no operation labels), and the final state of the episode.

    With the commanded ``actions (T, J)`` (what teleoperation and scripted data record), an anchor
    is the last step of each period in which the commanded joints and grippers hold still, i.e.
    where the next motion is commanded. From measured ``states (T + 1, D)`` alone, it is the
    stillest state of each rest period (deceleration turning into re-acceleration); a gripper
    pressing on an object hides its command there, so this is less exact.

    Returns (A,) int64 state indices, increasing."""
    layout = StateLayout.of_length(states.shape[-1])
    joints = np.concatenate([np.arange(layout.dim)[layout.qpos(a)] for a in ARMS])
    grippers = [layout.gripper(a) for a in ARMS]
    if actions is not None:
        signal = np.concatenate([actions[:1], actions], axis=0)  # signal[i] = command in force before state i
        joint_thr = grip_thr = cfg.rest_command_change
    else:
        signal, joint_thr, grip_thr = states, cfg.rest_joint_speed, cfg.rest_gripper_speed
    d = np.abs(np.diff(signal, axis=0))  # (T, ·): change from index i to i + 1
    activity = np.maximum(d[:, joints].max(axis=1) / joint_thr, d[:, grippers].max(axis=1) / grip_thr)
    moving = activity > 1.0
    out, t, n = [], 0, len(moving)
    seen_motion = False
    while t < n:
        if moving[t]:
            seen_motion = True
            t += 1
            continue
        start = t
        while t < n and not moving[t]:
            t += 1
        if seen_motion and t < n and t - start >= cfg.min_rest_steps:
            out.append(t if actions is not None else start + int(np.argmin(activity[start:t])) + 1)
    if n and seen_motion:
        out.append(n)
    return np.asarray(out, dtype=np.int64)


def moving_arm(states: np.ndarray, t0: int, t1: int) -> str:
    """Which arm moved between state indices ``t0`` and ``t1``: left, right or both."""
    layout = StateLayout.of_length(states.shape[-1])
    travel = {a: float(np.abs(np.diff(states[t0:t1 + 1, layout.qpos(a)], axis=0)).sum()
                       + np.abs(np.diff(states[t0:t1 + 1, layout.gripper(a)])).sum()) for a in ARMS}
    hi = max(travel.values())
    active = [a for a in ARMS if travel[a] > 0.25 * hi]
    return active[0] if len(active) == 1 else "both"


def match_anchors(pred: np.ndarray, true: np.ndarray, tol: int = 3) -> tuple[int, int, int]:
    """Greedy one-to-one matching within ``tol`` steps, in time order.

    Returns (matched, len(pred), len(true)): precision = matched / len(pred), recall = matched / len(true)."""
    used = np.zeros(len(true), dtype=bool)
    matched = 0
    for p in pred:
        cand = np.where(~used & (np.abs(true - p) <= tol))[0]
        if len(cand):
            used[cand[np.argmin(np.abs(true[cand] - p))]] = True
            matched += 1
    return matched, len(pred), len(true)


def episode_anchors(record: EpisodeRecord, arrays: dict[str, np.ndarray], cfg: AnchorsConfig) -> Anchors:
    """The anchors of a kept episode from the configured source."""
    states, actions = arrays["states"], arrays["actions"]
    if cfg.source == "symbolic":
        t = np.asarray(arrays["anchor_t"], dtype=np.int64)
        names = [str(n) for n in arrays["anchor_name"]]
        arms = [a.arm for a in record.anchors] if len(record.anchors) == len(t) else [None] * len(t)
    else:
        t = kinematic_anchors(states, actions if cfg.kinematic.use_commands else None, cfg.kinematic)
        names = [f"K{i}" for i in range(len(t))]
        arms = [None] * len(t)
    if len(t) == 0:
        raise ValueError(f"episode {record.episode_id} has no anchors")
    prev = np.concatenate([[0], t[:-1]])
    arms = [a or moving_arm(states, int(p), int(q)) for a, p, q in zip(arms, prev, t)]
    return Anchors(t=t, names=names, arms=arms, states=anchor_states(states, actions, t))


def _rng(cfg: AnchorsConfig, task: str, seed: int, salt: str) -> np.random.Generator:
    return np.random.default_rng([cfg.seed, zlib.crc32(task.encode()), int(seed), zlib.crc32(salt.encode())])


def reached(state: np.ndarray, anchor_state: np.ndarray, tol: float) -> bool:
    """Whether measured ``state (D,)`` has reached the measured anchor state ``anchor_state (D,)``:
    every arm joint within ``tol`` radians and every gripper within ``GRIPPER_REACHED``."""
    layout = StateLayout.of_length(state.shape[-1])
    for arm in ARMS:
        if np.abs(state[layout.qpos(arm)] - anchor_state[layout.qpos(arm)]).max() >= tol:
            return False
        if abs(float(state[layout.gripper(arm)] - anchor_state[layout.gripper(arm)])) >= GRIPPER_REACHED:
            return False
    return True


GRIPPER_REACHED = 0.05  # largest normalised gripper difference at which an anchor counts as reached


def next_unreached(states: np.ndarray, anchor_t: np.ndarray, t: int, i: int, tol: float) -> int:
    """The first anchor index ``j >= i`` that the robot at step ``t`` has not reached yet (the
    last anchor when it has reached them all): what a decision taken at ``t`` should aim for."""
    j = i
    while j < len(anchor_t) - 1 and reached(states[t], states[anchor_t[j]], tol):
        j += 1
    return j


def plan_frames(task: str, seed: int, anchors: Anchors, cfg: AnchorsConfig, states: np.ndarray | None = None) -> pa.Table:
    """The frame plan of one episode as a table with ``PLAN_COLUMNS`` (rows in time order,
    each DAgger frame right after the expert frame of the same step).

    Per interval ``[a_{i-1}, a_i)``: with ``rest_frames`` its start (the robot at rest at anchor
    ``i - 1``, kind ``rest``), and ``frames_per_interval`` random steps after it (kind ``expert``).
    With ``relabel_reached`` and the measured ``states (T + 1, D)``, a frame that has already
    reached anchor ``i`` is labelled from the first anchor it has not reached."""
    rng = _rng(cfg, task, seed, "frames")
    H, A = cfg.horizon, len(anchors.t)
    relabel = cfg.relabel_reached and states is not None
    rows: list[dict] = []
    start = 0
    for i, end in enumerate(anchors.t.tolist()):
        steps = np.arange(start, end)
        first, start = int(steps[0]) if len(steps) else start, end
        if len(steps) == 0:
            continue
        pool = steps[1:] if cfg.rest_frames else steps
        picks = np.sort(rng.choice(pool, size=min(cfg.frames_per_interval, len(pool)), replace=False)) if len(pool) else pool
        frames = ([(first, "rest")] if cfg.rest_frames else []) + [(int(t), "expert") for t in picks.tolist()]
        for t, kind in frames:
            j = next_unreached(states, anchors.t, t, i, cfg.reached_tolerance) if relabel else i
            label_idx = horizon_indices(j, H, A)
            label = anchors.states[label_idx].astype(np.float32).reshape(-1)
            names = ",".join(anchors.names[k] for k in label_idx)
            base = dict(task=task, seed=int(seed), t=t, next_anchor=j, next_names=names, anchors=label)
            rows.append(dict(base, kind=kind, dagger_mode="", dagger_arm="", dagger_seed=0))
            if rng.random() < cfg.dagger.fraction:
                mode = "wrong_affordance" if rng.random() < cfg.dagger.wrong_affordance_prob else "near_target"
                arm = anchors.arms[j] if anchors.arms[j] != "both" else str(rng.choice(ARMS))
                rows.append(dict(base, kind="dagger", dagger_mode=mode, dagger_arm=arm, dagger_seed=int(rng.integers(2**31))))
    return _plan_table(rows, anchors, cfg)


def plan_dense_frames(task: str, seed: int, anchors: Anchors, actions: np.ndarray, states: np.ndarray,
                      cfg: AnchorsConfig) -> pa.Table:
    """The dense baseline's frame plan: a frame every ``dense.frame_stride`` steps of the
    ``actions (T, J)`` episode, labelled with the next H commanded actions as 32-d states."""
    H, T, d = cfg.horizon, len(actions), cfg.dense
    rows: list[dict] = []
    for t in range(0, T, d.frame_stride):
        steps = horizon_indices(t, H, T, d.action_stride)
        label = commanded_states(states, actions, steps).astype(np.float32).reshape(-1)
        nxt = int(np.searchsorted(anchors.t, t, side="right"))
        rows.append(dict(task=task, seed=int(seed), t=int(t), next_anchor=min(nxt, len(anchors.t) - 1),
                         next_names=",".join(f"step{s}" for s in steps.tolist()), anchors=label,
                         kind="expert", dagger_mode="", dagger_arm="", dagger_seed=0))
    return _plan_table(rows, anchors, cfg)


def _plan_table(rows: list[dict], anchors: Anchors, cfg: AnchorsConfig) -> pa.Table:
    H = cfg.horizon
    for k, r in enumerate(rows):
        r["frame"] = k
    D = anchors.states.shape[1]
    schema = pa.schema([
        ("task", pa.string()), ("seed", pa.int64()), ("frame", pa.int32()), ("t", pa.int32()), ("kind", pa.string()),
        ("next_anchor", pa.int32()), ("next_names", pa.string()), ("anchors", pa.list_(pa.float32(), H * D)),
        ("dagger_mode", pa.string()), ("dagger_arm", pa.string()), ("dagger_seed", pa.int64()),
    ])
    table = pa.Table.from_pylist([{k: r[k] for k in schema.names} for r in rows], schema=schema)
    meta = {"anchors": json.dumps({"t": anchors.t.tolist(), "names": anchors.names, "arms": anchors.arms,
                                   "source": cfg.source, "plan": cfg.plan, "horizon": H, "state_dim": D})}
    return table.replace_schema_metadata(meta)


def table_bytes(table: pa.Table) -> bytes:
    """Parquet bytes of ``table`` (deterministic for the same table)."""
    buf = io.BytesIO()
    pq.write_table(table, buf, compression="zstd")
    return buf.getvalue()


def run_anchors(record: EpisodeRecord, rollout_dir: Path, out_dir: Path, cfg: AnchorsConfig) -> str:
    """The anchor stage for one kept episode: tag, plan, write the plan; returns its relative path."""
    arrays = load_episode(rollout_dir, record)
    anchors = episode_anchors(record, arrays, cfg)
    if cfg.plan == "dense":
        table = plan_dense_frames(record.task, record.seed, anchors, arrays["actions"], arrays["states"], cfg)
    else:
        table = plan_frames(record.task, record.seed, anchors, cfg, arrays["states"])
    rel = plan_file(record.task, record.seed)
    atomic_write_bytes(Path(out_dir) / rel, table_bytes(table))
    return rel


@dataclass(frozen=True)
class FramePlan:
    """A frame plan read back: the table's rows as arrays (F frames, H anchors of D dims)."""

    t: np.ndarray            # (F,) int64
    kind: list[str]          # (F,) expert | dagger
    anchors: np.ndarray      # (F, H, D) float32
    dagger_mode: list[str]
    dagger_arm: list[str]
    dagger_seed: np.ndarray  # (F,) int64
    anchor_t: np.ndarray     # (A,) the episode's anchors
    anchor_names: list[str]

    def __len__(self) -> int:
        return len(self.t)


def load_plan(path: Path) -> FramePlan:
    """Read a plan written by ``run_anchors``."""
    table = pq.read_table(path)
    meta = json.loads(table.schema.metadata[b"anchors"])
    H, D = meta["horizon"], meta["state_dim"]
    flat = table.column("anchors").combine_chunks().flatten().to_numpy(zero_copy_only=False)
    return FramePlan(
        t=table.column("t").to_numpy().astype(np.int64),
        kind=table.column("kind").to_pylist(),
        anchors=flat.reshape(len(table), H, D).astype(np.float32),
        dagger_mode=table.column("dagger_mode").to_pylist(),
        dagger_arm=table.column("dagger_arm").to_pylist(),
        dagger_seed=table.column("dagger_seed").to_numpy().astype(np.int64),
        anchor_t=np.asarray(meta["t"], dtype=np.int64),
        anchor_names=meta["names"],
    )
