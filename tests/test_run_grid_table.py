"""``run_grid --table --longer``: each method beside a longer budget, with the verdict on its curve.

The records are synthetic, with curves whose slopes are known exactly, so every figure the table prints is
checked against a value computed here by hand.
"""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from scipy import stats

from benchmarks import run_grid

TASKS = run_grid.AGGREGATE_TASKS


def _record(seed: int, steps: int, interval: int, curve, **hyperparameters) -> dict:
    evaluations = [{"step": s, "score": float(curve(s))} for s in range(interval, steps + 1, interval)]
    final = float(np.mean([e["score"] for e in evaluations[-10:]]))
    return {"seed": seed, "final_normalized_score_mean": final, "evaluations": evaluations,
            "budget": {"policy_steps": steps, "eval_interval": interval, "eval_episodes": 10},
            "hyperparameters": {"lr": 3e-4, **hyperparameters}}


def _write(folder, method, task, record):
    path = run_grid.result_path(folder, method, task, record["seed"])
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))


@pytest.fixture
def grids(tmp_path):
    short, longer = tmp_path / "grid", tmp_path / "long20k"
    for i, task in enumerate(TASKS):
        for seed in (0, 1):
            _write(short, "bc", task, _record(seed, 5000, 500, lambda s: 30.0 + seed))
            # BC flat at 20k: seed 0 +0.2 per 1k, seed 1 flat; tasks 10 i² apart, so IQM and mean differ
            _write(longer, "bc", task, _record(seed, 20000, 2000, lambda s: 10.0 * i**2 + seed + (1 - seed) * 2e-4 * s))
            # TD3+BC rising 1 point per 1k steps, IQL falling 0.5 per 1k and at another learning rate
            _write(longer, "td3bc", task, _record(seed, 20000, 2000, lambda s: 10.0 + seed + 1e-3 * s))
            _write(longer, "iql", task, _record(seed, 20000, 2000, lambda s: 40.0 - 5e-4 * s, lr=1e-3))
            _write(short, "iql", task, _record(seed, 5000, 500, lambda s: 20.0))
            _write(longer, "tels", task, _record(seed, 4000, 2000, lambda s: 1.0))  # two evaluations only
    return short, longer


LONGER = "Each method at this budget and at a longer one"
LONGEST = "Each method at its longest budget"


def _section(text: str, heading: str) -> str:
    """The body of the ``## heading`` section of a rendered table."""
    return text.split(f"## {heading}")[1].split("\n## ")[0]


def _row(text: str, heading: str, task: str, label: str) -> list[str]:
    """The cells of the one row for ``task`` and method ``label`` in the ``heading`` section."""
    rows = [line for line in _section(text, heading).splitlines() if line.startswith(f"| {task} | {label} |")]
    assert len(rows) == 1, rows
    return [cell.strip() for cell in rows[0].strip("|").split("|")]


