"""Evaluation time: the episodes one at a time against all of them as one batch of envs.

Loads the actor of a finished run (``--run-dir``; by default a ``budget=smoke`` run of the
default configuration is trained first, in a temporary folder), then times ``--episodes``
deterministic evaluation episodes on the run's env sequentially (one env, one policy call
per step of each episode) and batched (:func:`~torchrl_tels.envs.make_eval_envs`, one policy
call per step for all), alternating, ``--repeats`` times, with torch's threads pinned. Prints
the median seconds of each, the speed-up, and the largest return difference between the
two (float rounding of the batched product, amplified by the body's dynamics).

    python -m benchmarks.eval_speed --threads 1
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.harness import run_recipe
from torchrl_tels.envs import evaluate_policy, make_eval_env, make_eval_envs
from torchrl_tels.modules import load_tels_actor, TSIDM
from torchrl_tels.run_folder import RunFolder


def load_actor(run_dir: Path):
    folder = RunFolder(run_dir)
    results = folder.read_results()
    env = make_eval_env(results["env"])
    tsidm = TSIDM.load(folder.tsidm_path, observation_dim=env.observation_spec["observation"].shape[-1],
                       action_dim=env.action_spec.shape[-1])
    return load_tels_actor(folder.policy_path, tsidm, env.action_spec).eval(), results["env"]


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, default=None, help="a finished run (default: train a smoke run)")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as tmp:
        run_dir = args.run_dir
        if run_dir is None:
            run_dir = Path(tmp) / "run"
            run_recipe([f"run_dir={run_dir}", "budget=smoke", "logger.wandb_mode=disabled"], args.threads, quiet=True)
        actor, env_id = load_actor(run_dir)
        one, batch = make_eval_env(env_id), make_eval_envs(env_id, args.episodes)
        times = {"sequential": [], "batched": []}
        returns = {}
        for repeat in range(args.repeats):
            for name, env in (("sequential", one), ("batched", batch)):
                start = time.perf_counter()
                returns[name], lengths = evaluate_policy(actor, env, args.episodes, seed=1000 * repeat,
                                                         with_lengths=True)
                times[name].append(time.perf_counter() - start)
    sequential, batched = statistics.median(times["sequential"]), statistics.median(times["batched"])
    gap = max(abs(a - b) / max(abs(a), 1.0) for a, b in zip(returns["sequential"], returns["batched"]))
    print(f"{env_id}, {args.episodes} episodes (last repeat: {sum(lengths)} steps), torch threads {args.threads}, "
          f"median of {args.repeats}")
    print("| evaluation | seconds | speed-up |\n|---|---|---|")
    print(f"| sequential | {sequential:.2f} | 1 |")
    print(f"| batched ({args.episodes} envs) | {batched:.2f} | {sequential / batched:.2f}x |")
    print(f"largest relative return difference, last repeat: {gap:.2e}")


if __name__ == "__main__":
    main()
