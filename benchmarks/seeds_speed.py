"""Seed-runs per hour: several seeds in one process (``seeds=[...]``) against one process per seed.

Runs ``recipes/tels_offline.py`` for ``--seeds`` seeds both ways, alternating which
goes first, ``--repeats`` times, with torch's threads pinned:

* one process, ``seeds=[0,...,n-1]``: the seeds' updates stacked into one ``torch.vmap``;
* ``n`` processes one after another, ``seed=k`` each.

Prints the median wall time of each (whole processes, start-up included) and of its training
alone (stage 1 + stage 2 from ``results.json``, evaluation included), and the seed-runs per hour
each gives. The budget is ``budget=smoke`` unless ``--overrides`` says otherwise.

    python -m benchmarks.seeds_speed --seeds 3 --repeats 2 --threads 1
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks.harness import machine_description, run_recipe
from torchrl_tels.run_folder import RunFolder


def training_seconds(results: dict) -> float:
    wall = results["wall_time_s"]
    return wall["tsidm"] + wall["policy"]


def one_process(folder: Path, seeds: int, overrides: list[str], threads: int) -> tuple[float, float]:
    start = time.perf_counter()
    run_recipe([f"run_dir={folder}", f"seeds=[{','.join(map(str, range(seeds)))}]", *overrides], threads, quiet=True)
    wall = time.perf_counter() - start
    return wall, training_seconds(RunFolder(folder).read_results())


def one_process_per_seed(folder: Path, seeds: int, overrides: list[str], threads: int) -> tuple[float, float]:
    wall = training = 0.0
    for seed in range(seeds):
        start = time.perf_counter()
        run_recipe([f"run_dir={folder / f'seed{seed}'}", f"seed={seed}", *overrides], threads, quiet=True)
        wall += time.perf_counter() - start
        training += training_seconds(RunFolder(folder).seed(seed).read_results())
    return wall, training


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--overrides", nargs="*", default=["budget=smoke"],
                        help="recipe overrides shared by both arms (default: budget=smoke)")
    args = parser.parse_args()
    overrides = [*args.overrides, "device=cpu", "logger.wandb_mode=disabled"]
    arms = {"one process": one_process, "one process per seed": one_process_per_seed}
    times = {name: [] for name in arms}
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            order = list(arms) if repeat % 2 == 0 else list(reversed(arms))
            for name in order:
                folder = Path(tmp) / f"{name.replace(' ', '_')}_{repeat}"
                times[name].append(arms[name](folder, args.seeds, overrides, args.threads))
                print(f"repeat {repeat}, {name}: {times[name][-1][0]:.1f} s", flush=True)
    print(f"\n{args.seeds} seeds, overrides {' '.join(args.overrides)}, torch threads {args.threads}, "
          f"median of {args.repeats}; {machine_description()}")
    print("| arm | wall s (processes) | training s | seed-runs per hour (wall) | speed-up |\n|---|---|---|---|---|")
    base = statistics.median(w for w, _ in times["one process per seed"])
    for name, values in times.items():
        wall, training = statistics.median(w for w, _ in values), statistics.median(t for _, t in values)
        print(f"| {name} | {wall:.1f} | {training:.1f} | {args.seeds * 3600 / wall:.0f} | {base / wall:.2f}x |")


if __name__ == "__main__":
    main()
