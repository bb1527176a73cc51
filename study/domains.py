"""AntMaze and Adroit beside the paper's Tables 1 and 6: the report's section on the sets beyond locomotion.

Reads the baseline grid's result JSONs (``benchmarks/results/<method>/<task>/seed<k>.json``) at the study
budget (5k policy steps; TELS 3k TS-IDM steps) and at 20k (``benchmarks/results/long20k``), the IQL variants
that settle the maze baseline (``benchmarks/results/iql_tanh_normal``, ``iql_raw_states``), TD3+BC's
(``td3bc_reward_as_recorded``, ``td3bc_alpha0``), the DAPG expert's own score
(``benchmarks/results/adroit_expert``) and, for TELS on the mazes, the weights of its guide (Eq. 10) that
each run records (``diagnostics.awr_weights``, ``diagnostics.guide_history``), and the same guide with
uniform weights (``study/results/maze_alpha0``).
"""
from __future__ import annotations

import json
import statistics
from pathlib import Path

from benchmarks import run_grid
from study.latent_scale import run_results
from torchrl_tels import stats
from torchrl_tels.record import final_success_rate
from torchrl_tels.run.stage1 import SELECTION_KEYS

GRID = run_grid.DEFAULT_RESULTS
MAZE_TASKS = ("antmaze-umaze-v0-10k", "antmaze-umaze-diverse-v0-10k")
ADROIT_TASKS = ("door-human-v1", "pen-expert-v1-10k", "door-expert-v1-10k", "hammer-expert-v1-10k",
                "relocate-expert-v1-10k")
METHODS = ("tels", "tels_paper", "bc", "td3bc", "iql")
HEADERS = ("TELS (default)", "TELS (paper's reading)", "BC", "TD3+BC", "IQL")
BASELINES = ("bc", "td3bc", "iql")
STUDY_STEPS = 5000
#: the same grid at a longer budget, for the arms that decide the verdict
LONGER_BUDGET = (GRID / "long20k", 20000)
#: the TD3+BC arms on the maze: (results dir, what differs)
TD3BC_ARMS = (("td3bc_reward_as_recorded", "rewards as recorded (0 and 1)"), (".", "rewards r − 1 (the grid's)"))
#: the TD3+BC arms on Adroit: (results dir, what differs), on the set where BC reaches the expert
ADROIT_TD3BC_TASK = "door-expert-v1-10k"
ADROIT_TD3BC_ARMS = (("td3bc_alpha0", "α = 0: behaviour cloning through TD3+BC's code"),
                     (".", "α = 2.5, the TD3+BC paper's (the grid's)"))
STUDY_RESULTS = Path(__file__).resolve().parent / "results"
#: TELS's maze guide with uniform weights, α = 0 in Eq. 10 (``study.run_choice --name maze_alpha0``: its runs are
#: STUDY_RESULTS/maze_alpha0/<task>), paired by seed with the grid's TELS (α = 10) on the same TS-IDM
MAZE_ALPHA0 = "maze_alpha0"
#: the grid's maze TELS with a stage 1 of 20k TS-IDM steps instead of 3k (``study.run_choice --name
#: maze_stage1_20k --override tsidm.steps=20000``), the paper's 1000 epochs being 21k-36k steps on these sets
MAZE_STAGE1 = "maze_stage1_20k"
#: the same 20k-step TS-IDMs (``tsidm.checkpoint``) under the uniform-weights guide (``--override guide.alpha=0``)
MAZE_STAGE1_ALPHA0 = "maze_stage1_20k_alpha0"
#: ``study.action_error`` on the maze runs: STUDY_RESULTS/action_error/<prefix>-<set>-seed<k>.json, by arm:
#: (prefix, label, where the arm's scores are: (method folder, results root, policy steps), TS-IDM steps)
MAZE_ACTION_ARMS = (("maze_long20k", "α = 10 (the grid's), 20k policy steps", ("tels", *LONGER_BUDGET), 3000),
                    (MAZE_ALPHA0, "α = 0, 5k policy steps", (MAZE_ALPHA0, STUDY_RESULTS, STUDY_STEPS), 3000),
                    (MAZE_STAGE1, "α = 10, 5k policy steps", (MAZE_STAGE1, STUDY_RESULTS, STUDY_STEPS), 20000),
                    (MAZE_STAGE1_ALPHA0, "α = 0, 5k policy steps", (MAZE_STAGE1_ALPHA0, STUDY_RESULTS, STUDY_STEPS),
                     20000))
#: the grid's Adroit TELS runs with α = 1, ``domain=adroit``'s value before it kept Table 11's
ADROIT_ALPHA1 = GRID / run_grid.ADROIT_ALPHA1
#: the grid's Adroit TELS runs with α = 0.01 and MuJoCo's two other departures (β = 0.01, the proposal
#: re-encoded), ``domain=adroit`` before it took the paper's values
ADROIT_DEPARTURES = GRID / run_grid.ADROIT_DEPARTURES
#: ``domain=adroit`` with MuJoCo's departures, Eq. 10's guide instead of Eq. 9's, on its TS-IDMs (``study.run_choice --name
#: adroit_guide_stochastic --override guide.mode=stochastic tsidm.checkpoint=<the grid run's TS-IDM>``)
ADROIT_STOCHASTIC = "adroit_guide_stochastic"
#: the guide's proposals re-evaluated with their step capped (``study.proposal_cap``): <arm>-<set>-seed<k>.json
PROPOSAL_CAP = STUDY_RESULTS / "proposal_cap"
#: the IQL arms that settle the maze baseline: (results dir, what differs)
IQL_ARMS = (
    ("iql_tanh_normal", "TorchRL's TanhNormal actor, raw states"),
    ("iql_raw_states", "the authors' actor (tanh-mean Gaussian, clipped actions), raw states, as the authors"),
    (".", "the authors' actor, states normalized (the grid's maze IQL)"),
)


