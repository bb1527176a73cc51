"""The reproduction study's tables, generated into RESULTS.md from the result JSONs.

    python -m study.tables            # writes study/RESULTS.md
    python -m study.tables --check    # exit 1 if RESULTS.md differs from what the JSONs give

RESULTS.md is the one place the study's numbers are published: every arm on every task (seeds,
final scores, and where a run recorded them the second-half score and the latent-scale
diagnostics), then the tables of ``summary``, ``eval_reading``, ``budget``, ``beta_rule
--report``, ``heldout_selection --table``, ``realization --table``, ``value_delivery --table``,
``model_selection --table``, ``local_q --table``, ``oracle_choice --table`` and ``model_lookahead --table``,
each under the command that prints it alone.
Nothing is trained. A new result JSON goes into RESULTS.md by running this again; the file says
it is generated and is not edited by hand.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys

from benchmarks.harness import portable, recorded_cpu, write_generated
from study import (beta_rule, budget, eval_reading, heldout_selection, latent_scale, precision,
                   local_q, model_lookahead, model_selection, oracle_choice, realization,
                   summary, value_delivery)

RESULTS = summary.HERE / "results"
OUT = summary.HERE / "RESULTS.md"
COMMAND = "python -m study.tables"
DIAGNOSTICS = ("latent_rms", "latent_step_rms")
#: The eval_reading tables published here: (arms, the arm of the paired change). Each pairs arms
#: run on one kind of CPU: the Intel Xeon arms against ``preset_avx512``, the AMD ones against ``beta0.01``.
READINGS = (
    ((summary.BETA_ARM, *eval_reading.BASELINES), "bc"),
    ((summary.AVX512_PRESET_ARM, "alpha1", "eta10", "beta0.1", "tsidm_ae_reencode"), summary.AVX512_PRESET_ARM),
    ((summary.BETA_ARM, "alpha0.3", "alpha1_epyc", "beta0.01_rerun"), summary.BETA_ARM),
)


def arm_runs() -> dict[tuple[str, str, tuple[str, ...]], list[dict]]:
    """{(arm, task, budget): [result, ...]} of every training run under ``results/``, in seed order."""
    found: dict[tuple[str, str, tuple[str, ...]], list[dict]] = {}
    for path in sorted(RESULTS.glob("*/*/seed*.json")):
        result = json.loads(path.read_text())
        if "final_normalized_score_mean" not in result:  # action-time, beta-rule and other readings
            continue
        key = (path.parent.parent.name, path.parent.name, tuple(result.get("budget") or ()))
        found.setdefault(key, []).append(result)
    for runs in found.values():
        runs.sort(key=lambda r: int(r["seed"]))
    return found


def _task_order(task: str) -> tuple[int, str]:
    return (summary.TASKS.index(task) if task in summary.TASKS else len(summary.TASKS), task)


def _mean_of(runs: list[dict], read, fmt: str) -> str:
    """The mean over the runs that recorded a value (``read`` gives None where one did not)."""
    values = [v for v in map(read, runs) if v is not None]
    if not values:
        return "—"
    text = format(statistics.mean(values), fmt)
    return text if len(values) == len(runs) else f"{text} (n={len(values)})"


def _budget(budget: tuple[str, ...]) -> str:
    if list(budget) == summary.SHARED_BUDGET:
        return "shared"
    return "`" + " ".join(budget) + "`" if budget else "none given"


def _weights(result: dict) -> str:
    """The beta of Eq. (7) and the alpha of Eq. (9) a run used ("—" where it did not record alpha)."""
    alpha = result.get("alpha")
    return f"{result.get('beta', float('nan')):g}, " + ("—" if alpha is None else f"{alpha:g}")


def arm_table() -> str:
    """One row per arm, task and budget: seeds, each seed's final score, their mean, the second-half
    score and the latent-scale diagnostics where the runs recorded them, and the CPUs; then the
    notes the runs carry."""
    lines = ["| arm | task | budget | overrides | β, α | seeds | final score per seed | mean | second-half mean "
             "| latent_rms | latent_step_rms | CPU |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    notes = []
    rows = sorted(arm_runs().items(), key=lambda kv: (kv[0][0], _task_order(kv[0][1]), kv[0][2]))
    for (arm, task, budget_), runs in rows:
        notes += [f"- {arm}, {task}, seed {r['seed']}: {r['note']}" for r in runs if r.get("note")]
        overrides = sorted({portable(" ".join(r.get("overrides") or [])) for r in runs})
        scores = [r["final_normalized_score_mean"] for r in runs]
        cpus = sorted({recorded_cpu(r) for r in runs})
        cells = [
            arm, task, _budget(budget_), " / ".join(f"`{o}`" if o else "(none)" for o in overrides),
            " / ".join(sorted({_weights(r) for r in runs})), ", ".join(str(r["seed"]) for r in runs),
            ", ".join(f"{s:.1f}" for s in scores),
            f"**{statistics.mean(scores):.1f}**", _mean_of(runs, lambda r: r.get("second_half_score_mean"), ".1f"),
            *(_mean_of(runs, lambda r, k=k: r.get("diagnostics", {}).get(k), ".4g") for k in DIAGNOSTICS),
            " / ".join("not recorded" if c == "unknown" else c for c in cpus),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines + (["", "Notes recorded with the runs:", "", *notes] if notes else []))


def render() -> str:
    readings = []
    for arms, against in READINGS:
        readings += [f"`python -m study.eval_reading --arms {' '.join(arms)} --against {against}`",
                     "", eval_reading.render(arms, against), ""]
    return "\n".join([
        "# Reproduction study: results",
        "",
        f"Generated by `{COMMAND}` from the JSONs under `study/results/` (the paper-default",
        "and baseline arms from `benchmarks/results/`); do not edit. The commands that made each arm's runs,",
        "the machines and what the study concluded are in `LOG.md`, the study's dated narrative.",
        "",
        "## The latent-scale fixes of Eq. (7)",
        "",
        "`python -m study.latent_scale`",
        "",
        latent_scale.report(),
        "",
        "## Every arm, per task",
        "",
        "Final score: the mean of a run's last `eval.last_n` evaluations (10 unless its budget says otherwise),",
        "D4RL-normalized. Second-half mean: the mean of the second half of its evaluations. `latent_rms` and",
        "`latent_step_rms`: the trained TS-IDM's latent spread and latent step on the data",
        "(`torchrl_tels.diagnostics.latent_statistics`), means over seeds. \"—\": the runs did not record it",
        "(they predate the field); \"(n=k)\": only k of the runs did. β, α: the weights of Eq. (7) and Eq. (9)",
        "the runs used, preset values included (α \"—\": the JSONs do not record it; it is the override's, else",
        "0.01). Budget \"shared\":",
        f"`{' '.join(summary.SHARED_BUDGET)}`.",
        "",
        arm_table(),
        "",
        "## Paired changes at the shared budget",
        "",
        "`python -m study.summary`",
        "",
        summary.render().rstrip("\n"),
        "",
        "## bf16 against fp32 at the shared budget",
        "",
        "`python -m study.precision`: the preset's final scores in bf16 on a CPU that multiplies it natively,",
        "paired with the same seeds in fp32; beside them, what a change of CPU alone does to the same fp32 runs.",
        "",
        precision.report(),
        "",
        "## The same runs read four ways",
        "",
        *readings,
        "## Longer budgets on the preset",
        "",
        "`python -m study.budget`",
        "",
        budget.render(),
        "",
        "The preset at the paper's whole budget (`budget=paper`: about 36k TS-IDM and 100k policy steps, 20",
        "evaluations of 10 episodes), read as Table 1 is, by the last 10 of the 20 evaluations. \"Every episode",
        "fell\": evaluations whose episodes all ended before 1000 steps. BC: the baseline grid's runs at the",
        "shared budget and at 50k policy steps (`benchmarks/results/long50k`; \"—\": not run). The last column",
        "is the final score's distance to the study's target, Table 1's TELS mean minus its std (negative: short",
        "of it).",
        "",
        budget.render_paper_budget(),
        "",
        "## The beta rule of App. B.5 read two ways",
        "",
        "`python -m study.beta_rule --report`",
        "",
        beta_rule.report(),
        "",
        *heldout_section(),
        *realization_section(),
        *value_delivery_section(),
        *model_selection_section(),
        *local_q_section(),
        *oracle_choice_section(),
        *model_lookahead_section(),
    ])


def reading_section(script, title: str, description: list[str], after_table: tuple[str, ...] = ()) -> list[str]:
    """A section for the readings ``script`` (a module with ``RESULTS`` and ``table()``) saved, if any."""
    if not any(script.RESULTS.glob("*.json")):
        return []
    return [f"## {title}", "", *description, "", script.table(), "", *after_table]


def heldout_section() -> list[str]:
    return reading_section(heldout_selection, "Held-out transitions against the score over a long stage 2", [
        "`python -m study.heldout_selection --table`: the recipe's default at 3k TS-IDM + 20k",
        "policy steps, trained on a whole-trajectory subset, the file's other trajectories held out; an evaluation",
        "(ten episodes) every 2k steps. \"Score at least held-out action MSE\": the score of the policy that an",
        "offline rule picking the lowest held-out Eq. (11) action error would keep. Rank correlation over the",
        "evaluations: negative when a lower held-out error goes with a higher score. Guide error / step: 1 is no",
        "better than \"stay put\".",
    ], ("![score and action error over policy steps](results/heldout_selection/heldout_selection.png)", ""))


def realization_section() -> list[str]:
    return reading_section(realization, "Do the states reached land where the guide proposed?", [
        f"`{realization.COMMAND} --table`: finished runs re-rolled for ten fresh episodes (no training).",
        "Data: the guide's error in predicting its training transitions' next latent, over their latent step",
        "(0 exact, 1 no better than \"stay put\"). Rollouts: the proposed step over the data's, and the error of",
        "the state reached against the proposal, over the proposed step (0: Eq. (11) lands on the proposal; 1: no",
        "better than staying put), over whole episodes and over their opening steps, which come before a fall.",
        "Arm `long20k`: the preset at 3k TS-IDM + 20k policy steps (`benchmarks/results/long20k`); arm `reach1`:",
        "the preset with `guide.reach_weight=1` at the shared budget (`results/reach1`).",
    ])


def value_delivery_section() -> list[str]:
    return reading_section(value_delivery, "Is the value the guide promises delivered?", [
        f"`{value_delivery.COMMAND} --table`: V (Eq. 8) trained again exactly as each finished run trained it",
        "(\"V loss\": the largest relative gap between the retrained V's logged losses and the run's; 0 is the run's",
        f"V), read from {value_delivery.STATES} of the run's training states. V rank: rank correlation of V(φ(s)) with the",
        "data's discounted return-to-go, where the data records the episode to its termination. The simulator is",
        "restarted from each data state; promised: V of the guide's proposal, delivered: V at the state the",
        "actor's action reaches, best of 16 random actions: the largest V any of 16 uniform random actions",
        "reaches; each minus V at the state the data's own action reaches (a fall reaches value 0), over V's",
        "standard deviation on the data, medians, with the share of states above 0 (for the random actions: the",
        "share where the promise exceeds their best). Reward: the actor's step's against the data action's. Rank promised, delivered: over the",
        f"states. {value_delivery.HORIZON}-step return: discounted (γ of the run) from the data states, medians, for",
        "the actor, for BC fitted to the same transitions, and the data's own recorded return; actor above BC:",
        "the share of states. Arm `long20k`: the preset at 3k TS-IDM + 20k policy steps; arm `reach1`: the preset",
        "with `guide.reach_weight=1` at the shared budget (`results/reach1`).",
    ])


def model_selection_section() -> list[str]:
    ms = model_selection
    return reading_section(ms, "Can the TS-IDM's forward model choose an action that delivers?", [
        f"`{ms.COMMAND} --table`: the same finished runs and V as above, from the same start states. Candidates:",
        f"the actor's latent action h_inv(z, π_g(z)) and {ms.CANDIDATES - 1} Gaussian perturbations of it",
        f"({ms.SCALE} × the data's latent-action std per dimension). Model rank: within a state, the rank",
        "correlation over the candidates of V at the forward model's predicted next latent z + h_fwd(z, z_a) with",
        "V at the state the simulator reaches with the candidate's action (0 on a fall), median over states;",
        "T-symmetry rank: the same for minus Eq. (6)'s consistency error. Gains: V at the reached state minus V at",
        "the state the actor's own action reaches, over V's standard deviation on the data, medians (share above",
        "0): for the candidate of largest predicted V (\"chosen\", with the model's own predicted gain), for the best",
        "candidate in hindsight, and for one fixed other candidate. Local, from the first",
        f"{ms.LOCAL_STATES} start states: each candidate's action first, then the actor, for the horizon's",
        "steps; within a state, the rank correlation over the candidates of this discounted return with V at the",
        "state the first step reached, with V at the predicted next latent, with the first step's reward and with",
        "r + γ·V(s'), and, as the ceiling of any ranking, with the same return after first actions nudged by",
        f"{ms.NUDGE:g} of the action box's half-width (1: the returns that follow are fully predictable from the",
        "first action); medians over states. Return spread: the std of these returns over the candidates, in V's",
        "units, over V's std on the data (median over states), the precision a choice among them needs. The",
        "return gain of the chosen candidate's first step over the actor's own: median (share above 0).",
        "Return over the horizon: discounted, medians, acting at every step with the actor's own candidate, the",
        f"chosen one, or one at random. The horizon of every return in a row is its own column ({value_delivery.HORIZON}",
        "unless the reading says otherwise; the arm's name then ends in the horizon).",
        f"Episodes: the normalized score over {ms.EPISODES} evaluation episodes seeded alike for the three.",
    ])


def local_q_section() -> list[str]:
    lq = local_q
    return reading_section(lq, "Does a Q, IQL's or one fitted to the data's returns, order one step's alternatives?", [
        f"`{lq.COMMAND} --table`: IQL (torchrl's offline config, {lq.IQL_STEPS} steps) trained on each",
        "TELS run's own training transitions, read on the start states, candidates and returns of the local",
        "columns above (over the row's horizon): within a state, the rank correlation over the candidates of IQL's",
        "min(Q₁, Q₂)(s, a) with the discounted return after (the candidate's action, then the TELS actor), median",
        "over states. IQL's score: its one evaluation at the end of training.",
        "",
        f"The return Q ({lq.RETURN_Q_STEPS} steps of least squares; rows without it predate it) is fitted without",
        "bootstrapping to the data's own discounted return over the row's horizon, on the rows that record it in",
        f"full, leaving out {lq.HELD_OUT:.0%} of the episodes. Held-out rank: across the left-out rows, the rank",
        "correlation of its values with their returns (does it order states?). Rank with the return after: as IQL's",
        "(does it order one state's actions?). Return gains, over the actor's own candidate, in the environment's",
        "reward units: of the candidate it ranks first, and of the best candidate (the one-step oracle's); median",
        "over states (share of states above the actor's).",
    ])


def oracle_choice_section() -> list[str]:
    oc = oracle_choice
    return reading_section(oc, "What would a perfect value gain from one step's alternatives?", [
        f"`{oc.COMMAND} --table`: the candidates of the model-selection table ({oc.CANDIDATES} latent actions around",
        "the actor's own), ranked by the truth: from the simulator's exact state, each candidate's action, then the",
        "actor, for the lookahead's number of steps, discounted as V is; the candidate of the largest return is",
        f"acted. The first {oc.STEPS} steps of each episode, reset alike for the actor and this oracle: the mean",
        "undiscounted return over the window, the mean paired change (episodes where the oracle is up), the median",
        "number of steps each lasted (the window's length where it did not fall), and the share of the oracle's",
        "decisions that were not the actor's own candidate. Under the table, per task and lookahead: the paired",
        "change pooled over every seed's episodes.",
    ])


def model_lookahead_section() -> list[str]:
    ml = model_lookahead
    return reading_section(ml, "Does the forward model, rolled further ahead, see what one step does not?", [
        f"`{ml.COMMAND} --table`: the start states, candidates and returns of the model-selection table's local",
        "columns (over the row's horizon). From each candidate's predicted next latent, the actor acts in the",
        "TS-IDM's forward model, z_{t+1} = z_t + h_fwd(z_t, h_inv(z_t, π_g(z_t))), for L − 1 more steps; within a",
        "state, the rank correlation over the candidates of V(z_L) with the return after, median over states",
        "(L = 1 is the model rank of the local columns). Drift: the RMS distance the actor's own candidate's latent",
        "has moved from the start after L model steps, over the data's RMS latent step.",
    ])


def main() -> int:
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare with RESULTS.md instead of writing it")
    args = parser.parse_args()
    return write_generated(OUT, render(), COMMAND, args.check)


if __name__ == "__main__":
    sys.exit(main())
