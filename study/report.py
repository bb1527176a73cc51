"""The reproduction report: does TELS reproduce the paper's Table 1, and if not, why? One page, from the JSONs.

    python -m study.report            # writes study/REPORT.md
    python -m study.report --check    # exit 1 if REPORT.md differs from what the JSONs give

REPORT.md is the answer for a reviewer: the verdict, Table 1 beside ours, the mechanism behind each finding
with the link to the generated table that shows it, two facts measured outside this repository
(``results/external/``), the deviations of the default and what each bought, and how to check one number.
Every number on the page is computed here from the result JSONs, through the readers the study and the
benchmarks already have (``summary``, ``budget``, ``latent_scale``, the readings' ``run_results``,
``benchmarks.run_grid``, ``torchrl_tels.stats``, ``benchmarks.data_size``, ``benchmarks.representations``);
the paper's values are ``benchmarks.run_grid.PAPER_TABLE1``. The prose is static; nothing is trained.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys

from benchmarks import data_size, representations, run_grid
from benchmarks.harness import recorded_cpu, write_generated
from study import (beta_rule, budget, domains, latent_scale, model_selection, oracle_choice, overview, summary,
                   value_delivery)
from torchrl_tels import stats
from torchrl_tels.record import second_half_mean

OUT = summary.HERE / "REPORT.md"
COMMAND = "python -m study.report"
EXTERNAL = summary.HERE / "results" / "external"
TSRL = EXTERNAL / "tsrl_hopper_medium_10k.json"
BASELINE_STRENGTH = EXTERNAL / "baseline_strength.json"
GRID = summary.GRID
LONGER_FOLDERS = run_grid.DEFAULT_LONGER  # the baseline grid at longer budgets (BENCHMARKS.md, "Longer runs")
TASKS = summary.TASKS
BASELINES = ("bc", "td3bc", "iql")
#: The default (``domain=mujoco``) at the study budget: latent_scale's "preset" arm, ``alpha1``.
DEFAULT_SOURCES = dict(latent_scale.ARMS)["preset"]
#: The same settings and seeds run on two kinds of CPU (Intel Xeon and AMD EPYC).
CPU_PAIR = ("alpha1", "alpha1_epyc")
PAPER_FULL = "paper_full"  # the paper's reading at the paper's budget (the recipe's default run of 2026-12-01)
HELD_OUT_SIZE = 100_000  # the HalfCheetah-v5 SAC set at its full 100k transitions (benchmarks/results/data_size)
CHECK_TASK, CHECK_SEED = "hopper-medium-v2-10k", 2
ENCODER_NAMES = {"tsidm": "TS-IDM", "ae": "autoencoder", "vae": "VAE", "contrastive": "InfoNCE"}
COLUMNS = ("tels_paper", "tels_default", *BASELINES)
HEADERS = ("TELS, paper's reading (`domain=paper`)", "TELS, default (`domain=mujoco`)", "BC", "TD3+BC", "IQL")


def _final(runs) -> list[float]:
    return [r["final_normalized_score_mean"] for r in runs]


def _by_seed(runs: dict[int, dict]) -> list[dict]:
    return [runs[s] for s in sorted(runs)]


def _grid_runs(method: str, task: str) -> list[dict]:
    """The baseline grid's runs of ``method`` on ``task`` at the study budget, in seed order."""
    return _by_seed(summary.seed_results(GRID / method / task, summary.on_grid_budget))


def _steps(run: dict) -> int:
    """The policy steps a run trained: the step of its last evaluation."""
    return run["evaluations"][-1]["step"]


