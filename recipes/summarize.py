"""The table of a sweep, or of any run folders: per dataset and across datasets.

    python recipes/summarize.py runs/multirun/2026-12-06_10-00-00
    python recipes/summarize.py runs/a runs/b runs/c --out runs/table

Reads the ``results.json`` of every recipe run folder under the folders given and writes, per dataset, the
mean normalized score, its 95 % t-interval over seeds and n, and across datasets the IQM with a
stratified-bootstrap 95 % interval (``torchrl_tels.summary``), as ``summary.md``, ``summary.csv`` and
``summary.png`` in ``--out`` (default: the first folder). Runs that computed with different settings (a sweep
over a hyperparameter) are arms: one table and one plot each (``summary_arm<i>.png``), labelled by the settings
that differ. Unfinished, failed and running runs are listed, not counted.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torchrl_tels.errors import TelsError
from torchrl_tels.summary import arms, arms_csv, collect_runs, summarize
from torchrl_tels.training import write_text


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path, help="run folders, or folders holding run folders")
    parser.add_argument("--out", type=Path, default=None,
                        help="where summary.{md,csv,png} go (default: the first folder)")
    args = parser.parse_args(argv)
    try:
        records = collect_runs(args.folders)
        if not any(r.status == "finished" for r in records):
            raise TelsError(f"no finished run under {', '.join(map(str, args.folders))} "
                            f"({len(records)} run folder(s) found, none with results.json).")
        groups = arms(records)
        unfinished = [r for r in records if r.status != "finished"]
        summaries = {label: summarize(runs + unfinished) for label, runs in groups.items()}
    except TelsError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out = args.out or args.folders[0]
    out.mkdir(parents=True, exist_ok=True)
    if len(summaries) == 1:
        (summary,) = summaries.values()
        markdown, table = summary.markdown(), summary.csv()
        summary.plot(out / "summary.png")
        plots = ["summary.png"]
    else:  # a sweep over settings: one table per arm, and a plot each
        markdown = "".join(f"## {label}\n\n{s.markdown()}\n" for label, s in summaries.items())
        table = arms_csv(summaries)
        plots = []
        for i, (label, s) in enumerate(summaries.items()):
            s.plot(out / f"summary_arm{i}.png", title=label)
            plots.append(f"summary_arm{i}.png")
    write_text(out / "summary.md", markdown)
    write_text(out / "summary.csv", table)
    print(markdown + f"written: {out / 'summary.md'}, summary.csv, {', '.join(plots)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