def test_longer_budget_rows_give_both_scores_the_slope_and_the_verdict(grids):
    short, longer = grids
    text = run_grid.render_table(short, (longer,)).read_text()
    task = TASKS[0]
    bc = _row(text, LONGER, task, "BC")
    assert bc[2].startswith("5k steps") and bc[4].startswith("20k steps")
    assert bc[3] == "**30.5** ± 0.5 (n=2)"
    # final score: mean of all 10 evaluations (2k..20k); seed 0 is 2e-4 s, seed 1 is 1
    seed0 = 2e-4 * np.mean(np.arange(2000, 20001, 2000))
    mean, std = np.mean([seed0, 1.0]), np.std([seed0, 1.0])
    assert bc[5] == f"**{mean:.1f}** ± {std:.1f} (n=2)"
    # second half: evaluations 12k..20k; the seed mean rises 0.1 per 1k, 0.8 points across the 8k
    assert bc[6] == "+0.10 (+0.8 ± 0.0 across it)" and bc[7] == "flat"
    td3bc = _row(text, LONGER, task, "TD3+BC")
    assert td3bc[2] == "—" and td3bc[3] == "—"
    assert td3bc[6] == "+1.00 (+8.0 ± 0.0 across it)" and td3bc[7] == "**still rising**"
    iql = _row(text, LONGER, task, "IQL")
    assert iql[6] == "-0.50 (-4.0 ± 0.0 across it)"
    assert iql[7] == "**still falling**; **hyperparameters differ: lr**"
    assert _row(text, LONGER, task, "TELS")[6:8] == ["—", "too few evaluations"]
    flatness = _section(text, "Have the learning curves flattened?")
    # the synthetic runs record no per-episode scores, so the scatter cannot be split
    assert f"| {task} | BC | 5k | 2 | 30.5 → 30.5 | +0.00 (+0.0 ± 0.0 across it) | flat | — |" in flatness
    # a name an older run does not record reads as the default: no difference at the default, one elsewhere
    older, at_default = {"hyperparameters": {"lr": 3e-4}}, {"hyperparameters": {"lr": 3e-4, "reward_scale": 1.0}}
    changed = {"hyperparameters": {"lr": 3e-4, "reward_scale": "return_range"}}
    assert run_grid._differing_hyperparameters([older, at_default], "iql", task) == []
    assert run_grid._differing_hyperparameters([older, changed], "iql", task) == ["reward_scale"]
    maze_run = {"hyperparameters": {"reward_bias": -1.0}}
    assert run_grid._differing_hyperparameters([older, maze_run], "iql", "antmaze-umaze-v0-10k") == []
    # TELS: the β its TS-IDM trained at, the one setting its grids have changed
    assert run_grid._differing_hyperparameters([{"beta": 1.0}, {"beta": 1.0}], "tels", task) == []
    assert run_grid._differing_hyperparameters([{"beta": 1.0}, {"beta": 0.01}], "tels", task) == ["tsidm.beta"]
    assert bc[8].endswith("(../long20k/TABLE.md)")  # relative to grid/TABLE.md


def test_the_aggregate_gets_a_row_per_longer_budget(grids):
    short, longer = grids
    text = run_grid.render_table(short, (longer,)).read_text()
    row = next(line for line in text.splitlines() if line.startswith("| BC at 20k steps |"))
    scores = np.array([[json.loads(run_grid.result_path(longer, "bc", t, s).read_text())
                        ["final_normalized_score_mean"] for t in TASKS] for s in (0, 1)])
    iqm, mean = stats.trim_mean(scores.reshape(-1), 0.25), scores.mean()
    assert abs(iqm - mean) > 1.0  # the check below can tell the two apart
    assert re.search(rf"\| 2 × 4 \| \*\*{iqm:.1f}\*\* \[[^]]*\] \| \*\*{mean:.1f}\*\* \[", row), (row, iqm, mean)
    assert any(line.startswith("| BC | 2 × 4 | **30.5**") for line in text.splitlines())
    assert (short / "plots" / "aggregate.png").stat().st_size > 0


def test_a_tels_row_says_its_beta_where_the_grids_trained_at_different_betas(grids):
    """The TELS rows of the aggregate name their β only when the grids differ in it (here 1 at 5k, 0.01 at 20k)."""
    short, longer = grids
    for task in TASKS:
        for seed in (0, 1):
            _write(short, "tels", task, {**_record(seed, 5000, 500, lambda s: 20.0), "beta": 1.0})
            _write(longer, "tels", task, {**_record(seed, 20000, 2000, lambda s: 25.0), "beta": 0.01})
    labels = [line.split(" | ")[0] for line in run_grid.render_table(short, (longer,)).read_text().splitlines()
              if line.startswith("| TELS")]
    assert "| TELS, β = 1" in labels and "| TELS at 20k steps, β = 0.01" in labels
    for task in TASKS:
        for seed in (0, 1):
            _write(longer, "tels", task, {**_record(seed, 20000, 2000, lambda s: 25.0), "beta": 1.0})
    labels = [line.split(" | ")[0] for line in run_grid.render_table(short, (longer,)).read_text().splitlines()
              if line.startswith("| TELS")]
    assert "| TELS" in labels and "| TELS at 20k steps" in labels