class Data:
    """Everything the page reads, loaded once."""

    def __init__(self):
        self.grid = run_grid.load_results(GRID)
        longer = {folder: run_grid.load_results(folder) for folder in LONGER_FOLDERS}
        tasks = [t for t in run_grid.TASKS if t in self.grid] + sorted(t for t in self.grid if t not in run_grid.TASKS)
        self.picks = run_grid.longest_budget_picks(self.grid, longer, tasks, GRID)
        self.longest_matrices = run_grid.longest_budget_matrices(self.picks)
        self.study: dict[str, dict[str, list[dict]]] = {}  # {task: {column: runs}} at the study budget
        self.longer: dict[str, dict[str, list[dict]]] = {}  # {task: {column: runs}} at the longer budget
        for task in TASKS:
            self.study[task] = {"tels_paper": _grid_runs("tels", task),
                                "tels_default": _by_seed(latent_scale._runs(DEFAULT_SOURCES, task)),
                                **{m: _grid_runs(m, task) for m in BASELINES}}
            self.longer[task] = {
                "tels_paper": _by_seed(summary.seed_results(summary.HERE / "results" / PAPER_FULL / task, lambda r: True)),
                "tels_default": _by_seed(budget.runs(*budget.PAPER_BUDGET, task)),
                **{m: sorted(self.picks[task, m].runs, key=lambda r: r["seed"]) if (task, m) in self.picks else []
                   for m in BASELINES}}
        self.held_out_verdict = overview.held_out_verdict()  # the nine locomotion rows: the opening and its section
        self.antmaze_scores = overview.antmaze_scores()  # AntMaze 100k: the opening and its section
        self.held_out = {m: data_size.load().get((m, HELD_OUT_SIZE), {}) for m in data_size.METHODS}

    def study_scores(self, task: str, column: str) -> list[float]:
        return _final(self.study[task][column])

    def longer_scores(self, task: str, column: str) -> list[float]:
        """Second-half means (:func:`torchrl_tels.record.second_half_mean`): Table 1's reading at any budget."""
        return [second_half_mean(r["evaluations"]) for r in self.longer[task][column]]

    def study_matrix(self, column: str):
        """``[seeds, tasks]`` study-budget final scores of a column over the four sets, seeds every set has."""
        import numpy as np

        by_task = [{r["seed"]: r["final_normalized_score_mean"] for r in self.study[t][column]} for t in TASKS]
        seeds = sorted(set.intersection(*(set(d) for d in by_task)))
        return np.array([[d[s] for d in by_task] for s in seeds])

    def longest(self, method: str):
        """``(label, [seeds, tasks] matrix)`` of a method at its longest budgets (run_grid's aggregate)."""
        prefix = run_grid.LABELS[method] + " at "
        return next((label, m) for label, m in self.longest_matrices.items() if label.startswith(prefix))


def _estimate(matrix) -> tuple[float, float, float]:
    """IQM and its stratified-bootstrap 95 % interval, as the grid's and the study's aggregate tables give it."""
    return run_grid._interval_estimates({"m": matrix})["m"][0]


def _iqm_text(matrix) -> str:
    point, low, high = _estimate(matrix)
    return f"{point:.1f} [{low:.1f}, {high:.1f}]"


def _relation(matrix, other) -> str:
    """Where one IQM stands against another: above or below where their 95 % intervals are apart, else level."""
    (_, low, high), (_, other_low, other_high) = _estimate(matrix), _estimate(other)
    return "above" if low > other_high else "below" if high < other_low else "level with"


def _mean_text(matrix) -> str:
    """The mean over tasks × seeds and its stratified-bootstrap 95 % interval."""
    point, low, high = run_grid._interval_estimates({"m": matrix})["m"][1]
    return f"{point:.1f} [{low:.1f}, {high:.1f}]"


def _target(task: str) -> float:
    """The study's target on a set: Table 1's TELS mean minus its std."""
    mean, std = run_grid.PAPER_TABLE1[task]["tels"]
    return mean - std


# ----------------------------------------------------------------------------------------------- sections
def verdict(d: Data) -> list[str]:
    paper_tels = statistics.mean(run_grid.PAPER_TABLE1[t]["tels"][0] for t in TASKS)
    paper_bc = statistics.mean(run_grid.PAPER_TABLE1[t]["bc"][0] for t in TASKS)
    reached_study = [t for t in TASKS if statistics.mean(d.study_scores(t, "tels_default")) >= _target(t)]
    paper_budget = {t: d.longer_scores(t, "tels_default") for t in TASKS if d.longer_scores(t, "tels_default")}
    reached_paper = [t for t, s in paper_budget.items() if statistics.mean(s) >= _target(t)]
    bc_label, bc_long = d.longest("bc")
    tels_label, tels_long = d.longest("tels")
    full = d.longer_scores("hopper-medium-v2-10k", "tels_paper")
    word = ("Yes" if len(reached_study) == len(TASKS) or len(reached_paper) == len(TASKS)
            else "No" if not reached_study and len(reached_paper) <= 1 else "Only in part")
    named = lambda tasks: ", ".join(t.removesuffix("-v2-10k") for t in tasks) or "none"
    return [
        "## Verdict", "",
        f"**{word}.** Table 1's TELS averages {paper_tels:.1f} over the four D4RL-10k locomotion sets; ours, in the "
        f"default (`domain=mujoco`) at the study budget, averages {_mean_text(d.study_matrix('tels_default'))} over "
        f"{d.study_matrix('tels_default').shape[0]} seeds × {len(TASKS)} sets (95 % stratified-bootstrap intervals, "
        "`torchrl_tels/stats.py`; \"level\" below: the two intervals overlap). Its interquartile mean, "
        f"{_iqm_text(d.study_matrix('tels_default'))}, is {_relation(d.study_matrix('tels_default'), d.study_matrix('bc'))} "
        f"our BC's on the same files and budget, {_iqm_text(d.study_matrix('bc'))}, and "
        f"{_relation(d.study_matrix('tels_default'), d.study_matrix('tels_paper'))} the paper's reading's, "
        f"{_iqm_text(d.study_matrix('tels_paper'))}. The default reaches Table "
        f"1's mean − std on {len(reached_study)} of {len(TASKS)} sets ({named(reached_study)}). At the paper's budget, "
        f"one seed per set, the default reaches it on {len(reached_paper)} of {len(paper_budget)} "
        f"({named(reached_paper)}), and the paper's reading, run there on hopper-medium only, scores "
        + (f"{full[0]:.1f} against Table 1's {run_grid.PAPER_TABLE1['hopper-medium-v2-10k']['tels'][0]:.1f}. "
           if full else "nothing (no runs). ")
        + f"Our baselines are not where Table 1 has them: trained to its longest budget "
        f"({bc_label.removeprefix('BC at ')}) our BC averages {_mean_text(bc_long)}, where Table 1's BC averages "
        f"{paper_bc:.1f}, and its IQM, {_iqm_text(bc_long)}, is {_relation(bc_long, tels_long)} the default's at its "
        "own longest "
        f"({tels_label.removeprefix('TELS at ')}), {_iqm_text(tels_long)}. The study traces the gap to "
        "the values: learned from 10k transitions, they order states but not one state's alternatives, so the gain "
        "the guide promises is never delivered, and TELS acts much as BC does (mechanisms below).", "",
        *overview.held_out_verdict_line(d.held_out_verdict),
        *(line + "\n" for line in domains.verdict_lines()),
        "Details: [AntMaze and Adroit](#antmaze-and-adroit-beside-tables-1-and-6).", ""]


