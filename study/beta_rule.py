"""App. B.5's beta rule read two ways: which beta has the lowest TS-IDM training loss?

    python -m study.beta_rule --task hopper-medium-v2-10k --seed 0 --beta 0.1
    python -m study.beta_rule --report

The paper selects beta of Eq. (7) from {0.01, 0.1, 1} as "the one with the lowest TS-IDM
training loss". Eq. (7) is ell_rec + beta * (ell_dyn + ell_ode + ell_Tsym), so comparing that
weighted total across beta scales three of its four terms by the candidate itself and leans
toward the smallest beta whatever the model learned. The unweighted sum of the four terms
compares every candidate on the same objective. This script records both for each
(task, seed, beta), at the study's stage-1 budget (``tsidm.steps=3000``):

- it reuses the stage 1 of a full run of the study where one exists with that beta and seed
  (``beta0.01`` arm: beta = 0.01; ``reencode`` arm: beta = 1; stage 1 does not depend on stage-2
  options), and otherwise trains stage 1 alone (the recipe with a one-step stage 2) under
  ``runs/reproduction/beta_rule/``;
- it reads each term from the run's CSV scalars (logged every 100 steps) and averages the
  points in the last 10% of steps, the window the recipe's ``tsidm.beta=auto`` compares;
- it writes ``results/beta_rule/<task>/seed<k>_beta<b>.json`` (skipped if it exists, unless ``--force``).

``--report`` prints, per task and seed, both readings and the beta each picks.
"""
from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

from benchmarks.harness import command_line, machine_description, REPO, run_recipe, skip_existing, write_result
from torchrl_tels.run_folder import RunFolder

OUT = REPO / "study" / "results" / "beta_rule"
TSIDM_STEPS = 3000
TERMS = ("ell_rec", "ell_dyn", "ell_ode", "ell_tsym")
FULL_RUN_ARMS = {0.01: "beta0.01", 1.0: "reencode"}  # arms whose stage 1 ran at this beta and budget


def tail_mean(path: Path) -> float:
    """Mean of the logged points in the last 10% of stage-1 steps."""
    rows = [(int(step), float(value)) for step, value in csv.reader(path.open())]
    last = max(step for step, _ in rows)
    window = [value for step, value in rows if step > 0.9 * last]
    if last != TSIDM_STEPS or not window:
        raise ValueError(f"{path}: expected stage-1 scalars up to step {TSIDM_STEPS}, found up to {last}")
    return sum(window) / len(window)


def run_dir_for(task: str, seed: int, beta: float) -> Path:
    arm = FULL_RUN_ARMS.get(beta)
    if arm is not None:
        full = REPO / "runs" / "reproduction" / arm / task / f"seed{seed}"
        if (full / "csv" / "scalars" / "tsidm" / "ell_total.csv").exists():
            return full
    return REPO / "runs" / "reproduction" / "beta_rule" / task / f"seed{seed}_beta{beta:g}"


def record(task: str, seed: int, beta: float, threads: int, force: bool = False) -> None:
    out = OUT / task / f"seed{seed}_beta{beta:g}.json"
    if skip_existing(out, force):
        return
    run_dir = run_dir_for(task, seed, beta)
    scalars = run_dir / "csv" / "scalars" / "tsidm"
    command = None
    if not (scalars / "ell_total.csv").exists() or not RunFolder(run_dir).is_finished:
        # A one-step stage 2 with one episode: the recipe only needs to finish; nothing of it is read.
        command = run_recipe([
            f"dataset.name={task}", f"seed={seed}", f"run_dir={run_dir}", "resume=true", "logger.wandb_mode=disabled",
            f"tsidm.steps={TSIDM_STEPS}", f"tsidm.beta={beta:g}",
            "policy.steps=1", "eval.interval=1", "eval.episodes=1", "eval.last_n=1"], threads)
    recorded_beta = RunFolder(run_dir).read_results()["beta"]
    if abs(recorded_beta - beta) > 1e-12:
        raise ValueError(f"{run_dir} trained stage 1 with beta={recorded_beta}, not {beta}")
    terms = {name: tail_mean(scalars / f"{name}.csv") for name in TERMS}
    write_result(out, {
        "task": task, "seed": seed, "beta": beta, "tsidm_steps": TSIDM_STEPS, "terms": terms,
        "weighted_eq7": terms["ell_rec"] + beta * sum(terms[k] for k in TERMS[1:]),
        "unweighted_sum": sum(terms.values()),
        "run_dir": run_dir, "command": None if command is None else command_line(command),
        "date": time.strftime("%Y-%m-%d"), "machine": machine_description(),
    }, force)
    print(f"{task} seed {seed} beta {beta:g}: " + ", ".join(f"{k} {v:.4f}" for k, v in terms.items()))


def recorded() -> dict[tuple[str, int], dict[float, dict]]:
    """``{(task, seed): {beta: record}}`` of every recorded stage 1."""
    rows: dict[tuple[str, int], dict[float, dict]] = {}
    for path in sorted(OUT.glob("*/seed*_beta*.json")):
        result = json.loads(path.read_text())
        rows.setdefault((result["task"], result["seed"]), {})[result["beta"]] = result
    return rows


def picks(rows: dict[tuple[str, int], dict[float, dict]] | None = None) -> dict[tuple[str, int], tuple[float, float]]:
    """``{(task, seed): (beta of the lowest Eq. (7) as written, beta of the lowest unweighted sum)}``."""
    rows = recorded() if rows is None else rows
    return {key: (min(by_beta, key=lambda b: by_beta[b]["weighted_eq7"]),
                  min(by_beta, key=lambda b: by_beta[b]["unweighted_sum"])) for key, by_beta in sorted(rows.items())}


def report() -> str:
    """The table of every recorded (task, seed, beta), then the beta each reading picks per task and seed."""
    rows = recorded()
    lines = ["| task | seed | beta | ell_rec | ell_dyn | ell_ode | ell_Tsym | Eq. (7) weighted | unweighted sum |",
             "|---|---|---|---|---|---|---|---|---|"]
    chosen = picks(rows)
    lines_picks = []
    for (task, seed), by_beta in sorted(rows.items()):
        for beta, r in sorted(by_beta.items()):
            t = r["terms"]
            lines.append(f"| {task} | {seed} | {beta:g} | " + " | ".join(f"{t[k]:.4f}" for k in TERMS)
                         + f" | {r['weighted_eq7']:.4f} | {r['unweighted_sum']:.4f} |")
        weighted, unweighted = chosen[task, seed]
        lines_picks.append(f"- {task} seed {seed} (beta in {sorted(by_beta)}): weighted picks {weighted:g}, "
                           f"unweighted picks {unweighted:g}")
    return "\n".join([*lines, "", *lines_picks])


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--task")
    parser.add_argument("--seed", type=int)
    parser.add_argument("--beta", type=float, nargs="+", default=[0.01, 0.1, 1.0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--report", action="store_true", help="print the table of what is recorded")
    parser.add_argument("--force", action="store_true", help="rewrite results that exist")
    args = parser.parse_args()
    if args.report:
        print(report())
        return
    if args.task is None or args.seed is None:
        parser.error("--task and --seed are required unless --report is given")
    for beta in args.beta:
        record(args.task, args.seed, beta, args.threads, args.force)


if __name__ == "__main__":
    main()
