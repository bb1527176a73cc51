"""How long the deployment monitor takes to score a dataset, by how many rows it scores per call.

Cross-fitted calibration scores every transition the monitor fits on (up to ``monitor.max_transitions``,
100k) with detectors that never saw it; the nearest-state term builds a (rows, bank) distance matrix per
call, 20,000 bank states wide. This times ``DeploymentMonitor._data_scores`` over the 100k HalfCheetah-v5 SAC set
(``../shared/datasets/halfcheetah-v5-sac/medium-100k.npz``) at each ``--rows``, the sizes interleaved block by
block, and prints the median seconds per pass and of the nearest-state term alone, beside that term's
expanded form (the sum written out, as the module computed it before). The detectors are fitted for a few steps only:
scoring costs the same whatever the weights::

    python -m benchmarks.monitor_scoring --rows 2048 256 64 --repeats 5 --threads 1
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

from benchmarks.data_cost import source
from benchmarks.harness import machine_description


def expanded_distance(states, state: torch.Tensor) -> torch.Tensor:
    """The nearest-state distance with the (rows, bank) sum written out, ||x||^2 + ||b||^2 - 2 x.b, as
    ``NearestStateDistance`` computed it before it folded the sum into one product: the comparison arm."""
    x = (state - states.obs_loc) / states.obs_scale
    squared = x.pow(2).sum(-1, keepdim=True) + states.bank_sq - 2.0 * x @ states.bank.T
    return squared.amin(-1).clamp_min(0.0).sqrt()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.monitor_scoring", description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[2048, 256, 64], help="rows scored per call")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from torchrl_tels.data import load_dataset
    from torchrl_tels.envs.monitor import DeploymentMonitor

    data = load_dataset(str(source()))
    dynamics, states = DeploymentMonitor.fit_detectors(data, steps=10)
    monitor = DeploymentMonitor(dynamics=dynamics, states=states, flag=False)
    next_observation = data.get(("next", "observation"))
    passes = {rows: [] for rows in args.rows}
    nearest = {rows: [] for rows in args.rows}
    expanded = {rows: [] for rows in args.rows}
    with torch.no_grad():
        for _ in range(args.repeats):
            for rows in args.rows:
                start = time.perf_counter()
                monitor._data_scores(data, rows)
                passes[rows].append(time.perf_counter() - start)
                start = time.perf_counter()
                for chunk in next_observation.split(rows):
                    states(chunk)
                nearest[rows].append(time.perf_counter() - start)
                start = time.perf_counter()
                for chunk in next_observation.split(rows):
                    expanded_distance(states, chunk)
                expanded[rows].append(time.perf_counter() - start)
    print(f"{machine_description()}; {args.threads} torch thread(s); {len(data):,} transitions, "
          f"{states.bank.shape[0]:,} bank states, dynamics ensemble of {dynamics.members}; "
          f"median of {args.repeats} interleaved passes")
    print("| rows per call | whole scoring pass, s | nearest-state term alone, s | its expanded form, s |")
    print("|---|---|---|---|")
    for rows in args.rows:
        print(f"| {rows} | {statistics.median(passes[rows]):.2f} | {statistics.median(nearest[rows]):.2f} "
              f"| {statistics.median(expanded[rows]):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
