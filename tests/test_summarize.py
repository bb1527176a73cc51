"""recipes/summarize.py: the table of any run folders, checked against independent computations."""
from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats as scipy_stats

from torchrl_tels.run_folder import claim_run_dir
from torchrl_tels.summary import collect_runs, summarize

REPO_ROOT = Path(__file__).resolve().parents[1]
SCORES = {"hopper-medium-v2-10k": [40.0, 50.0, 45.0], "walker2d-medium-v2-10k": [20.0, 35.0, 30.0, 90.0]}


def fake_run(folder: Path, dataset: str | None, seed: int, score: float | None, alpha: float = 1.0) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(f"seed: {seed}\nthreads: {seed}\nguide:\n  alpha: {alpha}\n"
                                        f"dataset:\n  name: {dataset}\n")
    if score is not None:
        (folder / "results.json").write_text(json.dumps({"dataset": dataset, "seed": seed,
                                                         "final_normalized_score_mean": score}))
    return folder


@pytest.fixture
def sweep(tmp_path):
    root = tmp_path / "sweep"
    for name, scores in SCORES.items():
        for seed, score in enumerate(scores):
            fake_run(root / f"{name}_{seed}", name, seed, score)
    fake_run(root / "died", None, 7, None)
    running = fake_run(root / "live", None, 8, None)
    return root, running


def t_interval(values):
    values = np.asarray(values)
    half = scipy_stats.t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values))
    return values.mean(), values.mean() - half, values.mean() + half


def test_summary_matches_independent_statistics(sweep):
    root, running = sweep
    with claim_run_dir(running, resume=True, overwrite=False):
        records = collect_runs([root])
    status = {r.folder.name: r.status for r in records}
    assert status["died"] == "unfinished" and status["live"] == "running"
    summary = summarize(records)
    for name, scores in SCORES.items():
        row = summary.datasets[name]
        assert row["n"] == len(scores)
        np.testing.assert_allclose((row["mean"], row["low"], row["high"]), t_interval(scores), rtol=1e-6)
    common = [[SCORES[n][s] for n in sorted(SCORES)] for s in range(3)]  # seed 3 is walker2d's only
    assert summary.aggregate["seeds"] == [0, 1, 2]
    assert summary.aggregate["iqm"] == pytest.approx(scipy_stats.trim_mean(np.ravel(common), 0.25))
    assert summary.aggregate["low"] <= summary.aggregate["iqm"] <= summary.aggregate["high"]
    text = summary.markdown()
    assert "died (unfinished)" in text and "live (running)" in text


def test_command_writes_markdown_csv_and_plot(sweep, tmp_path):
    root, _ = sweep
    out = tmp_path / "table"
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "recipes" / "summarize.py"), str(root), "--out", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["dataset"] for r in rows] == [*sorted(SCORES), "IQM over datasets"]
    assert float(rows[0]["mean"]) == pytest.approx(np.mean(SCORES[rows[0]["dataset"]]))
    assert (out / "summary.png").stat().st_size > 0 and "| hopper-medium-v2-10k | 45.0 |" in (out / "summary.md").read_text()
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "recipes" / "summarize.py"), str(empty)],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.startswith("error: no finished run") and not any(empty.iterdir())


def test_runs_with_other_settings_are_arms_of_their_own(sweep, tmp_path):
    root, _ = sweep
    for seed, score in enumerate([10.0, 12.0, 14.0]):  # the same sets and seeds at another alpha
        fake_run(root / f"alpha_{seed}", "hopper-medium-v2-10k", seed, score, alpha=0.01)
    out = tmp_path / "table"
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "recipes" / "summarize.py"), str(root), "--out", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    text = (out / "summary.md").read_text()
    assert "## guide.alpha=0.01" in text and "## guide.alpha=1.0" in text  # threads differ too, but say nothing
    rows = list(csv.DictReader((out / "summary.csv").open()))
    low = [r for r in rows if r["arm"] == "guide.alpha=0.01" and r["dataset"] == "hopper-medium-v2-10k"]
    assert float(low[0]["mean"]) == pytest.approx(12.0) and low[0]["n"] == "3"
    assert (out / "summary_arm0.png").exists() and (out / "summary_arm1.png").exists()


def test_summary_plot_title_is_not_cut_off(tmp_path):
    """At the plot's default size (one or two datasets: the narrowest figure), the whole title lies inside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_tels.summary import Summary

    summary = Summary(datasets={"hopper-medium-v2-10k": {"mean": 40.0, "low": 35.0, "high": 45.0, "n": 3,
                                                          "seeds": [0, 1, 2], "scores": [38.0, 40.0, 42.0]}})
    opened = []
    original = plt.subplots

    def keep(*args, **kwargs):
        fig, ax = original(*args, **kwargs)
        opened.append(fig)
        return fig, ax

    plt.subplots = keep
    try:
        summary.plot(tmp_path / "summary.png", title="guide.alpha=0.01 tsidm.beta=1 on the hopper sets")
    finally:
        plt.subplots = original
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = opened[0]
    renderer = FigureCanvasAgg(fig).get_renderer()  # the plot closed its figure
    box, frame = fig.axes[0].title.get_window_extent(renderer), fig.bbox
    assert box.x0 >= frame.x0 and box.x1 <= frame.x1 and box.y1 <= frame.y1


def test_evaluation_plot_shows_each_evaluation_s_episodes(tmp_path, monkeypatch):
    """eval_scores.png's series: the mean line, every episode's score as a dot, and the band between the
    25th and 75th percentiles of each evaluation's episodes (checked against NumPy)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_tels.training import plot_curves

    episodes = {500: [10.0, 20.0, 30.0, 40.0], 1000: [50.0, 55.0, 90.0, 95.0]}
    opened = []
    original = plt.subplots
    monkeypatch.setattr(plt, "subplots", lambda *a, **k: opened.append(original(*a, **k)) or opened[-1])
    plot_curves({"score": [(s, float(np.mean(v))) for s, v in episodes.items()]}, tmp_path / "eval_scores.png",
                title="t", spread={"score": list(episodes.items())})
    _, ax = opened[0]
    (dots,) = ax.collections[1:2]
    assert sorted(map(tuple, dots.get_offsets().tolist())) == sorted((s, x) for s, v in episodes.items() for x in v)
    band = ax.collections[0].get_paths()[0].vertices
    for step, values in episodes.items():
        at = band[np.isclose(band[:, 0], step), 1]
        assert np.isclose(at.min(), np.percentile(values, 25)) and np.isclose(at.max(), np.percentile(values, 75))
    assert (tmp_path / "eval_scores.png").stat().st_size > 0