def _row_cells(scores_of, note_of) -> list[str]:
    return [stats.interval_cell(scores_of(c), note_of(c)) for c in COLUMNS]


def table1(d: Data) -> list[str]:
    lines = ["## Table 1, side by side", "",
             "| set | scores | " + " | ".join(HEADERS) + " |", "|---|---|" + "---|" * len(COLUMNS)]
    not_flat: dict[str, list[str]] = {}
    for task in TASKS:
        paper = run_grid.PAPER_TABLE1[task]
        paper_cells = [f"{paper['tels'][0]:.1f} ± {paper['tels'][1]:.1f}", ""] + [
            f"{paper[m][0]:.1f} ± {paper[m][1]:.1f}" for m in BASELINES]
        lines.append(f"| {task} | Table 1 | " + " | ".join(paper_cells) + " |")
        lines.append("| | ours, study budget | " + " | ".join(_row_cells(lambda c: d.study_scores(task, c),
                                                                        lambda c: "")) + " |")

        def note(column: str) -> str:
            runs = d.longer[task][column]
            if not runs:
                return ""
            text = run_grid._steps_label(_steps(runs[0]))
            if column in BASELINES and not d.picks[task, column].flat:
                verdict_ = d.picks[task, column].verdict.strip("*")
                not_flat.setdefault(verdict_, []).append(f"{run_grid.LABELS[column]} on {task.removesuffix('-v2-10k')}")
                if verdict_ != "no trend detected":
                    text += f", {verdict_}"
            return text

        lines.append("| | ours, longer | " + " | ".join(_row_cells(lambda c: d.longer_scores(task, c), note)) + " |")
    held = [sorted(d.held_out.get("tels", {}).items()), sorted(d.held_out.get("bc", {}).items())]
    if any(held):
        scores = {"tels_paper": [], "tels_default": [s for _, s in sorted(d.held_out.get("tels", {}).items())],
                  **{m: [s for _, s in sorted(d.held_out.get(m, {}).items())] for m in BASELINES}}
        lines.append(f"| halfcheetah-v5 SAC medium, {HELD_OUT_SIZE // 1000}k (not in Table 1) | ours, study budget | "
                     + " | ".join(stats.interval_cell(scores[c]) for c in COLUMNS) + " |")
    else:
        lines.append(f"| halfcheetah-v5 SAC medium, {HELD_OUT_SIZE // 1000}k | no runs |" + " |" * len(COLUMNS))
    no_trend = not_flat.get("no trend detected", [])
    moving = {v: cells for v, cells in not_flat.items() if v != "no trend detected"}
    cells_longer = sum(1 for t in TASKS for m in BASELINES if (t, m) in d.picks)
    budget_ = dict(item.split("=") for item in summary.SHARED_BUDGET)
    study_steps = lambda key: run_grid._steps_label(int(budget_[key]))
    longer_runs = [r for t in TASKS for runs in d.longer[t].values() for r in runs]
    readings = {}  # {policy steps: number of evaluations} of the longer runs
    for r in longer_runs:
        readings.setdefault(_steps(r), len(r["evaluations"]))
    baseline_steps = sorted({_steps(r) for t in TASKS for m in BASELINES for r in d.longer[t][m]})
    lines += [
        "",
        "Table 1's values are as the paper prints them (`benchmarks.run_grid.PAPER_TABLE1`): mean ± std over seeds at "
        f"{run_grid._steps_label(run_grid.PAPER_POLICY_STEPS)} policy steps, no interval, one TELS column. "
        "Ours: the mean over seeds, its 95 % Student-t interval, mean ± t(0.975, n − 1)·s/√n with s the seeds' sample "
        "standard deviation (`torchrl_tels.stats.t_interval`), and n. A t-interval, because with three seeds a "
        "bootstrap can draw only ten distinct resamples and its interval stays inside the seeds' range, understating "
        "how little three seeds pin down; n=1 gets no interval. "
        f"**Study budget**: {study_steps('tsidm.steps')} TS-IDM and {study_steps('optim.steps')} policy steps "
        f"(baselines: {study_steps('optim.steps')}), an evaluation of {budget_['eval.episodes']} episodes every "
        f"{budget_['eval.interval']} steps, the score the mean of all of them; TELS in the paper's reading is the baseline grid's TELS "
        f"([TABLE.md](../benchmarks/results/TABLE.md)), the default is the `{DEFAULT_SOURCES[0]}` arm "
        "([RESULTS.md](RESULTS.md#every-arm-per-task)). "
        f"**Longer**: TELS at the paper's whole budget, {run_grid._steps_label(run_grid.PAPER_POLICY_STEPS)} policy "
        "steps (`paper_full`: the paper's reading, the recipe's default run of the time; `paper_budget_preset`: the "
        "default, `budget=paper`); each baseline at the longest budget it was run at, "
        + " or ".join(run_grid._steps_label(n) for n in baseline_steps) + " policy steps ([TABLE.md, \"Each method "
        "at its longest budget\"](../benchmarks/results/TABLE.md#each-method-at-its-longest-budget)). The score is "
        "then the mean of the later half of the evaluations, as Table 1 reads its runs: "
        + ", ".join(f"the last {n - n // 2} of {n} at {run_grid._steps_label(steps)}"
                    for steps, n in sorted(readings.items(), reverse=True)) + ". "
        f"No baseline's longest curve passes the grid's flatness test (its trend ± twice its standard error within "
        f"{run_grid.FLAT_POINTS:g} points): on {len(no_trend)} of {cells_longer} cells the test detects no trend but "
        "cannot call the curve flat (the evaluations' scatter leaves bands several points wide)"
        + "".join(f"; {', '.join(cells)}: {verdict_}" for verdict_, cells in sorted(moving.items()))
        + ". The halfcheetah-v5 row is the HalfCheetah-v5 SAC set at its full size, evaluated on HalfCheetah-v5 with "
        "the halfcheetah references ([DATA_SIZE.md](../benchmarks/results/data_size/DATA_SIZE.md); its TELS ran the "
        "recipe's default of its date, `budget=study`); nothing ran on it at a longer budget or in the paper's "
        "reading.", ""]
    return lines


