"""How long the deployment monitor takes to score a dataset, by how many rows it scores per call.

Cross-fitted calibration scores every transition the monitor fits on (up to ``monitor.max_transitions``,
100k) with detectors that never saw it; the nearest-state term builds a (rows, bank) distance matrix per
call, 20,000 bank states wide, one slice of the bank at a time. This times ``DeploymentMonitor._data_scores`` over
the 100k HalfCheetah-v5 SAC set (``../shared/datasets/halfcheetah-v5-sac/medium-100k.npz``) at each ``--rows``,
the sizes interleaved block by block, and prints the median seconds per pass and of the nearest-state term alone,
beside that term computed over the whole bank in one product (as the module computed it before it sliced the
bank). The detectors are fitted for a few steps only: scoring costs the same whatever the weights::

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


def whole_bank_distance(states, state: torch.Tensor) -> torch.Tensor:
    """The nearest-state distance from one (rows, bank) product, as ``NearestStateDistance`` computed it before
    it sliced the bank: the comparison arm."""
    x = (state - states.obs_loc) / states.obs_scale
    closest = torch.addmm(states.bank_sq, x, states.bank.T, alpha=-2.0).amin(-1)
    return (x.pow(2).sum(-1) + closest).clamp_min(0.0).sqrt()


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
    whole_bank = {rows: [] for rows in args.rows}
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
                    whole_bank_distance(states, chunk)
                whole_bank[rows].append(time.perf_counter() - start)
    print(f"{machine_description()['cpu']}, torch {torch.__version__}; {args.threads} torch thread(s); "
          f"{len(data):,} transitions, "
          f"{states.bank.shape[0]:,} bank states, dynamics ensemble of {dynamics.members}; "
          f"median of {args.repeats} interleaved passes")
    print("| rows per call | whole scoring pass, s | nearest-state term alone, s "
          "| the term over the whole bank at once, s |")
    print("|---|---|---|---|")
    for rows in args.rows:
        print(f"| {rows} | {statistics.median(passes[rows]):.2f} | {statistics.median(nearest[rows]):.2f} "
              f"| {statistics.median(whole_bank[rows]):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
