"""The perfect policy: the expert's own labels carried out by the closed-loop executor.

If the evaluation protocol (``stages/evaluate.py``: one decision → the first predicted anchor by a
smooth joint-space motion, or a chunk of dense actions) cannot finish a task with the *true*
labels, no trained policy can; these episodes measure that ceiling. For a kept expert episode of
``(task, seed)`` the scene is rebuilt with rendering (as the evaluation does) and at each decision
the oracle "predicts" exactly the labels the frame plan would give at that point of the expert's
episode: the next H anchors, or the next H commanded actions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from anchordp3.schemas.episode import EpisodeRecord
from anchordp3.schemas.run import RunConfig
from anchordp3.sim.closed_loop import EvalEpisode
from anchordp3.stages.anchors import commanded_states, episode_anchors, horizon_indices
from anchordp3.stages.evaluate import act


@dataclass(frozen=True)
class OracleResult:
    """success: the task's check passed; steps: control steps used; decisions: labels carried out."""

    success: bool
    steps: int
    decisions: int


def oracle_episode(record: EpisodeRecord, arrays: dict[str, np.ndarray], cfg: RunConfig, through: str = "pose") -> OracleResult:
    """Carry out the expert episode's labels (``cfg.anchors.plan``) until success, the step limit
    or the labels run out. arrays: the rollout's ``states (T + 1, 32)``, ``actions (T, J)`` and tags."""
    ep = EvalEpisode(record.task, record.seed, cfg.world())
    H = cfg.anchors.horizon
    if cfg.anchors.plan == "dense":
        d = cfg.anchors.dense
        actions, states = arrays["actions"], arrays["states"]
        labels = [commanded_states(states, actions, horizon_indices(t, H, len(actions), d.action_stride))
                  for t in range(0, len(actions), d.execute * d.action_stride)]
    else:
        a = episode_anchors(record, arrays, cfg.anchors).states
        labels = [a[horizon_indices(i, H, len(a))] for i in range(len(a))]
    decisions = 0
    for pred in labels:
        if ep.success() or ep.steps >= ep.step_limit:
            break
        act(ep, pred, cfg.anchors, through, skip_reached=0.0)  # each label once, in order
        decisions += 1
    return OracleResult(success=ep.success(), steps=ep.steps, decisions=decisions)