def _share(values: list[float]) -> str:
    return f"{min(values):+.3f} to {max(values):+.3f}"


def mechanisms(d: Data) -> list[str]:
    # Eq. (7)'s symmetry: the latent shrinks under the free scale; the fixes against the default.
    shrink = json.loads((summary.HERE / "results" / "latent_shrink" / "free" / "seed0.json").read_text())
    rms = shrink["history"]["latent_rms"]
    fixes = {label: _estimate(_arm_matrix(sources)) for label, sources in latent_scale.ARMS
             if label in ("standardized", "relative", "TSRL-style weighting")}
    default_iqm = _estimate(d.study_matrix("tels_default"))[0]
    # Eq. (9)'s promise, on the 20k default runs read.
    delivery = [r for (arm, _, _), r in latent_scale.run_results(value_delivery.RESULTS).items() if arm == "long20k"]
    # V's local rank against the ceiling, hopper and walker2d readings at the 100-step horizon.
    local = [r["local"] for (arm, task, _), r in latent_scale.run_results(model_selection.RESULTS).items()
             if arm == "long20k" and task.startswith(("hopper", "walker2d")) and r.get("local")]
    pooled = oracle_choice.pooled(latent_scale.run_results(oracle_choice.RESULTS))
    oracle = {key: v for key, v in pooled.items() if key[1] == max(k[1] for k in pooled)}  # the longest lookahead
    shorter = {key: v for key, v in pooled.items() if key not in oracle}
    # Representations: IQL on each encoder's latents, the mean over the four sets.
    found = representations._scores(representations.RESULTS)
    encoder_means = {e: statistics.mean(statistics.mean(found[e, t]) for t in representations.TASKS)
                     for e in representations.ENCODERS if all(found[e, t] for t in representations.TASKS)}
    # Data size: TELS (default) − BC per size, paired over seeds.
    sizes = data_size.load()
    gaps = {size: statistics.mean(sizes["tels", size][s] - sizes["bc", size][s]
                                  for s in sorted(set(sizes["tels", size]) & set(sizes["bc", size])))
            for size in data_size.SIZES if ("tels", size) in sizes and ("bc", size) in sizes}
    # More budget: the default at the paper's budget, and at its longest grid budget against BC.
    fell = {t: sum(max(e["lengths"]) < budget.EPISODE_STEPS for r in d.longer[t]["tels_default"] for e in r["evaluations"])
            for t in TASKS if d.longer[t]["tels_default"]}
    evaluations = {t: sum(len(r["evaluations"]) for r in d.longer[t]["tels_default"]) for t in fell}
    below = [t for t in fell if statistics.mean(d.longer_scores(t, "tels_default")) < statistics.mean(d.study_scores(t, "tels_default"))]
    tels_label, tels_long = d.longest("tels")
    bc_label, bc_long = d.longest("bc")
    hopper_falls = ", ".join(f"{fell[t]} of {evaluations[t]} evaluations on {t.removesuffix('-v2-10k')}"
                             for t in fell if t.startswith("hopper"))
    return [
        "## What the study found, mechanism by mechanism", "",
        "**Eq. (7) has a latent-scale symmetry.** Scaling the latent by any c > 0, with the maps around it rescaled "
        "to match, leaves ℓ_rec and ℓ_ode unchanged and multiplies ℓ_dyn and ℓ_Tsym by c² (`TSIDMLoss`'s docstring), "
        "so stage 1 can lower Eq. (7) by shrinking the latent space instead of learning dynamics: under Eq. (7) as "
        f"written its RMS spread fell from {rms[0][1]:.3f} at step {rms[0][0]} to "
        f"{latent_scale._around(rms, shrink['steps']):.3f} after {shrink['steps'] // 1000}k steps (hopper-medium, one "
        "seed). The fixes that remove the symmetry score "
        + ("below" if all(iqm < default_iqm for iqm, _, _ in fixes.values()) else "not consistently better than")
        + " the default over the four sets (IQM "
        + ", ".join(f"{label} {iqm:.1f}" for label, (iqm, _, _) in fixes.items())
        + f", against {default_iqm:.1f}), so the default keeps Eq. (7) as written, with β = 0.01 chosen on scores "
        "([RESULTS.md](RESULTS.md#the-latent-scale-fixes-of-eq-7)).", "",
        "**The value gain Eq. (9) promises is not delivered.** On the default's 20k-step runs read "
        f"({len(delivery)}), V at the guide's proposal is above V where the data's own action leads by a median of "
        f"{_share([r['promised']['median'] for r in delivery])} of V's spread, while the state the actor reaches gains "
        f"{_share([r['delivered']['median'] for r in delivery])}; V ranks the data's states by return-to-go "
        f"(rank correlation {min(r['value']['rank_with_return_to_go'] for r in delivery):.2f} to "
        f"{max(r['value']['rank_with_return_to_go'] for r in delivery):.2f}), so the promise is V's extrapolation to "
        "latents no action reaches ([RESULTS.md](RESULTS.md#is-the-value-the-guide-promises-delivered)).", "",
        "**The improvement is there, one step away, and no learned value sees it.** Among the actor's latent "
        f"action and {model_selection.CANDIDATES - 1} perturbations of it, V's rank correlation with the return that follows is "
        f"{min(r['value_rank'] for r in local):.2f} to {max(r['value_rank'] for r in local):.2f} on the hopper and "
        f"walker2d runs read, where the ceiling of any ranking (the same returns after first actions nudged by "
        f"{model_selection.NUDGE:.0%} of the action box's half-width) "
        f"is {min(r['repeat_rank'] for r in local):.2f} to {max(r['repeat_rank'] for r in local):.2f} "
        "([RESULTS.md](RESULTS.md#can-the-ts-idms-forward-model-choose-an-action-that-delivers)); IQL's Q and a Q "
        "fitted to the data's own returns also stay far below that ceiling ([RESULTS.md](RESULTS.md#does-a-q-iqls-or-one-fitted-to-the-"
        "datas-returns-order-one-steps-alternatives)). An oracle choosing among the same candidates by the "
        f"simulator's {next(iter(oracle))[1]}-step return beats the actor by "
        + ", ".join(f"{relative:+.0%} on {task.removesuffix('-v2-10k')} ({up} of {n} episodes up)"
                    for (task, _), (_, relative, up, n) in oracle.items())
        + "; with shorter lookaheads it loses ("
        + ", ".join(f"{relative:+.0%} at {lookahead} steps on {task.removesuffix('-v2-10k')}"
                    for (task, lookahead), (_, relative, _, _) in shorter.items())
        + ") ([RESULTS.md](RESULTS.md#what-would-a-perfect-value-gain-from-one-steps-alternatives)).", "",
        "**T-symmetry adds nothing to the representation here.** IQL on the frozen latents of each encoder, mean over "
        "the four sets: " + ", ".join(f"{ENCODER_NAMES.get(e, e)} {m:.1f}" for e, m in encoder_means.items())
        + "; the TS-IDM's latent is "
        + ("no better than" if encoder_means.get("tsidm", 0) <= encoder_means.get("ae", 0) else "above")
        + " a plain autoencoder's "
        "([REPRESENTATIONS.md](../benchmarks/results/representations/REPRESENTATIONS.md)).", "",
        "**Less data does not favour TELS.** On nested subsets of the HalfCheetah-v5 SAC set, TELS (default) minus BC "
        f"is below zero at {sum(g < 0 for g in gaps.values())} of {len(gaps)} sizes from {min(gaps):,} to "
        f"{max(gaps):,} transitions ({min(gaps.values()):+.1f} to {max(gaps.values()):+.1f}), all at the study budget "
        "([DATA_SIZE.md](../benchmarks/results/data_size/DATA_SIZE.md)).", "",
        "**More budget does not close the gap.** At the paper's budget (one seed per set) the default is below its "
        f"study-budget mean on {len(below)} of {len(fell)} sets; on the hopper sets the guide's proposals drift off "
        f"the data's step scale until every episode falls ({hopper_falls}) "
        "([RESULTS.md](RESULTS.md#longer-budgets-on-the-preset)). At its longest grid budget "
        f"({tels_label.removeprefix('TELS at ')}) the default's IQM is {_iqm_text(tels_long)}, BC's "
        f"({bc_label.removeprefix('BC at ')}) {_iqm_text(bc_long)} "
        "([TABLE.md](../benchmarks/results/TABLE.md#each-method-at-its-longest-budget)).", ""]