def runs(method: str, task: str, results: Path = GRID, steps: int = STUDY_STEPS) -> list[dict]:
    """The runs of ``method`` on ``task`` in ``results`` at ``steps`` policy steps, in seed order."""
    found = []
    for path in sorted((results / method / task).glob("seed*.json")):
        record = json.loads(path.read_text())
        if policy_steps(record) == steps:
            found.append(record)
    return sorted(found, key=lambda r: r["seed"])


def tsidm_source(record: dict) -> str | None:
    """Where a run's TS-IDM came from: ``run_dir/tsidm.pt`` of the run it reused (``tsidm.checkpoint``), or
    ``None`` where the run trained its own."""
    overrides = record.get("recipe_overrides") or record.get("overrides") or []
    found = [o.split("=", 1)[1] for o in overrides if isinstance(o, str) and o.startswith("tsidm.checkpoint=")]
    return found[-1] if found else None


def _stage1_losses(record: dict) -> list:
    """The final stage-1 losses of the TS-IDM a run acted with: its own (the selected candidate's, under
    ``tsidm.beta=auto``), or those the grid read from the TS-IDM it reused (``tsidm_reused``)."""
    stage1 = (record.get("tsidm_reused") or {}).get("beta_results") or record.get("beta_results") or []
    # with tsidm.beta=auto the run acted on the candidate it selected, the one trained at its recorded beta
    acted = [b for b in stage1 if "beta" in record and b.get("beta") == record["beta"]]
    return [b.get("final_loss") for b in acted or stage1]


def same_tsidm(other: dict, trained: dict) -> bool:
    """Whether run ``other`` acted on the TS-IDM run ``trained`` trained: the two TS-IDMs' final stage-1 losses
    agree (a retrained one matches exactly: the recipe is deterministic on one CPU thread), or, for a run that
    recorded no losses of the TS-IDM it reused (``study.run_choice``), its ``tsidm.checkpoint`` is in
    ``trained``'s run folder or in the folder ``trained`` itself reused its TS-IDM from (compared by the folder's
    last four parts, ``<work dir>/<method>/<task>/seed<k>``, which survive a moved or relative path)."""
    losses, reference = _stage1_losses(other), _stage1_losses(trained)
    if losses and reference:
        return losses == reference
    source = tsidm_source(other)
    # the TS-IDM ``trained`` acted with lives in its own folder, or where it reused one from
    folders = [Path(trained["run_dir"])] + [Path(p).parent for p in (tsidm_source(trained),) if p]
    return source is not None and any(Path(source).parent.parts[-4:] == f.parts[-4:] for f in folders)


def policy_steps(record: dict) -> int:
    """A run's policy steps: from the recipe's ``budget`` record, or, where ``study.run_choice`` replaced that
    field with its budget overrides, the step of the run's last evaluation (the recipe evaluates at the end)."""
    budget = record["budget"]
    return int(budget["policy_steps"]) if isinstance(budget, dict) else int(record["evaluations"][-1]["step"])


