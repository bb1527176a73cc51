import json

import pytest
from scipy import stats

from study import heldout_selection


def _result(scores, heldout_mse, seed=0):
    evaluations = [{"step": 2000 * (i + 1), "score": score,
                    "trained": {"actor_action_mse": 0.05, "guide_error_ratio": 0.3},
                    "heldout": {"actor_action_mse": mse, "guide_error_ratio": 1.0 + i / 10}}
                   for i, (score, mse) in enumerate(zip(scores, heldout_mse))]
    return {"task": "hopper-medium-v2-10k", "seed": seed, "trained_rows": 7000, "heldout_rows": 2000,
            "evaluations": evaluations}


def test_the_rank_correlation_is_spearmans():
    x, y = [0.3, 0.1, 0.15, 0.25, 0.2], [10.0, 50.0, 40.0, 20.0, 35.0]
    assert heldout_selection.spearman(x, y) == pytest.approx(stats.spearmanr(x, y).statistic)


def test_the_offline_rule_keeps_the_policy_with_the_least_held_out_error(tmp_path, monkeypatch):
    # the held-out error is lowest at 4k, where the score is not the best (6k): the row says both
    result = _result([10.0, 45.0, 50.0, 20.0], [0.30, 0.10, 0.15, 0.25])
    row = heldout_selection.selection_row(result).split(" | ")
    assert row[3] == "50.0 at 6000" and row[4] == "20.0" and row[5] == "35.0"  # best, final, mean of 6k and 8k
    assert row[6] == "45.0 at 4000"
    assert row[7] == f"{stats.spearmanr([0.30, 0.10, 0.15, 0.25], [10.0, 45.0, 50.0, 20.0]).statistic:+.2f}"
    assert row[9] == "0.3000 → 0.2500" and row[10] == "1.00 → 1.30 |"

    monkeypatch.setattr(heldout_selection, "RESULTS", tmp_path)
    for seed in (0, 1):
        (tmp_path / f"t-seed{seed}.json").write_text(json.dumps(_result([1.0, 2.0], [0.2, 0.1], seed)))
    assert heldout_selection.table().count("\n| hopper-medium-v2-10k |") == 2
    assert heldout_selection.plot().stat().st_size > 0