def _arm_matrix(sources: tuple[str, ...]):
    """``[seeds, tasks]`` final scores of a latent_scale arm over the four sets (seeds every set has)."""
    import numpy as np

    by_task = [latent_scale._runs(sources, t) for t in TASKS]
    seeds = sorted(set.intersection(*(set(r) for r in by_task)))
    return np.array([[r[s]["final_normalized_score_mean"] for r in by_task] for s in seeds])


def external(d: Data) -> list[str]:
    tsrl = json.loads(TSRL.read_text())
    bc_runs = d.study[tsrl["task"]]["bc"]
    strength = json.loads(BASELINE_STRENGTH.read_text())
    ours = _final(_by_seed(summary.seed_results(summary.REPO / strength["ours"]["results"] / strength["method"]
                                                / strength["task"], lambda r: True)))
    paper_value = run_grid.PAPER_TABLE1[strength["task"]][strength["method"]][0]
    steps = run_grid._steps_label(_steps(next(iter(summary.seed_results(
        summary.REPO / strength["ours"]["results"] / strength["method"] / strength["task"], lambda r: True).values()))))
    above = [t for t in TASKS if statistics.mean(d.study_scores(t, "bc")) > run_grid.PAPER_TABLE1[t]["bc"][0]]
    return [
        "## Two facts about the baselines", "",
        f"**TSRL from its public code.** Table 1 lists TSRL at {run_grid.PAPER_TABLE1[tsrl['task']]['tsrl'][0]:.1f} "
        f"on {tsrl['task']}. Run from [its code]({tsrl['code']}), changed {tsrl['changes_to_the_code']}, it scored "
        f"{tsrl['score']:.1f} ({tsrl['score_reading']}), against our BC's {statistics.mean(_final(bc_runs)):.1f} "
        f"(n={len(bc_runs)}) on that file at the study budget. Caveats: " + "; ".join(tsrl["caveats"])
        + f". Measured {tsrl['measured']}: cite it as \"{tsrl['cite_as']}\" "
        f"([`results/external/{TSRL.name}`](results/external/{TSRL.name})).", "",
        f"**Our baselines are far stronger than the paper's on the same files.** On {strength['task']} our BC scores "
        f"{stats.interval_cell(ours, steps + ' policy steps')} against Table 1's BC {paper_value:.1f}; already at the study budget our "
        f"BC is above Table 1's on {len(above)} of {len(TASKS)} sets. {strength['conclusion']} "
        f"([`results/external/{BASELINE_STRENGTH.name}`](results/external/{BASELINE_STRENGTH.name})).", ""]