def scored_evaluations(record: dict) -> list[dict]:
    """The evaluations a run's score averages, as TABLE.md reads them: at the study budget the last 10, at a
    longer budget the later half (TABLE.md's longer-budget sections)."""
    evaluations = record["evaluations"]
    if policy_steps(record) == STUDY_STEPS:
        return evaluations[-record["final_over_last_n_evaluations"]:]
    return evaluations[len(evaluations) // 2:]


def scores(records: list[dict]) -> list[float]:
    return [statistics.fmean(e["score"] for e in scored_evaluations(r)) for r in records]


def cell(records: list[dict], success: bool = False) -> str:
    rates = [final_success_rate(scored_evaluations(r)) for r in records]
    note = f"success {statistics.mean(rates):.2f}" if success and records and None not in rates else ""
    return stats.interval_cell(scores(records), note)


def relation(a: list[float], b: list[float]) -> str:
    """``above``, ``below`` or ``level with`` by the two t-intervals (level when they overlap or n < 2)."""
    if len(a) < 2 or len(b) < 2:
        return "not comparable with (n < 2)"
    _, a_low, a_high = stats.t_interval(a)
    _, b_low, b_high = stats.t_interval(b)
    return "above" if a_low > b_high else "below" if a_high < b_low else "level with"


def _paper(task: str, method: str) -> str:
    value = run_grid.PAPER_TABLE1.get(task, {}).get(method)
    return "—" if value is None else run_grid.paper_cell(value)


def saturation(tasks) -> dict[str, float]:
    """The share of each set's action entries at exactly -1 or 1."""
    from torchrl_tels.data import load_dataset

    return {task: float((load_dataset(task)["action"].abs() == 1).float().mean()) for task in tasks}


def expert_ceiling(task: str) -> dict | None:
    path = GRID / "adroit_expert" / f"{task.split('-')[0]}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def verdict_lines() -> list[str]:
    """One sentence per domain and budget, from the numbers: TELS against the best baseline on each set."""
    lines = []
    budgets = (("the study budget", GRID, STUDY_STEPS), (f"{LONGER_BUDGET[1] // 1000}k steps", *LONGER_BUDGET))
    for label, tasks in (("AntMaze", MAZE_TASKS), ("Adroit", ADROIT_TASKS)):
        for budget, results, steps in budgets:
            parts, ran = [], 0
            for task in tasks:
                tels = scores(runs("tels", task, results, steps))
                ran_here = {m: s for m in BASELINES if (s := scores(runs(m, task, results, steps)))}
                if not tels or not ran_here:
                    continue
                best = max(ran_here, key=lambda m: statistics.mean(ran_here[m]))
                other = ran_here[best]
                ran += 1
                among = "" if len(ran_here) == len(BASELINES) else (
                    f" (the baselines run there: {', '.join(run_grid.LABELS[m] for m in ran_here)})")
                paper = scores(runs("tels_paper", task, results, steps))
                paper_text = (f", the paper's reading {statistics.mean(paper):.1f} (n={len(paper)}), "
                              f"{relation(paper, other)} it" if paper else "")
                parts.append(f"{task}: TELS {statistics.mean(tels):.1f} (n={len(tels)}), {relation(tels, other)} "
                             f"{run_grid.LABELS[best]} {statistics.mean(other):.1f} (n={len(other)}){among}"
                             f"{paper_text}")
            if not parts and steps != STUDY_STEPS:
                continue  # no longer runs in this domain yet
            missing = len(tasks) - ran
            lines.append(f"**{label}** at {budget}: " + ("; ".join(parts) if parts else "no set has both TELS and "
                         "a baseline yet") + (f"; {missing} of {len(tasks)} sets lack TELS or every baseline"
                                             if missing else "") + ".")
    bc = [(task, scores(runs("bc", task)), run_grid.PAPER_TABLE1.get(task, {}).get("bc")) for task in ADROIT_TASKS]
    bc = [(task, ours, paper[0]) for task, ours, paper in bc if ours and paper]
    if bc:
        lines.append(f"**Adroit, BC**: Tables 1 and 6 give BC {min(p for *_, p in bc):.1f}–{max(p for *_, p in bc):.1f} "
                     "on these sets; ours, on the same data and budget as TELS, scores " + "; ".join(
                         f"{task} {statistics.mean(ours):.1f} (n={len(ours)}; the paper's {paper:.1f})"
                         for task, ours, paper in bc) + ".")
    best = [(task, scores(runs(MAZE_STAGE1_ALPHA0, task, STUDY_RESULTS)), scores(runs("bc", task)))
            for task in MAZE_TASKS]
    best = [f"{task}: {statistics.mean(arm):.1f} (n={len(arm)}), {relation(arm, bc)} BC {statistics.mean(bc):.1f}"
            for task, arm, bc in best if arm and bc]
    if best:
        lines.append("**AntMaze**, TELS's best variant found, at the study's 5k policy steps (the paper's stage-1 "
                     "length and uniform guide weights, which gives up the value weighting; not the default, see "
                     "\"What limits TELS on the mazes\"): " + "; ".join(best) + ".")
    return lines


def _maze_guide_rows() -> list[str]:
    rows = ["| set | policy steps | seed | ESS / n | weights at the clip | start cell: data → weight "
            "| goal cell: data → weight | V on the data | V's batch mean, first → halfway → last logged |",
            "|---|---|---|---|---|---|---|---|---|"]
    for task, (results, steps) in ((t, b) for t in MAZE_TASKS for b in ((GRID, STUDY_STEPS), LONGER_BUDGET)):
        for record in runs("tels", task, results, steps):
            weights = record.get("diagnostics", {}).get("awr_weights")
            if not weights:
                continue
            regions = weights.get("regions", {})
            start, goal = regions.get("0,0", {}), regions.get("0,2", {})
            rows.append(f"| {task} | {steps:,} | {record['seed']} | {' | '.join(guide_weight_cells(weights))} | "
                        f"{start.get('data_share', 0):.1%} → {start.get('weight_share', 0):.1%} | "
                        f"{goal.get('data_share', 0):.1%} → {goal.get('weight_share', 0):.1%} | "
                        f"{value_range_cell(weights)} | {value_history_cell(record)} |")
    return rows if len(rows) > 2 else []


def guide_weight_cells(weights: dict) -> tuple[str, str]:
    """Eq. 10's weights over the data at the end of training: Kish's ESS / n, and the share at the clip."""
    return f"{weights['effective_sample_fraction']:.3f}", f"{weights['clipped_fraction']:.1%}"


def value_range_cell(weights: dict) -> str:
    """V's range over the data at the end of training."""
    return f"[{weights['value_min']:.1f}, {weights['value_max']:.1f}]"


def value_history_cell(record: dict) -> str:
    """V's batch mean as training logged it: first, halfway and last."""
    history = record["diagnostics"].get("guide_history", {}).get("value/state_value", [])
    return " → ".join(f"{value:.1f} (step {step})" for step, value in
                      (history[0], history[len(history) // 2], history[-1])) if history else "not logged"


def _arm_table(heading: str, task: str, arms) -> list[str]:
    """TD3+BC's arms on ``task``, one row each; nothing until the first arm has a run."""
    cells = [cell(runs("td3bc", task, GRID / folder), task in ADROIT_TASKS) for folder, _ in arms]
    if cells[0] == "no runs":
        return []
    return [f"{heading} On {task}:", "", "| TD3+BC arm | score |", "|---|---|",
            *(f"| {label} | {c} |" for (_, label), c in zip(arms, cells)), ""]


def _maze_alpha0_rows() -> list[str]:
    """The maze guide's weighting tested: α = 10 (the grid's TELS) against α = 0 beside BC; nothing before a run."""
    arms = {task: (runs("tels", task), runs(MAZE_ALPHA0, task, STUDY_RESULTS), runs("bc", task))
            for task in MAZE_TASKS}
    if not any(alpha0 for _, alpha0, _ in arms.values()):
        return []
    rows = ["**Is the guide's weighting what costs TELS the mazes?** The guide's weights above are few and far "
            "between (a few per cent of the data carry them), so the guide learns from a few hundred transitions "
            "where BC learns from all. If that is the cost, uniform weights (α = 0: Eq. 10 becomes the latent "
            "guide's likelihood on every transition, its T-symmetry term unchanged) bring TELS to BC's level. "
            "Same seeds, TS-IDM and protocol as the grid's TELS (`python -m study.run_choice --name maze_alpha0 "
            "--override guide.alpha=0`, budget as the grid's maze TELS):", "",
            "| set | TELS, α = 10 (the grid's) | TELS, α = 0 | BC | α = 0 − α = 10, paired by seed | α = 0 against BC |",
            "|---|---|---|---|---|---|"]
    for task, (weighted, alpha0, bc) in arms.items():
        change = paired_change(paired_by_seed(alpha0, weighted))
        rows.append(f"| {task} | {cell(weighted)} | {cell(alpha0)} | {cell(bc)} | {change} | "
                    f"{relation(scores(alpha0), scores(bc))} BC |")
    return [*rows, ""]


def scores_by_seed(records: list[dict]) -> dict[int, float]:
    return {r["seed"]: s for r, s in zip(records, scores(records))}


def paired_by_seed(records: list[dict], reference: list[dict]) -> list[float]:
    """Score differences ``records`` − ``reference`` over the seeds both have."""
    base = scores_by_seed(reference)
    return [s - base[seed] for seed, s in scores_by_seed(records).items() if seed in base]


def paired_change(differences: list[float]) -> str:
    """The mean paired difference and how many seeds went up, or ``no pairs``."""
    if not differences:
        return "no pairs"
    return (f"{statistics.mean(differences):+.1f} ({sum(d > 0 for d in differences)} of {len(differences)} "
            "seeds up)")


def _maze_action_rows() -> list[str]:
    """Where the maze actor's action error comes from (``study.action_error`` on the saved runs), by the length
    of the run's stage 1."""
    rows, ratios = [], {}  # ratios[TS-IDM steps][part]: the oracle's error over BC's
    for prefix, label, (method, results, steps), tsidm_steps in MAZE_ACTION_ARMS:
        for task in MAZE_TASKS:
            short = task.removeprefix("antmaze-").removesuffix("-v0-10k")
            arm_scores = scores_by_seed(runs(method, task, results, steps))
            for path in sorted((STUDY_RESULTS / "action_error").glob(f"{prefix}-{short}-seed*.json")):
                seed = int(path.stem.rsplit("seed", 1)[1])
                train = json.loads(path.read_text())["train"]
                parts = {"all": train["action_mse"], "bound": train["action_mse_at_bound"],
                         "inside": train["action_mse_inside"]}
                for part, m in parts.items():
                    ratios.setdefault(tsidm_steps, {}).setdefault(part, []).append(m["oracle"] / m["bc"])
                ratios[tsidm_steps].setdefault("actor", []).append(parts["all"]["guide"] / parts["all"]["bc"])
                ratios[tsidm_steps].setdefault("guide", []).append(train["guide_error_over_step"])
                score = f"{arm_scores[seed]:.1f}" if seed in arm_scores else "—"
                rows.append(f"| {task} | {label} | {tsidm_steps:,} | {seed} | {score} | "
                            + " | ".join(f"{m['oracle']:.3f} / {m['bc']:.3f}" for m in parts.values())
                            + f" | {parts['all']['guide']:.3f} | {train['guide_error_over_step']:.2f} |")
    if not rows:
        return []

    def span(values: list[float], digits: int = 1) -> str:
        low, high = f"{min(values):.{digits}f}", f"{max(values):.{digits}f}"
        return low if low == high else f"{low}–{high}"

    lines = ["**Where the maze actor's action error comes from**, on each run's own transitions (`python -m "
             "study.action_error --run-dir <run> --name <arm>-<set>-seed<k>`): the mean squared action error of "
             "Eq. (11) fed the true next latent, ψ_a(h_inv(z, φ_s(s'))) (the TS-IDM's own floor), against BC's, "
             "fitted by MSE on the same transitions; the same over the action entries at a bound (exactly ±1) and "
             "inside; the actor as it acts; and the guide's latent error over the data's latent step "
             "(‖π_g(z) − z'‖² / ‖z' − z‖²). The grid's stage 1 is 3,000 TS-IDM steps; the paper's, 1000 epochs "
             "(Table 10), is about 21,000 on umaze and 36,000 on umaze-diverse (`python -m study.run_choice --name "
             "maze_stage1_20k --override tsidm.steps=20000`, otherwise the grid's maze TELS; with α = 0, the same TS-IDMs "
             "through `tsidm.checkpoint`, `--name maze_stage1_20k_alpha0`):", "",
             "| set | arm | TS-IDM steps | seed | score | Eq. (11) with the true z' / BC | at a bound | inside | "
             "actor | guide error / step |", "|---|---|---|---|---|---|---|---|---|---|", *rows, ""]
    for tsidm_steps, r in sorted(ratios.items()):
        n = len(r["all"])
        reading = (f"After {tsidm_steps:,} TS-IDM steps ({n} run{'s' if n > 1 else ''}), Eq. (11) fed the true next "
                   f"latent errs {span(r['all'])}× BC's error ({span(r['bound'])}× at a bound, {span(r['inside'])}× "
                   f"inside); the actor as it acts, {span(r['actor'])}× BC's, its guide's squared latent error "
                   f"{span(r['guide'], 2)} of the data's squared step.")
        lines.append(f"- {reading}")
    paired = [f"α = {alpha}, {task} seed {seed} {short_stage1[seed]:.1f} → {longer:.1f}"
              for alpha, short, long in (("10", ("tels", GRID), MAZE_STAGE1), ("0", (MAZE_ALPHA0, STUDY_RESULTS),
                                                                              MAZE_STAGE1_ALPHA0))
              for task in MAZE_TASKS
              for short_stage1 in [scores_by_seed(runs(short[0], task, short[1]))]
              for seed, longer in scores_by_seed(runs(long, task, STUDY_RESULTS)).items()
              if seed in short_stage1]
    if paired:
        lines.append("- Scores at 5,000 policy steps, same seed, stage 1 of 3,000 → 20,000 TS-IDM steps: "
                     + "; ".join(paired) + ".")
    lines += ["", "Above 1×, the TS-IDM's inverse dynamics is a floor above BC before the guide proposes anything; on "
              "the locomotion runs read it lies at or below BC's ([RESULTS.md, \"Where the action error comes from\"]"
              "(RESULTS.md#the-latent-scale-fixes-of-eq-7)).", ""]
    return lines


#: the maze TELS arms at the study's 5k policy steps, by (guide α, TS-IDM steps): (label, method folder, results root)
MAZE_STAGE1_ARMS = (("α = 10, 3k (the grid's)", "tels", GRID), ("α = 0, 3k", MAZE_ALPHA0, STUDY_RESULTS),
                    ("α = 10, 20k", MAZE_STAGE1, STUDY_RESULTS), ("α = 0, 20k", MAZE_STAGE1_ALPHA0, STUDY_RESULTS))


def _maze_arm_rows() -> list[str]:
    """The maze TELS arms side by side per set, each paired by seed with the grid's TELS, beside BC."""
    if not any(runs(MAZE_STAGE1_ALPHA0, task, STUDY_RESULTS) for task in MAZE_TASKS):
        return []
    rows, paired, reading = [], [], []
    best = MAZE_STAGE1_ARMS[-1]
    for task in MAZE_TASKS:
        arms = [runs(folder, task, root) for _, folder, root in MAZE_STAGE1_ARMS]
        bc = runs("bc", task)
        rows.append(f"| {task} | " + " | ".join(cell(records) for records in arms) + f" | {cell(bc)} |")
        for (label, _, _), records in zip(MAZE_STAGE1_ARMS[1:], arms[1:]):
            differences = paired_by_seed(records, arms[0])
            if differences:
                paired.append(f"{task}, {label}: {paired_change(differences)}, "
                              f"{relation(scores(records), scores(bc))} BC")
        arm, bc_scores = scores(arms[-1]), scores(bc)
        if arm and bc_scores:
            wins = sum(d > 0 for d in paired_by_seed(arms[-1], arms[0]))
            reading.append(f"{task}: {statistics.mean(arm):.1f} (n={len(arm)}, above the grid's TELS on {wins} of "
                           f"{len(arm)} seeds) against BC's {statistics.mean(bc_scores):.1f} (n={len(bc_scores)}), "
                           f"{relation(arm, bc_scores)} BC by the intervals")
    return ["**The maze arms side by side** (guide α, TS-IDM steps; 5k policy steps, the grid's protocol; the grid's "
            "TELS and the study arms "
            + ", ".join(f"`{arm}`" for _, arm, folder in MAZE_STAGE1_ARMS if folder == STUDY_RESULTS) + "):", "", "| set | " + " | ".join(label for label, _, _ in MAZE_STAGE1_ARMS)
            + " | BC |", "|---|" + "---|" * (len(MAZE_STAGE1_ARMS) + 1), *rows, "",
            "Each arm against the grid's TELS, paired by seed, and against BC by the t-intervals: "
            + "; ".join(paired) + ".", "",
            f"**What limits TELS on the mazes.** The arm \"{best[0]}\" (the paper's stage-1 length, uniform guide "
            "weights) is the change that helps on both sets: " + "; ".join(reading) + ". It is not made "
            "`domain=maze`'s default. With α = 0, Eq. 10 no longer weights by the advantage, so the guide is "
            "behaviour cloning in the TS-IDM's latent space and the value function does not act on the policy: "
            "what helps is giving up the offline-RL part, and what is left does not beat BC. The two limits the "
            "instruments above show are the guide's weighting (a few per cent of the data carry its weights, and "
            "removing them moved the score more than the longer stage 1 alone) and, at the study's 3k stage 1, the "
            "TS-IDM's inverse-dynamics floor above BC's error, which the paper's stage-1 length brings below BC's "
            "(the bullets above give the actor's error as it acts against BC's).", ""]


def _adroit_mode_rows() -> list[str]:
    """Eq. 9 (``domain=adroit``'s guide) against Eq. 10 on the same TS-IDMs, by seed, both with MuJoCo's
    departures (``domain=adroit`` when these ran); nothing before a run."""
    arms = {task: (runs("tels", task, ADROIT_DEPARTURES), runs(ADROIT_STOCHASTIC, task, STUDY_RESULTS))
            for task in ADROIT_TASKS}
    arms = {task: pair for task, pair in arms.items() if pair[1]}
    if not arms:
        return []
    rows, summary, wins = [], [], []
    for task, (deterministic, stochastic) in arms.items():
        by_seed = {r["seed"]: r for r in deterministic}
        same = []
        for record in stochastic:
            default = by_seed.get(record["seed"])
            shared = default is not None and same_tsidm(record, default)
            weights = record.get("diagnostics", {}).get("awr_weights") or {}
            ess = f"{weights['effective_sample_fraction']:.3f}" if weights else "—"
            default_score = f"{scores([default])[0]:.1f}" if default else "—"
            rows.append(f"| {task} | {record['seed']} | {default_score} | {scores([record])[0]:.1f} | {ess} | "
                        f"{'yes' if shared else 'no'} |")
            if shared:
                same.append(record)
        paired = paired_by_seed(same, deterministic)
        summary.append(f"| {task} | {cell(deterministic, True)} | {cell(stochastic, True)} | "
                       f"{paired_change(paired)} |")
        if paired and statistics.mean(paired) > 0 and 2 * sum(d > 0 for d in paired) > len(paired):
            wins.append(task)
    return ["**Eq. 9 or Eq. 10 on Adroit.** The paper does not say which guide its Adroit runs used; `domain=adroit` "
            "takes Eq. 9's deterministic guide, as for dense-reward MuJoCo. Its runs with MuJoCo's departures "
            "(β = 0.01, the proposal re-encoded: the domain when these ran, `benchmarks/results/"
            f"{run_grid.ADROIT_DEPARTURES}`) with Eq. 10's "
            "advantage-weighted likelihood instead, Table 11's α = 0.01 kept, on each such run's own TS-IDM "
            "(`python -m study.run_choice --name adroit_guide_stochastic --override guide.mode=stochastic "
            "tsidm.checkpoint=<the grid run's TS-IDM>`, budget as the grid's Adroit TELS; today that also needs "
            "`guide.reencode_proposal=true`). ESS / n is Kish's "
            "effective sample size of Eq. 10's weights over the data at the end of training (1: uniform):", "",
            "| set | seed | Eq. 9 | Eq. 10 | ESS / n | same TS-IDM |", "|---|---|---|---|---|---|",
            *rows, "", "| set | Eq. 9 | Eq. 10 | Eq. 10 − Eq. 9, paired by seed |", "|---|---|---|---|",
            *summary, "",
            (f"Eq. 10 is up in mean and on most seeds on {len(wins)} of the {len(arms)} sets read"
             + (f" ({', '.join(wins)})" if wins else "") + "; to replace the default it would have to be up on every "
             "set, so `domain=adroit` keeps Eq. 9." if len(wins) < len(arms) else
             f"Eq. 10 is up in mean and on most seeds on every set read ({', '.join(wins)})."), ""]


def _adroit_paper_rows() -> list[str]:
    """The paper's reading on Adroit against MuJoCo's departures (``domain=adroit`` before it took the paper's
    values), by seed: the β App. B.5 selects, each candidate's stage-1 loss, and the paired difference where both
    acted on the same TS-IDM; nothing before a run."""
    arms = {task: (runs("tels", task, ADROIT_DEPARTURES), runs("tels_paper", task)) for task in ADROIT_TASKS}
    arms = {task: pair for task, pair in arms.items() if pair[1]}
    if not arms:
        return []
    candidates = sorted({b["beta"] for _, paper in arms.values() for r in paper for b in r["beta_results"]})
    rows, by_set = [], []
    for task, (default, paper) in arms.items():
        by_seed = {r["seed"]: r for r in default}
        same = []
        for record in paper:
            losses = {b["beta"]: b for b in record["beta_results"]}
            weighted = min(losses.values(), key=lambda b: b[SELECTION_KEYS["weighted"]])["beta"]
            reference = by_seed.get(record["seed"])
            shared = reference is not None and same_tsidm(record, reference)
            rows.append(f"| {task} | {record['seed']} | " + " | ".join(
                f"{losses[b]['final_sum']:.3f}" if b in losses else "—" for b in candidates)
                + f" | {record['beta']:g} | {weighted:g} | "
                + (f"{scores([reference])[0]:.1f}" if reference else "—") + f" | {scores([record])[0]:.1f} | "
                + ("yes" if shared else "no") + " |")
            if shared:
                same.append(record)
        by_set.append((task, default, paper, same))
    any_shared = any(same for *_, same in by_set)  # a column of its own only where the rule selected the departures' β
    summary = [f"| {task} | {cell(default, True)} | {cell(paper, True)} | {paired_change(paired_by_seed(paper, default))} |"
               + (f" {paired_change(paired_by_seed(same, default))} |" if any_shared else "")
               for task, default, paper, same in by_set]
    return ["**The paper's reading on Adroit.** `domain=adroit_paper` departs from the paper nowhere: β is selected "
            "per run from {" + ", ".join(f"{b:g}" for b in candidates) + "} as App. B.5 and Table 10 say for "
            "domains other than MuJoCo 10k (the lowest of stage 1's four terms summed unweighted, the reading that "
            "picks the paper's own β = 1 on MuJoCo: RESULTS.md, β rule), and h_inv gets z' itself (Eq. 11 as "
            "written). MuJoCo's departures (`domain=adroit` when these ran) train β = 0.01, the first candidate, "
            "from the same seed, and re-encode the "
            "proposal. Per run: each candidate's final unweighted sum, the β selected, the β that Eq. 7 as written "
            "would select, and the scores (grid runs, `python -m benchmarks.run_grid --method tels_paper`, budget "
            "as the grid's Adroit TELS):", "",
            "| set | seed | " + " | ".join(f"sum at β = {b:g}" for b in candidates)
            + " | β selected | Eq. 7's pick | departures | paper's reading | same TS-IDM |",
            "|---|---|" + "---|" * (len(candidates) + 5), *rows, "",
            "| set | departures | paper's reading | paper's − departures', paired by seed |"
            + (" on the same TS-IDM |" if any_shared else ""), "|---|---|---|---|" + ("---|" if any_shared else ""),
            *summary, "", _adroit_default_reading(by_set), ""]


def _wins_broadly(differences: dict[str, list[float]]) -> bool:
    """Whether an arm, by its paired differences per set, is up in mean on every set and on most seeds."""
    seeds = [d for task_d in differences.values() for d in task_d]
    return (all(d and statistics.mean(d) > 0 for d in differences.values())
            and 2 * sum(d > 0 for d in seeds) > len(seeds))


def _adroit_default_reading(by_set: list[tuple]) -> str:
    """How the paper's reading fared against MuJoCo's departures, and whether the default's runs (the paper's
    values since) repeat the paper's reading's scores on the TS-IDMs they reused."""
    differences = {task: paired_by_seed(paper, departures) for task, departures, paper, _ in by_set}
    seeds = [d for task_d in differences.values() for d in task_d]
    reading = (f"The paper's reading is up in mean on {sum(bool(d) and statistics.mean(d) > 0 for d in differences.values())} "
               f"of {len(differences)} sets and on {sum(d > 0 for d in seeds)} of {len(seeds)} seeds. ")
    if _wins_broadly({task: [-x for x in d] for task, d in differences.items()}):
        return reading + ("The departures win broadly, so by the study's rule (the paper's value unless a change "
                          "wins broadly) `domain=adroit` should keep them.")
    reading += ("The departures do not win broadly, so by the study's rule (the paper's value unless a change wins "
                "broadly) `domain=adroit` takes the paper's values.")
    reused = [(r, paper[r["seed"]]) for task, _, paper_runs, _ in by_set
              for paper in [{p["seed"]: p for p in paper_runs}]
              for r in runs("tels", task) if run_grid.reused_tsidm_of(r, "tels_paper") and r["seed"] in paper]
    if reused:
        same = sum(scores([r])[0] == scores([p])[0] for r, p in reused)
        reading += (f" {len(reused)} of its runs, in the TELS (default) column above, started stage 2 from the "
                    "paper's-reading run's TS-IDM of the same seed, the stage-1 settings being the same (`python -m "
                    "benchmarks.run_grid --method tels --work-dir <a new work dir> --tsidm-from <the grid's work dir> "
                    f"--tsidm-from-method tels_paper`); on {same} of them the score equals the paper's reading's to "
                    "the last digit.")
    return reading


def _guide_cells(record: dict | None) -> str:
    """A run's score, and its guide's proposed latent step over the data's (RMS) and their cosine, at the end."""
    if record is None:
        return "— | — | —"
    diagnostics = record.get("diagnostics", {})
    return (f"{scores([record])[0]:.1f} | {diagnostics.get('guide_step_ratio', float('nan')):.1f} | "
            f"{diagnostics.get('guide_step_cosine', float('nan')):.2f}")


def _adroit_guide_rows() -> list[str]:
    """Where the deterministic guide's proposals go on Adroit, under MuJoCo's α and Table 11's, and what
    capping them does to a trained run (``study.proposal_cap``); nothing before a run records its guide."""
    arms = {task: (runs("tels", task, ADROIT_ALPHA1), runs("tels", task, ADROIT_DEPARTURES), runs("bc", task))
            for task in ADROIT_TASKS}
    rows, paired = [], {}
    for task, (alpha1, alpha_paper, bc) in arms.items():
        default = {r["seed"]: r for r in alpha1}
        paper_alpha = {r["seed"]: r for r in alpha_paper}
        for seed in sorted(set(default) | set(paper_alpha)):
            both = seed in default and seed in paper_alpha
            shared = both and same_tsidm(paper_alpha[seed], default[seed])
            rows.append(f"| {task} | {seed} | {_guide_cells(default.get(seed))} | {_guide_cells(paper_alpha.get(seed))} "
                        f"| {('yes' if shared else 'no') if both else '—'} | {cell(bc)} |")
            if shared:
                paired.setdefault(task, []).append(scores([paper_alpha[seed]])[0] - scores([default[seed]])[0])
    if not rows:
        return []
    maze = [json.loads(path.read_text())["train"] for path in sorted((STUDY_RESULTS / "action_error").glob("maze_*.json"))]
    maze_ratio = [m["guide_step_ratio"] for m in maze if "guide_step_ratio" in m]
    lines = ["**Where the guide's proposals go on Adroit.** Eq. (9)'s guide proposes the next latent z' = π_g(z); "
             "each run records, at the end of training over its data, the proposed step's RMS over the data's "
             "(‖π_g(z) − z‖ against ‖φ_s(s') − φ_s(s)‖) and the mean cosine between the two steps "
             "(`torchrl_tels.diagnostics.action_chain_statistics`)"
             + (f"; on the {len(maze_ratio)} maze runs read above the ratio is {min(maze_ratio):.2f}–"
                f"{max(maze_ratio):.2f}" if maze_ratio else "")
             + ". `domain=adroit` weighted Eq. (9)'s value term with α = 1, the `mujoco` domain's departure, until "
             f"these runs (`benchmarks/results/{run_grid.ADROIT_ALPHA1}`); Table 11 gives 0.01 for \"other tasks\", "
             "which `domain=adroit` keeps since. Both arms here keep MuJoCo's two other departures, as the domain "
             f"did then; the α = 0.01 runs are in `benchmarks/results/{run_grid.ADROIT_DEPARTURES}` "
             "(`python -m benchmarks.run_grid --grid --method tels --tsidm-from <the α = 1 grid's work dir>` "
             "before `domain=adroit` took the paper's values, which started stage 2 from the α = 1 run's TS-IDM of "
             "the same seed, or trained one where that was gone). "
             "\"Same TS-IDM\": the α = 0.01 run acted on the α = 1 run's TS-IDM, reused or trained again to the "
             "same final loss; only those seeds enter the paired differences:", "",
             "| set | seed | α = 1: score | proposed / data step | cosine | α = 0.01: score | "
             "proposed / data step | cosine | same TS-IDM | BC |", "|---|---|---|---|---|---|---|---|---|---|", *rows, ""]
    lines += ["Per set, over every seed each arm has:", "", "| set | α = 1 | α = 0.01 | BC |",
              "|---|---|---|---|", *(f"| {task} | " + " | ".join(cell(records, True) for records in task_arms) + " |"
                                    for task, task_arms in arms.items()), ""]
    if paired:
        lines += ["α = 0.01 − α = 1, paired by seed: " + "; ".join(
            f"{task} {paired_change(d)}"
            for task, d in paired.items()) + ".", ""]
    capped = [(task, seed, record["scores"]) for (arm, task, seed), record in run_results(PROPOSAL_CAP).items()
              if arm == "tels" and task in ADROIT_TASKS]
    if capped:
        caps = list(dict.fromkeys(name for _, _, readings in capped for name in readings))
        lines += ["The α = 1 runs re-evaluated with the guide's step capped at k times the data's RMS "
                  "latent step (`python -m study.proposal_cap --run-dir <run> --name tels-<set>-seed<k> --caps 0.01 "
                  "1 2`: no training, the same ten episodes per reading; cap 0.01 is next to no step at all; \"as "
                  "trained\" is the uncapped final policy on those episodes, one evaluation, where a run's score "
                  "averages its last ten, so the two differ):", "",
                  "| set | seed | " + " | ".join(caps) + " |", "|---|---|" + "---|" * len(caps),
                  *(f"| {task} | {seed} | " + " | ".join(f"{readings[c]:.1f}" if c in readings else "—" for c in caps)
                    + " |" for task, seed, readings in capped), ""]
    return lines


def _longer_rows() -> list[str]:
    """The arms that decide the verdict, at the longer budget, beside their study-budget cells."""
    results, steps = LONGER_BUDGET
    rows, intervals = [], set()
    for task in (*MAZE_TASKS, *ADROIT_TASKS):
        for method in METHODS:
            longer = runs(method, task, results, steps)
            if longer:
                adroit = task in ADROIT_TASKS
                rows.append(f"| {task} | {run_grid.LABELS[method]} | {cell(runs(method, task), adroit)} | "
                            f"{cell(longer, adroit)} |")
                intervals.update(r["budget"]["eval_interval"] for r in longer)
    if not rows:
        return []
    intervals = sorted(intervals)
    return ["", f"**At {steps:,} policy steps** (the same protocol, evaluations every "
            f"{' or '.join(f'{i:,}' for i in intervals)} steps, the score the mean "
            f"of the later half; [`{results.relative_to(GRID.parent.parent)}`](../{results.relative_to(GRID.parent.parent)})), "
            "the arms that decide the verdict:", "",
            f"| set | arm | {STUDY_STEPS:,} steps | {steps:,} steps |", "|---|---|---|---|", *rows]


def section() -> list[str]:
    lines = ["## AntMaze and Adroit, beside Tables 1 and 6", "",
             "The same protocol as the locomotion rows: every method 5k policy steps (TELS after 3k TS-IDM steps), "
             "the score the mean of the last 10 evaluations (AntMaze: of its two), each cell the mean over seeds with "
             "its 95 % t-interval and n; the paper's value after `·`. AntMaze evaluates 50 episodes every 2,500 steps "
             "in the D4RL "
             "umaze env (`torchrl_tels.envs.antmaze`); Adroit 10 episodes every 500 steps in gymnasium-robotics' "
             "envs with D4RL's reward and episode length (`torchrl_tels.envs.adroit`), with D4RL's success rate "
             "after the score. TELS runs `domain=maze` (Table 11's AntMaze values, Eq. 10) and `domain=adroit` "
             "(Tables 10-11's values for other tasks, β selected as App. B.5 says, Eq. 9: the same values as "
             "`domain=adroit_paper`, the paper's reading, since MuJoCo's departures did not win there; see \"The "
             "paper's reading on Adroit\" and \"Where the guide's proposals go on Adroit\" below). "
             "Every number is in the grid's JSONs ([TABLE.md](../benchmarks/results/TABLE.md)).", "",
             "| set | " + " | ".join(HEADERS) + " | DAPG expert (ceiling) |",
             "|---|" + "---|" * (len(HEADERS) + 1)]
    for task in (*MAZE_TASKS, *ADROIT_TASKS):
        adroit = task in ADROIT_TASKS
        expert = expert_ceiling(task) if adroit else None
        ceiling = (f"{expert['score_mean']:.1f}, success {expert['success_rate']:.2f} (n={expert['episodes']} episodes)"
                   if expert else "—")
        lines.append(f"| {task} | " + " | ".join(
            "the default's (`domain=maze` is Table 11's)" if m == "tels_paper" and not adroit
            else f"{cell(runs(m, task), adroit)} · {_paper(task, m)}" for m in METHODS) + f" | {ceiling} |")
    lines += _longer_rows()
    lines += ["", "**Settling the maze baseline.** IQL on the same data and budget, three ways:", "",
              "| IQL arm | " + " | ".join(MAZE_TASKS) + " |", "|---|" + "---|" * len(MAZE_TASKS)]
    for folder, label in IQL_ARMS:
        lines.append(f"| {label} | " + " | ".join(cell(runs("iql", t, GRID / folder)) for t in MAZE_TASKS) + " |")
    first, last = (scores(runs("iql", MAZE_TASKS[0], GRID / IQL_ARMS[i][0])) for i in (0, -1))
    raw = scores(runs("iql", MAZE_TASKS[0], GRID / IQL_ARMS[1][0]))
    saturated = ", ".join(f"{task} {share:.1%}" for task, share in saturation(MAZE_TASKS + ADROIT_TASKS).items())
    lines += ["", f"On {MAZE_TASKS[0]}, the grid's maze IQL is {relation(last, first)} TorchRL's recipe actor and "
              f"{relation(last, raw)} the authors' actor on raw states. Share of action entries at exactly ±1: "
              f"{saturated}. The authors' actor is a Gaussian around a tanh mean, which reaches ±1 with a finite "
              "mean, where TorchRL's TanhNormal must push its pre-tanh mean without bound; the grid's maze IQL "
              "departs from the authors in one thing, normalized states (`benchmarks.baselines.MAZE_HYPERPARAMETERS`).",
              ""]
    lines += _arm_table(
        "**TD3+BC near zero on the mazes.** Its Q term is weighted λ = α / mean|Q| (the TD3+BC paper's "
        "normalization): with rewards of 0 and 1, Q starts near 0 and λ is large, so the actor chases an "
        "untrained Q; with r − 1, as IQL and POR train on AntMaze, |Q| is large from the start and λ small.",
        MAZE_TASKS[0], TD3BC_ARMS)
    lines += _arm_table(
        "**TD3+BC near zero on Adroit.** Is it the harness or the Q term? With α = 0 the same code (actor, "
        "critic, normalized states, evaluation) is behaviour cloning, and the actor's only change is its loss.",
        ADROIT_TD3BC_TASK, ADROIT_TD3BC_ARMS)
    guide = _maze_guide_rows()
    lines += ["**TELS's maze guide (Eq. 10), read.** Where its weights min(exp(αA), 100), α = 10, fall over every "
              "transition of the data at the end of training (`torchrl_tels.diagnostics.awr_weight_statistics`); "
              "cells are the maze's 4-unit cells, the start cell (0, 0) and the goal cell (0, 2):", ""]
    lines += guide if guide else ["No TELS maze run records its guide's weights yet."]
    lines.append("")
    return (lines + _maze_alpha0_rows() + _maze_action_rows() + _maze_arm_rows() + _adroit_guide_rows()
            + _adroit_mode_rows() + _adroit_paper_rows())