def test_two_longer_folders_at_one_budget_keep_a_row_each(grids, tmp_path):
    short, longer = grids
    twin = tmp_path / "twin"
    for task in TASKS:
        for seed in (0, 1):
            _write(twin, "bc", task, _record(seed, 20000, 2000, lambda s: 99.0))
    text = run_grid.render_table(short, (longer, twin)).read_text()
    lines = _section(text, "Aggregate over the four shared sets").splitlines()
    rows = [line for line in lines if line.startswith("| BC at 20k steps")]
    assert len(rows) == 2 and "**99.0**" in rows[1] and "twin" in rows[1] and "**99.0**" not in rows[0]


def test_a_missing_longer_folder_is_one_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        run_grid.parse_args(["--table", "--longer", str(tmp_path / "nowhere")])
    assert "--longer folder(s) not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run_grid.parse_args(["--method", "bc", "--task", TASKS[0], "--seed", "0", "--longer", str(tmp_path)])
    assert "--longer only applies to --table" in capsys.readouterr().err


def test_a_table_of_changed_baselines_names_the_change(grids):
    short, _ = grids
    assert "Changed from the baselines' defaults" not in run_grid.render_table(short).read_text()
    for seed in (0, 1):
        _write(short, "iql", TASKS[1], _record(seed, 5000, 500, lambda s: 20.0, reward_scale="return_range"))
    text = run_grid.render_table(short).read_text()
    assert "**Changed from the baselines' defaults:** IQL `reward_scale=return_range`." in text


def test_each_method_is_read_at_its_longest_budget_with_every_verdict(grids):
    short, longer = grids
    for i, task in enumerate(TASKS):
        for seed in (0, 1):
            # TD3+BC still rising at 5k; at 20k it rises until 10k and is flat at 10 i² + seed after it, so
            # its second-half score is exactly that while the mean of all ten evaluations is lower
            _write(short, "td3bc", task, _record(seed, 5000, 500, lambda s: s / 100.0))
            _write(longer, "td3bc", task, _record(seed, 20000, 2000,
                                                  lambda s: 10.0 * i**2 + seed - max(0.0, 10000 - s) / 1000.0))
    text = run_grid.render_table(short, (longer,)).read_text()
    task = TASKS[0]
    # BC at 20k: seed 0 is 2e-4 s, read over 12k..20k (mean step 16k), seed 1 is 1
    assert _row(text, LONGEST, task, "BC")[2:] == ["5k: flat · 20k: flat", "20k", "**2.1** ± 1.1 (n=2)"]
    assert _row(text, LONGEST, task, "TD3+BC")[2:] == ["5k: **still rising** · 20k: flat", "20k",
                                                    "**0.5** ± 0.5 (n=2)"]
    # flat over a short run, falling over a longer one: read at the longer, marked
    assert _row(text, LONGEST, task, "IQL")[2:] == ["5k: flat · 20k: **still falling**", "20k (**still falling**)",
                                                "**32.0** ± 0.0 (n=2)"]
    # two evaluations are too few to judge: the longest budget, marked, read at its later evaluation
    assert _row(text, LONGEST, task, "TELS")[2:] == ["4k: too few evaluations", "4k (too few evaluations)",
                                                 "**1.0** ± 0.0 (n=2)"]
    scores = np.array([[10.0 * i**2 + seed for i in range(len(TASKS))] for seed in (0, 1)])
    iqm, mean = stats.trim_mean(scores.reshape(-1), 0.25), scores.mean()
    section = _section(text, LONGEST)
    row = next(line for line in section.splitlines() if line.startswith("| TD3+BC at 20k steps |"))
    assert re.search(rf"\| 2 × 4 \| \*\*{iqm:.1f}\*\* \[[^]]*\] \| \*\*{mean:.1f}\*\* \[", row), (row, iqm, mean)
    assert any(line.startswith("| TELS at 4k steps, too few evaluations on 4 of 4 |") for line in section.splitlines())
    assert (short / "plots" / "aggregate_longest_budget.png").stat().st_size > 0