def _pooled(changes: dict[str, tuple[str, dict[int, float]]]) -> str:
    values = [v for _, by_seed in changes.values() for v in by_seed.values()]
    return f"{statistics.mean(values):+.1f} over {len(values)} runs, {sum(v > 0 for v in values)} up"


def deviations(d: Data) -> list[str]:
    changes = summary.paired_changes()
    paired = "RESULTS.md#paired-changes-at-the-shared-budget"
    picks = beta_rule.picks()
    weighted_small = sum(w == min(beta_rule.FULL_RUN_ARMS) for w, _ in picks.values())
    unweighted_one = sum(u == 1.0 for _, u in picks.values())
    budget_changes = [statistics.mean(d.longer_scores(t, "tels_default")) - statistics.mean(d.study_scores(t, "tels_default"))
                      for t in TASKS if d.longer_scores(t, "tels_default")]
    keep = {**changes.get("keep0.05", {}), **{f"{t} (re-encoded)": v for t, v in changes.get("keep0.05_reencode", {}).items()}}
    rows = [
        ("h_inv's input in Eq. (11)", "z' = π_g(z)", "φ_s(ψ_s(π_g(z)))", "`guide.reencode_proposal=false`",
         f"{_pooled(changes['reencode'])} (`reencode` against the paper's reading)", f"[paired changes]({paired})"),
        ("β of Eq. (7)", "1", "0.01", "`tsidm.beta=1`",
         f"{_pooled(changes['beta0.01'])} (`beta0.01` against `reencode`); on halfcheetah-medium-replay, held out, "
         "the TS-IDM it trains is what freezes the default, and the default at β = 1 on all nine rows decides "
         "whether it stays", f"[paired changes]({paired}); [which departure freezes it]"
         "(#table-1s-other-five-locomotion-rows-a-pre-registered-test-of-the-defaults)"),
        ("α of λ_α, Eq. (9)", "0.01", "1", "`guide.alpha=0.01`",
         f"{_pooled(changes['alpha1'])} (`alpha1`); {_pooled(changes['alpha1_epyc'])} on the other CPU (`alpha1_epyc`)",
         f"[paired changes]({paired})"),
        ("training length", f"{run_grid.PAPER_TSIDM_EPOCHS} epochs + "
         f"{run_grid._steps_label(run_grid.PAPER_POLICY_STEPS)} steps",
         " + ".join(run_grid._steps_label(int(o.split("=")[1])) for o in summary.SHARED_BUDGET[:2]) + " steps",
         "`budget=paper`",
         f"the paper's budget scores {statistics.mean(budget_changes):+.1f} on average against the study budget's "
         f"seed mean, lower on {sum(c < 0 for c in budget_changes)} of {len(budget_changes)} sets (one seed each)",
         "[longer budgets](RESULTS.md#longer-budgets-on-the-preset)"),
        ("β rule (App. B.5)", "lowest Eq. (7)", "lowest unweighted sum", "`tsidm.beta_selection=weighted`",
         f"picks β = 1, the paper's small-set value, on {unweighted_one} of {len(picks)} stage-1 runs; Eq. (7) as "
         f"written picks the smallest β on {weighted_small} of {len(picks)}, through its own weighting",
         "[β rule](RESULTS.md#the-beta-rule-of-app-b5-read-two-ways)"),
        ("\"moving average 0.05\"", "—", "`SoftUpdate(tau=0.05)`", "—",
         f"nothing to measure against the paper; the other reading (keep rate 0.05) scored {_pooled(keep)}",
         f"[paired changes]({paired}), `keep0.05`"),
        ("latent sizes", "not given", "observation / action size", "—",
         f"nothing to measure against the paper; twice as large scored {_pooled(changes['latent2x'])}",
         f"[paired changes]({paired}), `latent2x`"),
        ("Eq. (7)'s sum over data; Eq. (10)'s weight; TD mask; Adam", "sum; exp(αA); implicit; Adam",
         "batch mean; clipped at 100; (1 − terminated); fused Adam", "`guide.max_weight=1e30` (weight)",
         "not measured: a learning-rate scale, IQL's and POR's clip, TorchRL's convention, the same update", "—"),
    ]
    return ["## The deviations of the default, and what each bought", "",
            "The default is `domain=mujoco budget=study` (`recipes/config/domain/mujoco.yaml`, "
            "[README](../README.md#deviations-from-the-paper)). \"Bought\": the mean paired change of the final "
            "score against the arm it was built on (same seeds and kind of CPU), and how many runs rose; where the "
            "paper is silent, the same for the reading not taken, against ours.", "",
            "| choice | paper | default | restores the paper | what it bought | measured in |",
            "|---|---|---|---|---|---|", *("| " + " | ".join(r) + " |" for r in rows), ""]


