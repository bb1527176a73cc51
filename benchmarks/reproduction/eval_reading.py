"""Choice 6's evaluation protocol: the same runs' scores read four ways.

    python benchmarks/reproduction/eval_reading.py

The study scores a run by the mean of all ten evaluations (every 500 of its 5k policy steps),
which counts the half-trained policies of the first steps as much as the last. The paper does
not say how Table 1 was read. This reads the finished runs of the MuJoCo preset (the
``beta0.01`` arm) and the issue-6 grid's baselines at the same budget four ways: the study's mean
of all ten, the mean of the last four (3.5k-5k steps), the last evaluation alone, and the best
one (an upper bound no protocol should use). Nothing is trained.
"""
from __future__ import annotations

import json
import statistics

from summary import BETA_ARM, GRID, HERE, SHARED_BUDGET, TASKS, on_grid_budget

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
        paths, wanted = (GRID / method / task).glob("seed*.json"), on_grid_budget
    else:
        paths, wanted = (HERE / "results" / method / task).glob("seed*.json"), lambda r: r["budget"] == SHARED_BUDGET
    found = {}
    for path in sorted(paths):
        result = json.loads(path.read_text())
        if wanted(result):
            found[int(result["seed"])] = [e["score"] for e in result["evaluations"]]
    return found


def main():
    print("| task | method | seeds | " + " | ".join(READINGS) + " |")
    print("|---|---|---|" + "---|" * len(READINGS))
    for task in TASKS:
        bc = curves("bc", task)
        for method in (BETA_ARM, *BASELINES):
            runs = curves(method, task)
            cells = []
            for read in READINGS.values():
                text = f"{statistics.mean(read(c) for c in runs.values()):.1f}"
                paired = [read(runs[s]) - read(bc[s]) for s in runs if s in bc]
                if method != "bc" and paired:
                    text += f" ({statistics.mean(paired):+.1f})"
                cells.append(text)
            name = "TELS, MuJoCo preset" if method == BETA_ARM else method.upper()
            print(f"| {task} | {name} | {len(runs)} | " + " | ".join(cells) + " |")
    print("\nIn brackets: the mean change against BC on the same seeds under the same reading.")


if __name__ == "__main__":
    main()
