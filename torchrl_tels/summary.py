"""The table a paper needs from any set of run folders: per dataset and across datasets.

:func:`collect_runs` walks folders (a sweep's, or runs gathered by hand) for the recipe's run folders: every
folder with a ``config.yaml`` is a run; one with a ``results.json`` finished, one whose lock a live process
holds is running, any other unfinished (stopped or failed). :func:`summarize` turns the finished ones into,
per dataset, the mean normalized score, its 95 % Student-t interval over seeds and n
(:func:`torchrl_tels.stats.t_interval`), and across datasets the interquartile mean with a stratified-
bootstrap 95 % interval over the seeds every dataset has (:func:`torchrl_tels.stats.stratified_bootstrap_ci`).
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from torchrl_tels import stats
from torchrl_tels.errors import CheckpointError, ConfigError
from torchrl_tels.run_folder import RunFolder

__all__ = ["RunRecord", "Summary", "arms", "arms_csv", "collect_runs", "summarize"]


@dataclass
class RunRecord:
    folder: Path
    status: str                      # finished | running | unfinished
    dataset: str | None = None
    seed: int | None = None
    score: float | None = None       # final_normalized_score_mean
    settings: dict = field(default_factory=dict)  # what the run computed with, less its dataset and seed


#: config entries that say where and how a run executes, or which data and seed: not what sets arms apart
_NOT_ARM = ("seed", "seeds", "dataset", "run_dir", "resume", "overwrite", "threads", "device", "logger", "checkpoint",
            "compile", "monitor", "diagnostics", "precision")


def _flat(value, prefix: str = "") -> dict:
    if isinstance(value, dict):
        return {k: v for key, item in value.items() for k, v in _flat(item, f"{prefix}{key}.").items()}
    return {prefix[:-1]: json.dumps(value, sort_keys=True)}


@dataclass
class Summary:
    datasets: dict[str, dict] = field(default_factory=dict)  # dataset -> {mean, low, high, n, seeds}
    aggregate: dict | None = None      # {iqm, low, high, seeds, datasets}
    not_finished: list[RunRecord] = field(default_factory=list)

    def markdown(self) -> str:
        lines = ["| dataset | mean | 95 % interval | n | seeds |", "|---|---|---|---|---|"]
        for name, row in self.datasets.items():
            interval = "—" if math.isnan(row["low"]) else f"[{row['low']:.1f}, {row['high']:.1f}]"
            lines.append(f"| {name} | {row['mean']:.1f} | {interval} | {row['n']} | "
                         f"{', '.join(map(str, row['seeds']))} |")
        lines.append("")
        if self.aggregate is not None:
            a = self.aggregate
            interval = "no interval (one seed)" if math.isnan(a["low"]) else f"[{a['low']:.1f}, {a['high']:.1f}]"
            lines.append(f"Across {len(a['datasets'])} datasets × {len(a['seeds'])} seeds (seeds {a['seeds']}, the "
                         f"ones every dataset has): IQM **{a['iqm']:.1f}** {interval}, stratified bootstrap, 95 %.")
        else:
            lines.append("Across datasets: no IQM (fewer than two datasets, or no seed that every dataset has).")
        lines.append("")
        if self.not_finished:
            lines += ["Not finished, left out:", ""]
            lines += [f"- {r.folder} ({r.status})" for r in self.not_finished]
        else:
            lines.append("Every run found finished.")
        return "\n".join(lines) + "\n"

    def csv(self) -> str:
        out = io.StringIO()
        writer = csv.writer(out)
        writer.writerow(["dataset", "mean", "low", "high", "n", "seeds"])
        for name, row in self.datasets.items():
            writer.writerow([name, row["mean"], row["low"], row["high"], row["n"], " ".join(map(str, row["seeds"]))])
        if self.aggregate is not None:
            a = self.aggregate
            writer.writerow(["IQM over datasets", a["iqm"], a["low"], a["high"], len(a["seeds"]) * len(a["datasets"]),
                             " ".join(map(str, a["seeds"]))])
        return out.getvalue()

    def plot(self, path: Path, title: str = "") -> Path:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        names = list(self.datasets)
        fig, ax = plt.subplots(figsize=(max(4.0, 1.2 * len(names)), 3.5))
        for i, name in enumerate(names):
            row = self.datasets[name]
            ax.scatter([i] * len(row["scores"]), row["scores"], color="gray", s=12, zorder=2)
            err = None if math.isnan(row["low"]) else [[row["mean"] - row["low"]], [row["high"] - row["mean"]]]
            ax.errorbar([i], [row["mean"]], yerr=err, fmt="o", color="C0", capsize=4, zorder=3)
        ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel("normalized score")
        text = (f"{title}: " if title else "") + "mean and 95 % t-interval over seeds (dots: seeds)"
        # wrapped to the figure's width (about 11 characters an inch at 9 pt, centred over the axes), so none of it is cut off
        ax.set_title(textwrap.fill(text, width=int(11 * fig.get_figwidth())), fontsize=9)
        fig.tight_layout()
        tmp = path.with_name(f".{path.name}.tmp.png")
        fig.savefig(tmp, dpi=120)
        plt.close(fig)
        os.replace(tmp, path)
        return path


def collect_runs(folders) -> list[RunRecord]:
    """Every recipe run folder under ``folders`` (each a run folder or a folder holding some), with its status.

    A ``seeds=[...]`` run counts as its seeds' folders (``seed<k>/``), not as the folder that aggregates them.
    """
    records = []
    for top in map(Path, folders):
        if not top.is_dir():
            raise ConfigError(f"{top} is not a folder.")
        for run in RunFolder.find(top):
            status = run.status()
            record = RunRecord(run.path, status)
            if status == "finished":
                try:
                    results = run.read_results()
                    record.dataset, record.seed = str(results["dataset"]), int(results["seed"])
                    record.score = float(results["final_normalized_score_mean"])
                    config = run.read_config()
                except (CheckpointError, ValueError, KeyError, TypeError, yaml.YAMLError) as err:
                    raise ConfigError(f"{run.path} is not a finished run's folder: {err!r}.") from None
                record.settings = _flat({k: v for k, v in config.items() if k not in _NOT_ARM}
                                        | {"dataset": {k: v for k, v in (config.get("dataset") or {}).items()
                                                       if k not in ("name", "task")}})
            records.append(record)
    return records


def arms(records: list[RunRecord]) -> dict[str, list[RunRecord]]:
    """The finished runs grouped by what they computed with (their config less dataset, seed and how they ran),
    each group labelled by the settings in which the groups differ ("all runs" when there is one group)."""
    finished = [r for r in records if r.status == "finished"]
    groups: dict[tuple, list[RunRecord]] = {}
    for r in finished:
        groups.setdefault(tuple(sorted(r.settings.items())), []).append(r)
    if len(groups) <= 1:
        return {"all runs": finished}
    keys = sorted({k for key in groups for k, _ in key})
    differing = [k for k in keys if len({dict(key).get(k) for key in groups}) > 1]
    return {", ".join(f"{k}={dict(key).get(k, 'unset')}" for k in differing): runs for key, runs in groups.items()}


def summarize(records: list[RunRecord], *, reps: int = 2000, seed: int = 0) -> Summary:
    """One arm's :class:`Summary` (pass the runs of one of :func:`arms`); runs not finished are listed."""
    finished = [r for r in records if r.status == "finished"]
    summary = Summary(not_finished=[r for r in records if r.status != "finished"])
    by_dataset: dict[str, dict[int, float]] = {}
    for r in finished:
        seeds = by_dataset.setdefault(r.dataset, {})
        if r.seed in seeds:
            raise ConfigError(f"two finished runs of {r.dataset} with seed {r.seed} (one is {r.folder}); "
                              "summarize one of them.")
        seeds[r.seed] = r.score
    for name in sorted(by_dataset):
        scores = [by_dataset[name][s] for s in sorted(by_dataset[name])]
        centre, low, high = stats.t_interval(scores)
        summary.datasets[name] = {"mean": centre, "low": low, "high": high, "n": len(scores),
                                  "seeds": sorted(by_dataset[name]), "scores": scores}
    common = sorted(set.intersection(*(set(v) for v in by_dataset.values()))) if by_dataset else []
    if len(by_dataset) >= 2 and common:
        names = sorted(by_dataset)
        matrix = np.array([[by_dataset[n][s] for n in names] for s in common])
        if len(common) > 1:
            point, low, high = stats.stratified_bootstrap_ci(matrix, stats.iqm, reps=reps, seed=seed)
        else:
            point, low, high = stats.iqm(matrix), math.nan, math.nan
        summary.aggregate = {"iqm": point, "low": low, "high": high, "seeds": common, "datasets": names}
    return summary


def arms_csv(summaries: dict[str, Summary]) -> str:
    """One CSV of every arm's per-dataset rows (:meth:`Summary.csv`), the arm's label as the first column."""
    out = io.StringIO()
    writer = csv.writer(out)
    for i, (label, summary) in enumerate(summaries.items()):
        header, *rows = csv.reader(io.StringIO(summary.csv()))
        if i == 0:
            writer.writerow(["arm", *header])
        writer.writerows([label, *row] for row in rows)
    return out.getvalue()
