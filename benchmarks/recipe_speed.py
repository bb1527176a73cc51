"""Speed of the TELS recipe at the paper's widths on this machine, and the paper-budget run it implies.

Runs ``recipes/tels_offline.py`` itself (paper widths, Table 10/11) for a short
number of steps per stage, for each precision, interleaved and repeated, and
reads the steps/s it reports in ``results.json``. It prints median steps/s per
stage and the wall time of the full paper-budget run those rates imply (Table 10:
1000 TS-IDM epochs; Table 11: 100k policy steps; 20 evaluations of 10 episodes).

    python -m benchmarks.recipe_speed --threads 2

A projection is not a measurement of the full run: BENCHMARKS.md says which is which.
"""
from __future__ import annotations

import argparse
import math
import statistics
import tempfile
from pathlib import Path

from benchmarks.harness import run_recipe
from torchrl_tels.config import native_bf16_supported
from torchrl_tels.run_folder import RunFolder


def run_once(precision: str, threads: int, tsidm_steps: int, policy_steps: int, episodes: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        run_recipe([
            f"run_dir={tmp}/run", f"precision={precision}",
            f"tsidm.steps={tsidm_steps}", f"policy.steps={policy_steps}",
            f"eval.interval={policy_steps}", f"eval.episodes={episodes}", "eval.last_n=1",
            f"checkpoint.interval={10 * policy_steps}", "logger.wandb_mode=disabled",
        ], threads, quiet=True)
        results = RunFolder(Path(tmp) / "run").read_results()
    evaluation = results["evaluations"][-1]
    return {
        "tsidm_steps_per_s": results["steps_per_s"]["tsidm"],
        "policy_steps_per_s": results["steps_per_s"]["policy_excluding_eval"],
        "eval_s_per_episode": results["wall_time_s"]["eval"] / len(evaluation["returns"]),
    }


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--tsidm-steps", type=int, default=300)
    parser.add_argument("--policy-steps", type=int, default=500)
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--precisions", nargs="+", default=["fp32", "bf16"])
    args = parser.parse_args()
    if "bf16" in args.precisions and not native_bf16_supported():
        # the recipe refuses it here (emulated bf16 is tens of times slower): benchmarks.step_floor times it
        print("bf16 skipped: this CPU has no native bf16 matrix multiplication")
        args.precisions = [p for p in args.precisions if p != "bf16"]
    print(f"recipe at paper widths, hopper-medium-v2 10k, torch threads pinned to {args.threads}; "
          f"{args.tsidm_steps} TS-IDM + {args.policy_steps} policy steps per run, "
          f"median of {args.repeats} interleaved runs per precision")
    rates = {p: [] for p in args.precisions}
    for _ in range(args.repeats):
        for precision in args.precisions:
            rates[precision].append(
                run_once(precision, args.threads, args.tsidm_steps, args.policy_steps, args.episodes)
            )
    tsidm_steps = 1000 * math.ceil(9013 / 256)  # Table 10: 1000 epochs at batch 256
    print(f"{'precision':<10}{'TS-IDM steps/s':>16}{'policy steps/s':>16}{'eval s/episode':>16}"
          f"{'projected paper-budget run (min)':>30}")
    for precision, runs in rates.items():
        med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        minutes = (tsidm_steps / med["tsidm_steps_per_s"] + 100_000 / med["policy_steps_per_s"]
                   + 20 * 10 * med["eval_s_per_episode"]) / 60
        print(f"{precision:<10}{med['tsidm_steps_per_s']:>16.2f}{med['policy_steps_per_s']:>16.2f}"
              f"{med['eval_s_per_episode']:>16.2f}{minutes:>30.1f}")


if __name__ == "__main__":
    main()
