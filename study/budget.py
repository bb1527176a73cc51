"""Choice 5's budget on the MuJoCo preset: a longer stage 2 and a longer stage 1 against the study's.

    python -m study.budget

The study compares every choice at 3k TS-IDM steps and 5k policy steps; the paper trains about
36k and 100k. This reads two arms run on the preset (re-encoding, beta = 0.01, alpha = 1) against
the preset's own runs at the shared budget on the same seeds and CPU (``alpha1_epyc``; ``alpha1``
on halfcheetah, which ran on the same AMD machine):

- ``long20k_preset``: 20k policy steps, evaluated every 1k (``tsidm.steps=3000 optim.steps=20000
  eval.interval=1000 eval.episodes=10``), scored like the recipe, by its last ten evaluations
  (11k-20k). Its first 5k steps are the preset run's own (the evaluations they share are equal to
  every digit), so the change is what 15k more steps do to that run. It is given against the 5k
  run's last four evaluations (3.5k-5k) as well as its mean of all ten, which counts the
  half-trained policies of the first steps (0.5k-3k).
- ``tsidm9k``: a 3x longer stage 1 (``tsidm.steps=9000 optim.steps=5000 eval.interval=500
  eval.episodes=10``), scored like the study, by all ten evaluations.

Then the preset at the paper's whole budget (``paper_budget_preset``, ``budget=paper``: about 36k
TS-IDM and 100k policy steps, 20 evaluations), read as the paper reads Table 1, by the last 10 of
its 20 evaluations, against the TELS row of Table 1 and the study's target, the paper's mean minus
its std (:func:`paper_budget_row`).

Nothing is trained here.
"""
from __future__ import annotations

import argparse
import statistics

from benchmarks.run_grid import PAPER_TABLE1
from study.summary import (GRID, HERE, on_grid_budget, SHARED_BUDGET, TASKS, evaluation_scores,
                           seed_results)

PRESET_ARMS = {task: "alpha1" if task.startswith("halfcheetah") else "alpha1_epyc" for task in TASKS}
LONG_STAGE2 = ("long20k_preset", ["tsidm.steps=3000", "optim.steps=20000", "eval.interval=1000", "eval.episodes=10"])
LONG_STAGE1 = ("tsidm9k", ["tsidm.steps=9000", "optim.steps=5000", "eval.interval=500", "eval.episodes=10"])
PAPER_BUDGET = ("paper_budget_preset", ["budget=paper"])
LONG_BC = GRID / "long50k" / "bc"  # BC at 50k policy steps (run_grid --steps 50000), the grid's longest
EPISODE_STEPS = 1000  # eval.max_steps, the recipe's default: an episode shorter than this ended in a fall


def runs(arm: str, budget: list[str], task: str) -> dict[int, dict]:
    """{seed: result} of ``arm``'s runs on ``task`` that used ``budget``."""
    return seed_results(HERE / "results" / arm / task, lambda result: result["budget"] == budget)


def render() -> str:
    """The table of both arms against the preset's runs, then the count and mean of each change."""
    lines = ["| task | seed | preset, 5k policy steps: all 10 | last 4 | 20k steps: last 10 | change from all 10 "
             "| from last 4 | 9k TS-IDM steps: all 10 | change |",
             "|---|---|---|---|---|---|---|---|---|"]
    long_changes, late_changes, stage1_changes = [], [], []
    for task in TASKS:
        preset = runs(PRESET_ARMS[task], SHARED_BUDGET, task)
        long = runs(*LONG_STAGE2, task)
        stage1 = runs(*LONG_STAGE1, task)
        for seed in sorted(set(long) | set(stage1)):
            base = preset[seed]["final_normalized_score_mean"]
            last4 = statistics.mean(evaluation_scores(preset[seed])[-4:])
            cells = [f"{base:.1f}", f"{last4:.1f}"]
            if seed in long:
                late = long[seed]["final_normalized_score_mean"]
                long_changes.append(late - base)
                late_changes.append(late - last4)
                cells += [f"{late:.1f}", f"{late - base:+.1f}", f"{late - last4:+.1f}"]
            else:
                cells += ["", "", ""]
            if seed in stage1:
                longer = stage1[seed]["final_normalized_score_mean"]
                stage1_changes.append(longer - base)
                cells += [f"{longer:.1f}", f"{longer - base:+.1f}"]
            else:
                cells += ["", ""]
            lines.append(f"| {task} | {seed} | " + " | ".join(cells) + " |")
    for name, changes in (("20k policy steps (last 10) against the 5k run's all 10", long_changes),
                          ("20k policy steps (last 10) against the 5k run's last 4", late_changes),
                          ("9k TS-IDM steps", stage1_changes)):
        if changes:
            lines.append(f"\n{name}: {sum(c > 0 for c in changes)} of {len(changes)} up, "
                         f"mean change {statistics.mean(changes):+.1f}.")
    return "\n".join(lines)


def _mean_final(runs: dict[int, dict]) -> str:
    return f"{statistics.mean(r['final_normalized_score_mean'] for r in runs.values()):.1f}" if runs else "—"


def paper_budget_row(task: str, runs: dict[int, dict], bc_runs: dict[int, dict], long_bc_runs: dict[int, dict]) -> str:
    """One task's row: the paper's reading (last 10 of 20 evaluations), the second-half mean, the best
    evaluation and its step, how many evaluations ended every episode in a fall, BC in the same harness
    at the study's shared budget and at 50k policy steps, Table 1's TELS score, and the final score's
    distance to the study's target (Table 1's mean minus its std; negative: short of it)."""
    finals = [runs[s]["final_normalized_score_mean"] for s in sorted(runs)]
    evaluations = [e for s in sorted(runs) for e in runs[s]["evaluations"]]
    best = max(evaluations, key=lambda e: e["score"])
    all_fell = sum(max(e["lengths"]) < EPISODE_STEPS for e in evaluations)
    mean, std = PAPER_TABLE1[task]["tels"]
    final = statistics.mean(finals)
    cells = [task, ", ".join(map(str, sorted(runs))), ", ".join(f"{f:.1f}" for f in finals),
             f"{statistics.mean(r['second_half_score_mean'] for r in runs.values()):.1f}",
             f"{best['score']:.1f} ({best['step'] // 1000}k)", f"{all_fell} of {len(evaluations)}",
             _mean_final(bc_runs), _mean_final(long_bc_runs),
             f"{mean:g} ± {std:g}", f"{final - (mean - std):+.1f}"]
    return "| " + " | ".join(cells) + " |"


def render_paper_budget() -> str:
    """The table of :func:`paper_budget_row` over the sets the arm has run."""
    lines = ["| task | seeds | final: last 10 of 20 | second-half mean | best evaluation (step) "
             "| evaluations where every episode fell | BC, shared budget | BC, 50k steps | TELS, Table 1 "
             "| final − (mean − std) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for task in TASKS:
        paper_runs = runs(*PAPER_BUDGET, task)
        if paper_runs:
            lines.append(paper_budget_row(task, paper_runs, seed_results(GRID / "bc" / task, on_grid_budget),
                                          seed_results(LONG_BC / task, lambda r: True)))
    return "\n".join(lines)


def main() -> None:
    argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0]).parse_args()
    print(render())
    print()
    print(render_paper_budget())


if __name__ == "__main__":
    main()
