"""The GPU check's table, from what ``benchmarks/gpu_check.sh`` wrote on the lent machine.

    python -m benchmarks.gpu_table benchmarks/results/gpu/2026-12-04

reads the folder's ``walls.txt`` (name, exit code, wall seconds per run; a later line for a name
replaces an earlier one), ``gpu.txt``, ``tests.txt``, each run's ``results.json`` where the run
finished, and otherwise its log: a run stopped at its time cap still shows, in its last progress
bar of each stage, how many steps it made in how long. Writes ``GPU.md`` into the folder.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from torchrl_tels.run_folder import RunFolder

# tqdm's bar: "<desc>: 41%|...| 14612/36000 [02:46<04:10, 85.49it/s, ...]" (elapsed as mm:ss or h:mm:ss)
PROGRESS = re.compile(r"(?P<stage>stage [12])\b[^|\n]*?:\s+\d+%\|[^|]*\|\s*(?P<n>\d+)/(?P<total>\d+) "
                      r"\[(?P<elapsed>[\d:]+)<")
RUNS = (("paper_seed0", "paper budget (about 36k TS-IDM + 100k policy steps, 20 evaluations), 1 seed"),
        ("paper_seeds5", "paper budget, 5 seeds stacked in one process"),
        ("study_seed0", "study budget (3k TS-IDM + 5k policy steps), 1 seed"),
        ("study_seeds5", "study budget, 5 seeds stacked in one process"),
        # run by the 2026-12-04 version of gpu_check.sh (commit 49f4638) only
        ("shrink_free", "stage 1 alone, 36k steps, free latent (two such runs at once)"),
        ("shrink_standardized", "stage 1 alone, 36k steps, standardized latent (two such runs at once)"))


def seconds(clock: str) -> int:
    """tqdm's elapsed time ("02:46" or "1:02:46") in seconds."""
    total = 0
    for part in clock.split(":"):
        total = 60 * total + int(part)
    return total


def stage_progress(log: str) -> dict[str, tuple[int, int, int]]:
    """Per stage (1, 2), the last progress bar's (steps done, steps planned, elapsed seconds)."""
    last = {}
    for line in log.replace("\r", "\n").splitlines():
        for match in PROGRESS.finditer(line):
            last[match["stage"]] = int(match["n"]), int(match["total"]), seconds(match["elapsed"])
    return last


def read_walls(folder: Path) -> dict[str, tuple[int, int]]:
    walls = {}
    if not (folder / "walls.txt").exists():  # the check stopped before its first run
        return walls
    for line in (folder / "walls.txt").read_text().splitlines():
        name, code, wall = line.split()
        walls[name] = int(code), int(wall)  # the last line of a name is its last run
    return walls


EVAL_SECONDS = re.compile(r"eval_s=(\d+)")
MODE_LABELS = {"eager": "eager", "compile": "`compile.compile=true`", "cudagraphs": "`compile.cudagraphs=true`",
               "compile+cudagraphs": "both"}


def evaluation_seconds(log: str) -> int | None:
    """The evaluations' wall seconds so far, from the last stage-2 progress bar's ``eval_s``."""
    found = EVAL_SECONDS.findall(log)
    return int(found[-1]) if found else None


def speed_table(path: Path) -> list[str]:
    """``benchmarks.compile_speed``'s figures (``--json``) as a table: steps/s per stage and mode."""
    if not path.exists():
        return ["Not measured: the check wrote no " + path.name + "."]
    figures = json.loads(path.read_text())
    stages = figures["stages"]
    modes = [mode for mode in MODE_LABELS if any(mode in by_mode for by_mode in stages.values())]
    args = figures["args"]
    lines = [f"`python -m benchmarks.compile_speed --device {args['device']} --seeds {args['seeds']} "
             f"--steps {args['steps']} --repeats {args['repeats']}`: train steps per second at the recipe's widths, "
             f"evaluations excluded, median of {args['repeats']} interleaved blocks after {args['warmup']} warm-up "
             "steps (compilation and graph capture; their seconds in brackets).", "",
             "| stage | " + " | ".join(MODE_LABELS[m] for m in modes) + " |",
             "|---|" + "---|" * len(modes)]
    for stage, by_mode in stages.items():
        cells = [f"{by_mode[m]['steps_per_s']:,.0f} ({by_mode[m]['warmup_s']:.0f} s)" if m in by_mode else "—"
                 for m in modes]
        lines.append(f"| {'1 (TS-IDM)' if stage == 'tsidm' else '2 (V + guide)'} | " + " | ".join(cells) + " |")
    return lines


def stage_cell(progress: dict, stage: str) -> str:
    if stage not in progress:
        return "—"
    done, planned, elapsed = progress[stage]
    rate = f"{done / elapsed:.1f}" if elapsed else "—"
    return f"{rate} ({done:,}/{planned:,} steps in {elapsed} s)"


def shown(folder: Path) -> str:
    """The folder as the command to regenerate it names it: relative to the repository where it can be."""
    try:
        return folder.resolve().relative_to(Path(__file__).resolve().parents[1]).as_posix()
    except ValueError:
        return folder.as_posix()


def render(folder: Path) -> str:
    walls = read_walls(folder)
    read = lambda name: (folder / name).read_text().strip() if (folder / name).exists() else "not run"
    tests = read("tests.txt").splitlines()
    lines = [f"# GPU check, {folder.name}", "",
             f"Generated by `python -m benchmarks.gpu_table {shown(folder)}` from the files "
             "`bash benchmarks/gpu_check.sh` wrote on a lent GPU machine; do not edit.", "",
             f"- machine: {read('gpu.txt')} (nvidia-smi: name, memory, driver)",
             f"- the tests that use CUDA there: {tests[-1] if tests else 'no output'}", "",
             "## Train steps per second, by mode", "", *speed_table(folder / "compile_speed.json"), "",
             "## Whole runs", "",
             f"Mode: {read('mode.txt')} (the fastest above). Steps per second are the mean over the run so far "
             "(steps done / elapsed), read from the last progress bar of each stage; stage 2's includes its "
             "evaluations, whose seconds so far the next column gives. A run stopped at its time cap (exit 124) "
             "shows how far it got.", "",
             "| run | exit | wall s | stage 1 steps/s | stage 2 steps/s (with evaluations) | evaluations s | "
             "final score |",
             "|---|---|---|---|---|---|---|"]
    for name, label in RUNS:
        if name not in walls:
            continue
        code, wall = walls[name]
        log = folder / f"{name}.log"
        text = log.read_text(errors="replace") if log.exists() else ""
        progress = stage_progress(text)
        evaluations = evaluation_seconds(text)
        score = "did not finish"
        run = RunFolder(folder / name)
        if run.is_finished:
            r = run.read_results()
            score = f"{r.get('final_normalized_score_mean', r.get('final_score_mean', float('nan'))):.1f}"
        elif name.startswith("shrink"):
            score = "(stage 1 only)"
        lines.append(f"| {label} | {code} | {wall} | {stage_cell(progress, 'stage 1')} | "
                     f"{stage_cell(progress, 'stage 2')} | {'—' if evaluations is None else evaluations} | {score} |")
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    args = parser.parse_args()
    text = render(args.folder)
    (args.folder / "GPU.md").write_text(text)
    print(text, end="")


if __name__ == "__main__":
    main()
