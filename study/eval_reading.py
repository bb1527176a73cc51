"""Choice 6's evaluation protocol: the same runs' scores read four ways.

    python -m study.eval_reading
    python -m study.eval_reading --arms preset_avx512 alpha1 --against preset_avx512

The study scores a run by the mean of all ten evaluations (every 500 of its 5k policy steps),
which counts the half-trained policies of the first steps as much as the last. The paper does
not say how Table 1 was read. This reads the finished runs of the ``beta0.01`` arm (re-encoding,
beta = 0.01, alpha = 0.01) and the baseline grid's baselines at the same budget four ways: the study's mean
of all ten, the mean of the last four (3.5k-5k steps), the last evaluation alone, and the best
one (an upper bound no protocol should use). Nothing is trained. ``--arms`` reads other
variants of the study the same way, and ``--against`` names the arm the bracketed paired change
is taken against (BC unless given).
"""
from __future__ import annotations

import argparse
import statistics

from study.summary import (BETA_ARM, evaluation_scores, GRID, HERE, on_grid_budget, seed_results,
                           SHARED_BUDGET, TASKS)

BASELINES = ("bc", "td3bc", "iql")
READINGS = {
    "all 10 (the study's)": lambda c: statistics.mean(c),
    "last 4": lambda c: statistics.mean(c[-4:]),
    "last": lambda c: c[-1],
    "best": lambda c: max(c),
}


def curves(method: str, task: str) -> dict[int, list[float]]:
    """{seed: the scores of its evaluations in order} of ``method``'s runs at the shared budget."""
    if method in BASELINES:
        results = seed_results(GRID / method / task, on_grid_budget)
    else:
        results = seed_results(HERE / "results" / method / task, lambda r: r["budget"] == SHARED_BUDGET)
    return {seed: evaluation_scores(result) for seed, result in results.items()}


def render(arms=(BETA_ARM, *BASELINES), against: str = "bc") -> str:
    """The table of ``arms`` read four ways, with the paired change against ``against``."""
    lines = ["| task | method | seeds | " + " | ".join(READINGS) + " |", "|---|---|---|" + "---|" * len(READINGS)]
    for task in TASKS:
        base = curves(against, task)
        for method in arms:
            runs = curves(method, task)
            if not runs:
                continue
            cells = []
            for read in READINGS.values():
                text = f"{statistics.mean(read(c) for c in runs.values()):.1f}"
                paired = [read(runs[s]) - read(base[s]) for s in runs if s in base]
                if method != against and paired:
                    text += f" ({statistics.mean(paired):+.1f})"
                cells.append(text)
            name = ("TELS, beta0.01 arm (re-encoding, beta = 0.01)" if method == BETA_ARM
                    else method.upper() if method in BASELINES else method)
            lines.append(f"| {task} | {name} | {len(runs)} | " + " | ".join(cells) + " |")
    shown = against.upper() if against in BASELINES else against
    lines.append(f"\nIn brackets: the mean change against {shown} on the same seeds under the same reading.")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--arms", nargs="+", default=[BETA_ARM, *BASELINES], help="variants or baselines to read")
    parser.add_argument("--against", default="bc", help="the arm of the bracketed paired change")
    args = parser.parse_args()
    print(render(args.arms, args.against))


if __name__ == "__main__":
    main()