def check_yourself(d: Data) -> list[str]:
    first, second = ({r["seed"]: r for r in latent_scale._runs((arm,), CHECK_TASK).values()} for arm in CPU_PAIR)
    pairs = []
    for task in TASKS:
        a, b = latent_scale._runs((CPU_PAIR[0],), task), latent_scale._runs((CPU_PAIR[1],), task)
        for seed in sorted(set(a) & set(b)):
            if {recorded_cpu(a[seed])} != {recorded_cpu(b[seed])}:
                pairs.append(abs(a[seed]["final_normalized_score_mean"] - b[seed]["final_normalized_score_mean"]))
    elapsed = [r["elapsed_s"] for runs in (first, second) for r in runs.values() if r.get("elapsed_s")]
    cpus = [recorded_cpu(runs[CHECK_SEED]) for runs in (first, second)]
    bc = d.study[CHECK_TASK]["bc"][0]  # the grid's BC, lowest seed
    return [
        "## Check one number yourself", "",
        f"The default on {CHECK_TASK}, seed {CHECK_SEED}, at the study budget, one thread, as the study ran it "
        "(fp32, one evaluation episode at a time):", "",
        "```bash",
        f"OMP_NUM_THREADS=1 .venv/bin/python recipes/tels_offline.py dataset.name={CHECK_TASK} seed={CHECK_SEED} \\",
        "    threads=1 precision=fp32 eval.batched=false logger.wandb_mode=disabled run_dir=runs/check",
        ".venv/bin/python -c \"import json; print(round(json.load(open('runs/check/results.json'))"
        "['final_normalized_score_mean'], 1))\"",
        "```", "",
        f"The study recorded {first[CHECK_SEED]['final_normalized_score_mean']:.1f} for this run on an {cpus[0]} "
        f"(`{CPU_PAIR[0]}`) and {second[CHECK_SEED]['final_normalized_score_mean']:.1f} on an {cpus[1]} "
        f"(`{CPU_PAIR[1]}`); its runs of this set took {min(elapsed) / 60:.0f}-{max(elapsed) / 60:.0f} min "
        "(`elapsed_s`, two runs sharing two cores). The exact value depends on the CPU: the same settings and seeds "
        f"on the two CPUs differ by {statistics.mean(pairs):.1f} points on average and by up to {max(pairs):.1f} "
        f"over the {len(pairs)} (set, seed) pairs both ran, so expect a number within that spread, not the digits. "
        "The recorded runs come from the commits of their dates; this command at today's commit was not rerun for "
        "this page. The default run alone on the machine, at two threads, is timed in "
        "[BENCHMARKS.md](../BENCHMARKS.md#the-default-run-measured-the-mujoco-presets-budget).",
        "", f"Quicker, a cell of the baseline grid: BC on {CHECK_TASK}, seed {bc['seed']}, at the study budget:", "",
        "```bash",
        f"OMP_NUM_THREADS=1 .venv/bin/python -m benchmarks.run_grid --method bc --task {CHECK_TASK} --seed {bc['seed']} \\",
        "    --steps 5000 --eval-interval 500 --eval-episodes 10 --threads 1 --wandb-mode disabled --results-dir runs/check",
        "```", "",
        f"prints its final normalized score; the grid recorded {bc['final_normalized_score_mean']:.1f} "
        f"in {bc['elapsed_s']:.0f} s, one of the three seeds behind the BC cell above.", ""]


