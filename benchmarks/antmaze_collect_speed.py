"""How long ``recipes/collect_antmaze.py`` takes per 100k transitions on one core.

Times :func:`torchrl_tels.collection.antmaze.collect_antmaze` (the MuJoCo steps, D4RL's policy in NumPy and the
waypoint controller) on ``--episodes`` episodes of 1001 transitions, ``--repeats`` times, sets interleaved, and prints
the median scaled to 100k transitions with the machine it ran on. NumPy and torch are pinned to one thread::

    python -m benchmarks.antmaze_collect_speed --episodes 10 --repeats 3
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

from benchmarks.harness import machine_description  # noqa: E402
from torchrl_tels.collection.antmaze import ANTMAZE_SETS, EPISODE_ROWS, collect_antmaze  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.antmaze_collect_speed", description=__doc__.splitlines()[0])
    parser.add_argument("--sets", nargs="+", default=["medium-diverse", "large-diverse"], choices=sorted(ANTMAZE_SETS))
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    wall = {name: [] for name in args.sets}
    cpu = {name: [] for name in args.sets}
    for repeat in range(args.repeats):
        for name in args.sets:  # interleaved, so a change in the machine's load touches every set alike
            start, start_cpu = time.perf_counter(), time.process_time()
            collect_antmaze(name, episodes=args.episodes, seed=repeat, progress=False)
            wall[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
    rows = args.episodes * EPISODE_ROWS
    scale = 100_000 / rows
    print(f"machine: {machine_description()}; load average {os.getloadavg()[0]:.1f}")
    for name in args.sets:
        # CPU time is what one free core would take; wall time also counts waiting for a busy machine's cores
        print(f"{name}: {statistics.median(cpu[name]) * scale:.0f} s CPU, {statistics.median(wall[name]) * scale:.0f} s "
              f"wall per 100k transitions (medians of {args.repeats}, {rows} transitions each)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
