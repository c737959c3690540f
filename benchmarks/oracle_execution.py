"""The evaluation protocol's ceiling: closed-loop success of a perfect policy, per task and plan.

    python benchmarks/oracle_execution.py [--seeds 0-9] [--tasks a,b] [--plans anchors,anchors/joints,dense]

For each kept expert episode, the scene is rebuilt with rendering and the expert's own labels are
carried out exactly as the evaluation carries out a policy's predictions (``stages/oracle.py``):
the next anchor by a smooth motion to its end-effector poses by IK (``anchors``, our default) or
to its joint angles (``anchors/joints``, the report's), or chunks of 6 commanded actions 3 control
steps apart (dense plan). Prints successes, mean control steps against the expert's,
and seconds per episode. A task below 100 % here cannot be learned to 100 % under the protocol.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from anchordp3.schemas.episode import parse_seeds
from anchordp3.schemas.run import RunConfig
from anchordp3.sim.tasks import TASKS
from anchordp3.stages.oracle import oracle_episode
from anchordp3.stages.rollout import load_episode, rollout
from anchordp3.viz.table import text_table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0-9")
    ap.add_argument("--tasks", default=",".join(TASKS))
    ap.add_argument("--plans", default="anchors,anchors/joints,dense")
    args = ap.parse_args()
    plans = args.plans.split(",")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for task in args.tasks.split(","):
            base = RunConfig.model_validate({"name": "oracle", "tasks": [task], "cameras": {"width": 32, "height": 24}})
            ok = {p: 0 for p in plans}
            steps = {p: 0 for p in plans}
            expert_steps, kept, t0 = 0, 0, time.perf_counter()
            for seed in parse_seeds(args.seeds):
                rec = rollout(task, seed, base.world(), base.preset, Path(tmp))
                if not rec.success:
                    continue
                kept += 1
                expert_steps += rec.steps
                arrays = load_episode(Path(tmp), rec)
                for p in plans:
                    plan, _, through = p.partition("/")
                    cfg = base.model_copy(update={"anchors": base.anchors.model_copy(update={"plan": plan})})
                    res = oracle_episode(rec, arrays, cfg, through or "pose")
                    ok[p] += res.success
                    steps[p] += res.steps
            per = (time.perf_counter() - t0) / max(kept, 1)
            rows.append([task, kept] + [f"{ok[p]}/{kept}" for p in plans] + [f"{expert_steps / max(kept, 1):.0f}"]
                        + [f"{steps[p] / max(kept, 1):.0f}" for p in plans] + [f"{per:.1f}"])
            print(f"{task}: done", flush=True)
    print(text_table(["task", "kept"] + [f"{p} oracle" for p in plans] + ["expert steps"] + [f"{p} steps" for p in plans] + ["s/episode"], rows))


if __name__ == "__main__":
    main()
