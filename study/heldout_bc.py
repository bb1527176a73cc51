"""BC on the held-out set: a 10k subset of the HalfCheetah-v5 SAC data, at the study's budget.

    python -m study.heldout_bc --seed 0

trains TorchRL's ``BCLoss`` baseline (``benchmarks.baselines``) on the same whole episodes the recipe
takes with ``dataset.size=10000`` and that seed (``torchrl_tels.data.subset_dataset``), for 5k steps
with ten evaluations of ten episodes on HalfCheetah-v5 (D4RL halfcheetah references), and writes
``results/heldout_bc/halfcheetah-v5-sac-medium-10k/seed<k>.json``. No choice of the study was made on
this set, so it confirms or refutes a default chosen on the four shared sets.
"""
from __future__ import annotations

import argparse
import time

from benchmarks.baselines import train_baseline
from benchmarks.harness import machine_description, REPO, skip_existing, write_result
from torchrl_tels.data import load_dataset, shared_datasets_dir, subset_dataset

TASK = "halfcheetah-v5-sac-medium-10k"


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--force", action="store_true", help="rewrite the result if it exists")
    args = parser.parse_args()
    out = REPO / "study" / "results" / "heldout_bc" / TASK / f"seed{args.seed}.json"
    if skip_existing(out, args.force):
        return
    source = shared_datasets_dir() / "halfcheetah-v5-sac" / "medium-100k.npz"
    data = subset_dataset(load_dataset(str(source)), 10_000, seed=args.seed, mode="trajectories")
    start = time.time()
    result = train_baseline("bc", data, task="mujoco/halfcheetah/medium-v0", steps=5000, seed=args.seed,
                            eval_interval=500, eval_episodes=10, eval_batched=False, threads=1, progress=False)
    result.update(variant="heldout_bc", date=time.strftime("%Y-%m-%d"), elapsed_s=time.time() - start,
                  machine=machine_description(), command=f"python -m {__spec__.name} --seed {args.seed}")
    write_result(out, result, force=True)
    print(f"BC on {TASK}, seed {args.seed}: {result['final_normalized_score_mean']:.1f}")


if __name__ == "__main__":
    main()
