"""The paper-budget reading of ``study.budget``, on made-up runs."""
import statistics

from benchmarks.run_grid import PAPER_TABLE1
from study import budget

TASK = "walker2d-medium-v2-10k"


def _run(seed, scores, lengths):
    evaluations = [{"step": 5000 * (i + 1), "score": s, "lengths": l} for i, (s, l) in enumerate(zip(scores, lengths))]
    return {"seed": seed, "evaluations": evaluations, "final_normalized_score_mean": statistics.mean(scores[-10:]),
            "second_half_score_mean": statistics.mean(scores[10:])}


def test_paper_budget_row_reads_the_runs_against_table1():
    scores = [float(i) for i in range(20)]            # best: the last evaluation, at 100k
    lengths = [[1000, 300]] * 5 + [[200, 150]] * 15   # 15 evaluations in which every episode fell
    bc = {0: {"final_normalized_score_mean": 30.0}, 1: {"final_normalized_score_mean": 40.0}}
    row = budget.paper_budget_row(TASK, {0: _run(0, scores, lengths)}, bc, {0: bc[1]})
    cells = [c.strip() for c in row.strip("|").split("|")]
    mean, std = PAPER_TABLE1[TASK]["tels"]
    final = statistics.mean(range(10, 20))  # 14.5
    assert cells[0] == TASK and cells[1] == "0"
    assert cells[2] == "14.5" and cells[3] == "14.5"
    assert cells[4] == "19.0 (100k)"
    assert cells[5] == "15 of 20"
    assert cells[6] == "35.0"
    assert cells[7] == "40.0"
    assert cells[8] == f"{mean:g} ± {std:g}"
    assert float(cells[9]) == round(final - (mean - std), 1) < 0


def test_paper_budget_row_without_bc_and_with_no_falls():
    scores = [60.0] * 20
    row = budget.paper_budget_row(TASK, {0: _run(0, scores, [[1000, 1000]] * 20)}, {}, {})
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[5] == "0 of 20" and cells[6] == cells[7] == "—"
    mean, std = PAPER_TABLE1[TASK]["tels"]
    assert float(cells[9]) == round(60.0 - (mean - std), 1)
