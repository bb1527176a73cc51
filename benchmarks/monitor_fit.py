"""How long the cross-fitted monitor's dynamics ensembles take to train: one at a time, or stacked.

Cross-fitted calibration (``monitor.calibration=cross_fit``, the default) trains ``folds + 1`` dynamics
ensembles: one per fold and the deployed one. ``fit_ensembles`` trains them as one stacked ensemble, each
with the updates it would get alone (tests/test_monitor.py checks that against a hand-written loop). This
times both ways on the folds of the 100k HalfCheetah-v5 SAC set
(``../shared/datasets/halfcheetah-v5-sac/medium-100k.npz``) at the monitor's default widths, batch and
precision (bf16 where the CPU multiplies it natively, fp32 elsewhere), the two arms interleaved, and prints
the median milliseconds per training step of all ``folds + 1`` ensembles and what that makes of
``monitor.steps`` steps::

    python -m benchmarks.monitor_fit --steps 200 --repeats 5 --threads 1
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

from benchmarks.data_cost import source
from benchmarks.harness import machine_description, recipe_config


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.monitor_fit", description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200, help="training steps timed per arm and repeat")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from torchrl_tels.config import resolve_precision
    from torchrl_tels.data import load_dataset
    from torchrl_tels.data.subsets import trajectory_ids
    from torchrl_tels.envs.monitor import DeploymentMonitor
    from torchrl_tels.modules import DynamicsEnsemble, fit_ensembles

    monitor = recipe_config([]).monitor
    precision = resolve_precision("auto", "cpu")
    data = load_dataset(str(source()))
    trajectory = trajectory_ids(data)
    fold = trajectory % monitor.folds
    datasets = [data[fold != k] for k in range(monitor.folds)] + [data]
    transitions = [DeploymentMonitor._transitions(d, "train", "monitor_fit") for d in datasets]
    seeds = list(range(len(datasets)))

    def ensembles():
        return [DynamicsEnsemble(o.shape[-1], a.shape[-1], members=monitor.members, num_cells=tuple(monitor.num_cells))
                for o, a, _ in transitions]

    def one_at_a_time():
        for ensemble, data_k, seed in zip(ensembles(), transitions, seeds):
            fit_ensembles([ensemble], [data_k], seeds=[seed], steps=args.steps, precision=precision)

    def stacked():
        fit_ensembles(ensembles(), transitions, seeds=seeds, steps=args.steps, precision=precision)

    arms = {"one at a time": one_at_a_time, "stacked": stacked}
    times = {name: [] for name in arms}
    for _ in range(args.repeats):
        for name, arm in arms.items():
            start = time.perf_counter()
            arm()
            times[name].append((time.perf_counter() - start) / args.steps)
    print(f"{machine_description()['cpu']}, torch {torch.__version__}; {args.threads} torch thread(s); {precision}; "
          f"{len(datasets)} ensembles "
          f"({monitor.folds} folds and the deployed one) of {monitor.members} members, widths "
          f"{list(monitor.num_cells)}, batch 256; median of {args.repeats} interleaved repeats of {args.steps} steps")
    print(f"| training | ms per step (all {len(datasets)} ensembles) | {monitor.steps} steps, s |")
    print("|---|---|---|")
    for name, values in times.items():
        median = statistics.median(values)
        print(f"| {name} | {1000 * median:.1f} | {median * monitor.steps:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
