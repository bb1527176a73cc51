"""The DAPG expert's own score in the Adroit evaluation envs: the ceiling to read the Adroit rows against.

D4RL's reference "expert" return of each Adroit task is the DAPG expert's; through this package's envs
(gymnasium-robotics with D4RL's reward and episode length) it should score about 100. One JSON per task,
``benchmarks/results/adroit_expert/<task>.json``: the deterministic (mean-action) expert over ``--episodes``
episodes, seeded as the grid seeds its evaluations, with its normalized scores and D4RL success rate::

    python -m benchmarks.adroit_expert --policies ../shared/datasets/adroit/policies
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

from benchmarks.harness import invocation, machine_description, REPO, write_result
from torchrl_tels.collection import load_dapg_expert
from torchrl_tels.envs import evaluate_episodes, get_task, make_eval_envs, normalized_score
from torchrl_tels.envs.adroit import ADROIT_TASKS

OUT = REPO / "benchmarks" / "results" / "adroit_expert"


def measure(task: str, policies: Path, episodes: int, seed: int = 0) -> dict:
    spec = get_task(f"{task}-expert-v1")
    env = make_eval_envs(spec.env_id, episodes, info_keys=spec.info_keys)
    runs = evaluate_episodes(load_dapg_expert(policies / f"{task}-v0-dapg-policy.npz"), env, episodes,
                             seed=seed * 100_000, max_steps=1000, success_steps=spec.success_steps)
    scores = [normalized_score(spec, r["return"]) for r in runs]
    return {"task": task, "env": spec.env_id, "episodes": episodes, "scores": scores,
            "score_mean": statistics.mean(scores), "success_rate": sum(r["success"] for r in runs) / episodes,
            "lengths": [r["length"] for r in runs], "command": invocation(), "machine": machine_description()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.adroit_expert", description=__doc__.splitlines()[0])
    parser.add_argument("--policies", type=Path, default=REPO.parent / "shared" / "datasets" / "adroit" / "policies")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--force", action="store_true")
    args = parser.parse_args(argv)
    for task in ADROIT_TASKS:
        result = measure(task, args.policies, args.episodes)
        write_result(args.out / f"{task}.json", result, force=args.force)
        print(f"{task}: normalized score {result['score_mean']:.1f}, success rate {result['success_rate']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