def render(overview_rows=None) -> str:
    d = Data()
    overview_rows = overview.rows() if overview_rows is None else overview_rows
    return "\n".join([
        "# Does TELS reproduce the paper's Table 1?", "",
        f"Generated by `{COMMAND}` from the result JSONs under `study/results/` and `benchmarks/results/`; do not "
        "edit. Every table behind it: [RESULTS.md](RESULTS.md) (the study's), "
        "[TABLE.md](../benchmarks/results/TABLE.md) (the baseline grid's); what was run, when and why: "
        "[LOG.md](LOG.md); the study's scripts: [README.md](README.md).", "",
        *overview.figure_section(overview_rows), *verdict(d),
        *overview.antmaze_verdict_line(d.antmaze_scores), *table1(d), *overview.held_out_section(d.held_out_verdict),
        *domains.section(), *overview.antmaze_section(d.antmaze_scores), *mechanisms(d), *external(d), *deviations(d),
        *check_yourself(d)])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare with REPORT.md instead of writing it")
    args = parser.parse_args(argv)
    overview_rows = overview.rows()
    if args.check:
        stale = not overview.figure_is_current(overview_rows)
        if stale:
            print(f"{overview.FIGURE.name} is out of date: run {COMMAND}", file=sys.stderr)
        return max(write_generated(OUT, render(overview_rows), COMMAND, check=True), int(stale))
    overview.draw(overview_rows)
    return write_generated(OUT, render(overview_rows), COMMAND)


if __name__ == "__main__":
    sys.exit(main())