def test_the_second_half_mean_reads_the_later_half_of_any_number_of_evaluations():
    from torchrl_tels.record import second_half_mean

    assert second_half_mean([{"score": s} for s in (0.0, 10.0, 2.0, 4.0)]) == 3.0
    assert second_half_mean([{"score": s} for s in (0.0, 2.0, 4.0)]) == 3.0  # the middle one counts as later
    assert np.isnan(second_half_mean([]))


@pytest.mark.parametrize("trend, zigzag, verdict", [(0.0, 0.1, "flat"), (0.0, 6.0, "no trend detected"),
                                                   (3e-4, 6.0, "no trend detected"),
                                                   (3e-3, 6.0, "**still rising**")])
def test_the_verdict_weighs_a_trend_against_the_scatter_of_the_evaluations(trend, zigzag, verdict):
    # one seed, evaluations every 2k to 20k: a line of slope `trend` per step plus a ±`zigzag` alternation,
    # whose scatter about the fitted line sets the band (checked against scipy's regression); no trend under
    # a wide scatter is not flat: the band does not exclude a move of 2 points
    run = _record(0, 20000, 2000, lambda s: 30.0 + trend * s + zigzag * (-1) ** (s // 2000))
    late = [e for e in run["evaluations"] if e["step"] >= 12000]
    fit = stats.linregress([e["step"] / 1000 for e in late], [e["score"] for e in late])
    slope_cell, verdict_cell, flat = run_grid.curve_verdict([run])
    rise, band = fit.slope * 8, 2 * fit.stderr * 8
    assert slope_cell == f"{fit.slope:+.2f} ({rise:+.1f} ± {band:.1f} across it)"
    assert verdict_cell == verdict and flat == (verdict == "flat")


def test_an_aggregate_over_one_seed_gives_no_interval():
    matrices = {"one seed": np.array([[10.0, 20.0, 30.0, 40.0]]), "two seeds": np.array([[10.0, 20.0], [12.0, 26.0]])}
    estimates = run_grid._interval_estimates(matrices)
    assert all(np.isnan(low) and np.isnan(high) for _, low, high in estimates["one seed"])
    one, two = run_grid._aggregate_rows(matrices, estimates)
    assert one == "| one seed | 1 × 4 | **25.0** (one seed: no interval) | **25.0** (one seed: no interval) |"
    # two seeds: the mean of the four scores, with an interval that is not a point
    low, high = map(float, re.findall(r"\[([\d.]+), ([\d.]+)\]", two)[1])
    assert "**17.0** [" in two and low < 17.0 < high


def test_the_scatter_is_split_into_episode_noise_and_the_rest():
    # two seeds, evaluations every 2k to 20k, each of four episodes at mean ± spread (so each episode variance
    # is known); the seed means zigzag ±3 (plus noise) about a line, which sets the residual variance
    rng = np.random.default_rng(0)
    spreads = {0: 2.0, 1: 4.0}
    runs = []
    for seed, spread in spreads.items():
        evaluations = []
        for step in range(2000, 20001, 2000):
            mean = 30.0 + 1e-3 * step + 3.0 * (-1) ** (step // 2000) + rng.normal()
            evaluations.append({"step": step, "score": mean, "scores": [mean - spread, mean + spread] * 2})
        runs.append({"seed": seed, "evaluations": evaluations})
    fit = run_grid.second_half_fit(runs)
    late = list(range(12000, 20001, 2000))
    means = [np.mean([e["score"] for r in runs for e in r["evaluations"] if e["step"] == s]) for s in late]
    x = np.array(late) / 1000
    residuals = np.array(means) - np.polyval(np.polyfit(x, means, 1), x)
    residual_var = (residuals**2).sum() / (len(late) - 2)
    # each run's episodes: variance (ddof 1) of [m-a, m+a, m-a, m+a] is 4a²/3, over 4 episodes; two runs
    noise_var = sum(4 * a**2 / 3 / 4 for a in spreads.values()) / 2**2
    assert run_grid.scatter_over_episode_noise(runs, fit) == pytest.approx(residual_var / noise_var)
    # one episode per evaluation leaves the episode noise unknown
    for r in runs:
        for e in r["evaluations"]:
            e["scores"] = e["scores"][:1]
    assert run_grid.scatter_over_episode_noise(runs, fit) is None


def test_a_longest_budget_keeps_protocols_and_hyperparameters_apart(grids, capsys):
    short, longer = grids
    task = TASKS[0]
    # a third BC seed at 20k evaluated on another protocol, and one without evaluations
    _write(longer, "bc", task, _record(2, 20000, 4000, lambda s: 70.0))
    _write(longer, "bc", task, {**_record(3, 20000, 2000, lambda s: 0.0), "evaluations": []})
    text = run_grid.render_table(short, (longer,)).read_text()
    assert "BC hopper-medium-v2-10k seed 3" in capsys.readouterr().err
    cells = _row(text, LONGEST, task, "BC")
    assert cells[2].count("20k (") == 2 and "10 ep. every 4k" in cells[2] and "10 ep. every 2k" in cells[2]
    assert cells[4] == "**70.0** (n=1)"  # the later protocol's one run (the order is fixed), never the two mixed
    iql = _row(text, LONGEST, task, "IQL")
    assert iql[3] == "20k (**still falling**)"  # every 20k IQL run has lr=1e-3: nothing differs among them
    _write(longer, "iql", task, _record(2, 20000, 2000, lambda s: 40.0 - 5e-4 * s))
    text = run_grid.render_table(short, (longer,)).read_text()
    assert _row(text, LONGEST, task, "IQL")[3] == "20k (**still falling**); **hyperparameters differ: lr**"
    assert "IQL at 20k steps, still falling on 4 of 4, **hyperparameters differ** |" in text


def test_table_command_renews_the_longer_grids_own_tables_it_links(grids):
    short, longer = grids
    (longer / "TABLE.md").write_text("a stale table\n")
    assert run_grid.main(["--table", "--results-dir", str(short), "--longer", str(longer)]) == 0
    linked = re.findall(r"\]\(([^)]*long20k/TABLE\.md)\)", (short / "TABLE.md").read_text())
    assert linked, "the grid's table links the longer grid's own table"
    own = (longer / "TABLE.md").read_text()
    # its first row, BC on the first task. The row's TELS runs have 2 evaluations and the others 10, so each run
    # is read over the later half of its evaluations (12k..20k): 2e-4 · 16,000 = 3.2 and 1.0
    row = next(line for line in own.splitlines() if line.startswith(f"| {TASKS[0]} | "))
    bc = [cell.strip() for cell in row.strip("|").split("|")][2]
    assert bc.startswith("**2.1** ± 1.1 (n=2)"), bc


def test_a_row_whose_runs_have_different_numbers_of_evaluations_reads_each_over_its_later_half(tmp_path):
    task = TASKS[0]
    # BC: 20 evaluations every 5k to 100k, rising 1 per 5k (its last 10 are its later half: 11..20, mean 15.5);
    # TELS: 10 evaluations every 2k to 20k, rising 10 per 2k (its last 10 are all of them, mean 55; the later
    # half 60..100, mean 80)
    _write(tmp_path, "bc", task, _record(0, 100000, 5000, lambda s: s / 5000))
    _write(tmp_path, "tels", task, _record(0, 20000, 2000, lambda s: 10 * s / 2000))
    row = [line for line in run_grid.render_table(tmp_path).read_text().splitlines() if line.startswith(f"| {task} |")]
    cells = [cell.strip() for cell in row[0].strip("|").split("|")]
    assert "later half" in cells[1]
    assert cells[2].startswith("**15.5** (n=1)")
    tels = cells[2 + run_grid.TABLE_COLUMNS.index("tels")]
    assert tels.startswith("**80.0** (n=1)"), tels
    # a row whose runs share their number of evaluations keeps each run's own final score
    _write(tmp_path, "tels", task, _record(0, 100000, 5000, lambda s: 2 * s / 5000))
    row = [line for line in run_grid.render_table(tmp_path).read_text().splitlines() if line.startswith(f"| {task} |")]
    cells = [cell.strip() for cell in row[0].strip("|").split("|")]
    assert "later half" not in cells[1]
    assert cells[2 + run_grid.TABLE_COLUMNS.index("tels")].startswith("**31.0** (n=1)")
