"""The latent-scale fixes of Eq. (7) against the preset, the paper's reading and BC, with the mechanism's numbers.

    python -m study.latent_scale

prints one table per dataset (``study.tables`` writes it into RESULTS.md). Rows are
arms at the shared budget (3k TS-IDM, 5k policy steps, ten evaluations of ten episodes):

- ``paper``: the paper's reading (the baseline grid's TELS runs, Eq. 7 and Eq. 11 as written);
- ``preset``: the ``mujoco`` domain before the fix (re-encoding, beta = 0.01, alpha = 1; arms
  ``alpha1`` on the Intel Xeon, ``alpha1_epyc`` on halfcheetah);
- ``standardized`` / ``relative``: beta = 1, ``tsidm.latent_scale`` set, the guide's T-symmetry term
  divided by the data's mean squared latent step (``guide.tsym_relative=true``), alpha = 1 and re-encoding;
- ``standardized, guide ℓ_Tsym ×50``: the same with ``guide.tsym_weight=50``, which makes the guide's
  T-symmetry term a sizeable share of its state term on the hopper sets;
- ``TSRL-style weighting``: the free latent with TSRL's term weights, beta = 1 and
  ``tsidm.term_weights={dyn: 0.1, ode: 1, tsym: 0.1}``, and the guide's T-symmetry weight of TSRL's
  policy (100 on a mean over latent entries, i.e. ``guide.tsym_weight`` = 100 / latent size: 9.09 on
  hopper, 5.88 on walker2d and halfcheetah); TSRL's ℓ_dyn-free pre-training phase and L1 penalty are
  not reproduced;
- ``preset + reachability term``: ``guide.reach_weight=1`` (:class:`~torchrl_tels.objectives.TSymGuideLoss`);
- ``in-sample guide of Eq. (10)``: the preset with the paper's AntMaze guide, ``guide.mode=stochastic``, at
  POR's MuJoCo temperature (``guide.alpha=3``) and IQL's reward scale 1000 / (return range) of each set
  (``dataset.reward_scale``, :func:`benchmarks.baselines.return_range_scale`), so that V is never read at a
  state the data does not hold;
- ``BC``: the baseline grid's BC on the same file and budget.

Columns: each seed's final score (mean of the ten evaluations), the mean, the mean of the second half of
the evaluations, the change from BC and from the preset (means over the seeds both arms have), and,
where the runs recorded them, the trained TS-IDM's latent RMS spread and RMS step on the data, the
guide's T-symmetry term over its state term at the end of training, the RMS latent step the guide
proposes in the evaluation rollouts over the data's RMS latent step (1: steps of the data's size; far
above 1: proposals off the data), and how many evaluations were flagged frozen.
"""
from __future__ import annotations

import argparse
import json
import re
import statistics

from benchmarks.harness import recorded_cpu
from study import summary

#: (row label, arm folders under results/ tried in order, or a grid method)
ARMS = (
    ("paper", ("grid:tels",)),
    ("preset", ("alpha1", "alpha1_epyc")),
    ("standardized", ("scale_standardized",)),
    ("relative", ("scale_relative",)),
    ("standardized, guide ℓ_Tsym ×50", ("scale_standardized_tsym50",)),
    ("TSRL-style weighting", ("tsrl_weighting",)),
    ("preset + reachability term (guide.reach_weight=1)", ("reach1",)),
    ("preset with the in-sample guide of Eq. (10) (guide.mode=stochastic, α = 3, IQL reward scale)", ("awr_guide",)),
    ("BC", ("grid:bc",)),
)
#: The ``ae`` lead untangled: the ``ae`` TS-IDM (ℓ_rec only) under the preset of the time (alpha = 0.01,
#: re-encoding, beta = 0.01), with the guide's T-symmetry term (through h_fwd/h_rvs that ``ae`` never
#: trains) and without it (``guide.tsym_regularizer=false``).
UNTANGLE = (("guide ℓ_Tsym on", "tsidm_ae_reencode"), ("guide ℓ_Tsym off", "tsidm_ae_reencode_notsym"))
HELD_OUT = ("halfcheetah-v5-sac-medium-10k",
            (("preset", ("heldout_preset",)), ("standardized", ("heldout_standardized",)),
             ("standardized, guide ℓ_Tsym ×50", ("heldout_standardized_tsym50",)), ("BC", ("heldout_bc",))))


def _runs(sources: tuple[str, ...], task: str) -> dict[int, dict]:
    for source in sources:
        if source.startswith("grid:"):
            folder = summary.GRID / source[len("grid:"):] / task
            found = summary.seed_results(folder, summary.on_grid_budget)
        else:
            found = summary.seed_results(summary.HERE / "results" / source / task, lambda r: True)
        if found:
            return found
    return {}


def _final_ratio(result: dict) -> float | None:
    history = result.get("diagnostics", {}).get("guide_history", {}).get("guide/tsym_to_state_ratio")
    return statistics.mean(v for _, v in history[-5:]) if history else None


def _rollout_step(result: dict) -> float | None:
    data_step = result.get("diagnostics", {}).get("latent_step_rms")
    steps = [e["guide_step_rms"] for e in result["evaluations"] if "guide_step_rms" in e]
    return statistics.mean(steps) / data_step if steps and data_step else None


def _realized_error(result: dict) -> float | None:
    """Mean over a run's evaluations of the rollouts' realized error ratio, where it recorded one."""
    values = [e["realized_error_ratio"] for e in result["evaluations"] if e.get("realized_error_ratio") is not None]
    return statistics.mean(values) if values else None


def _mean(values) -> str:
    values = [v for v in values if v is not None]
    return f"{statistics.mean(values):.3g}" if values else "—"


def _change(runs: dict[int, dict], other: dict[int, dict]) -> str:
    seeds = sorted(set(runs) & set(other))
    if not seeds:
        return "—"
    diffs = [runs[s]["final_normalized_score_mean"] - other[s]["final_normalized_score_mean"] for s in seeds]
    ups = sum(d > 0 for d in diffs)
    return f"{statistics.mean(diffs):+.1f} ({ups}/{len(diffs)} up)"


def _frozen_cell(runs, seeds, frozen, has_frozen) -> str:
    if not has_frozen:
        return "—"
    return f"{sum(frozen)} of {sum(len(runs[s]['evaluations']) for s in seeds)}"


def _same_cpu_preset(runs: dict[int, dict], presets: list[dict[int, dict]], preset: dict[int, dict]) -> dict[int, dict]:
    """Of ``presets`` (the preset's runs from each of its sources), the one from the kind of CPU ``runs``
    recorded (same seeds are exact only on one kind), else ``preset`` (the table's preset row)."""
    cpus = {recorded_cpu(r) for r in runs.values()}
    return next((c for c in presets if c and {recorded_cpu(r) for r in c.values()} == cpus), preset)


def task_table(task: str, arms=ARMS) -> list[str]:
    found = {label: _runs(sources, task) for label, sources in arms}
    bc, preset = found.get("BC", {}), found.get("preset", {})
    presets = [_runs((source,), task) for source in dict(ARMS)["preset"]]
    lines = [f"**{task}**", "",
             "| arm | seeds | final score per seed | mean | second-half mean | vs BC | vs preset | latent_rms | "
             "latent_step_rms | guide ℓ_Tsym / state term | rollout step / data step | rollout realized error ratio | "
             "frozen evaluations |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, runs in found.items():
        if not runs:
            continue
        seeds = sorted(runs)
        scores = [runs[s]["final_normalized_score_mean"] for s in seeds]
        halves = [runs[s].get("second_half_score_mean") for s in seeds]
        diagnostics = [runs[s].get("diagnostics", {}) for s in seeds]
        frozen = [sum(e.get("frozen", False) for e in runs[s]["evaluations"]) for s in seeds]
        has_frozen = any("frozen" in e for s in seeds for e in runs[s]["evaluations"])
        lines.append(
            f"| {label} | {', '.join(map(str, seeds))} | {', '.join(f'{x:.1f}' for x in scores)} | "
            f"**{statistics.mean(scores):.1f}** | {_mean(halves)} | "
            f"{'—' if label == 'BC' else _change(runs, bc)} | "
            f"{'—' if label == 'preset' else _change(runs, _same_cpu_preset(runs, presets, preset))} | "
            f"{_mean(d.get('latent_rms') for d in diagnostics)} | {_mean(d.get('latent_step_rms') for d in diagnostics)} | "
            f"{_mean(_final_ratio(runs[s]) for s in seeds)} | {_mean(_rollout_step(runs[s]) for s in seeds)} | "
            f"{_mean(_realized_error(runs[s]) for s in seeds)} | {_frozen_cell(runs, seeds, frozen, has_frozen)} |")
    return lines + [""]


def _around(history: list, step: int, width: int = 4) -> float:
    """Mean of the ``width`` logged values ending at ``step`` (one batch each, so noisy alone)."""
    values = [v for s, v in history if s <= step][-width:]
    return statistics.mean(values)


def shrink_table() -> list[str]:
    """Stage 1 alone, longer than the study's 3k steps: does the latent space shrink? (``latent_shrink``)"""
    folder = summary.HERE / "results" / "latent_shrink"
    runs = sorted((json.loads(p.read_text()) for p in folder.glob("*/seed*.json")),
                  key=lambda run: (run["option"], run["seed"]))
    if not runs:
        return []
    lines = ["Stage 1 alone on hopper-medium-v2 10k, beta = 1 (`python -m study.latent_shrink`); "
             "each entry is the mean of the four batch values logged up to that step (every 250 steps), "
             "except the first, one batch at step 250. "
             "step / spread is latent_step_rms / latent_rms: the dynamics' share of the latent space's size, "
             "which a standardized latent can still shrink though its spread is fixed:", "",
             "| latent_scale | seed | steps | latent_rms at 250 / 3k / end | latent_step_rms at 3k / end | "
             "step / spread at 3k / end | ℓ_dyn at 3k / end | ℓ_Tsym at 3k / end |", "|---|---|---|---|---|---|---|---|"]
    for run in runs:
        h, end = run["history"], run["steps"]
        rms, step = h["latent_rms"], h["latent_step_rms"]
        lines.append(
            f"| {run['option']} | {run['seed']} | {end} | {rms[0][1]:.3f} / {_around(rms, 3000):.3f} / "
            f"{_around(rms, end):.3f} | {_around(step, 3000):.3f} / {_around(step, end):.3f} | "
            f"{_around(step, 3000) / _around(rms, 3000):.2f} / {_around(step, end) / _around(rms, end):.2f} | "
            f"{_around(h['ell_dyn'], 3000):.4f} / {_around(h['ell_dyn'], end):.4f} | "
            f"{_around(h['ell_tsym'], 3000):.4f} / {_around(h['ell_tsym'], end):.4f} |")
    return lines + [""]


def untangle_table() -> list[str]:
    (on_label, on_arm), (off_label, off_arm) = UNTANGLE
    rows = []
    for task in summary.TASKS:
        on, off = _runs((on_arm,), task), _runs((off_arm,), task)
        seeds = sorted(set(on) & set(off))
        if not seeds:
            continue
        score = lambda runs: ", ".join(f"{runs[s]['final_normalized_score_mean']:.1f}" for s in seeds)
        rows.append(f"| {task} | {', '.join(map(str, seeds))} | {score(on)} | {score(off)} | {_change(off, on)} |")
    if not rows:
        return []
    return ["The `ae` lead untangled: the `ae` TS-IDM (ℓ_rec only; alpha = 0.01, re-encoding, beta = 0.01), "
            "with and without the guide's T-symmetry term, which `ae` applies through the h_fwd/h_rvs it never "
            "trains:", "",
            f"| task | seeds | {on_label} | {off_label} | off − on |", "|---|---|---|---|---|", *rows, ""]


def aggregate_table(arms=ARMS) -> list[str]:
    """IQM and mean over the four sets × the seeds every set has, with stratified-bootstrap intervals."""
    import numpy as np

    from torchrl_tels import stats

    rows = []
    for label, sources in arms:
        by_task = [_runs(sources, task) for task in summary.TASKS]
        seeds = sorted(set.intersection(*(set(runs) for runs in by_task)))
        if len(seeds) < 2:
            continue
        scores = np.array([[runs[s]["final_normalized_score_mean"] for runs in by_task] for s in seeds])
        cells = [stats.stratified_bootstrap_ci(scores, statistic) for statistic in (stats.iqm, stats.mean)]
        rows.append(f"| {label} | {len(seeds)} × {len(by_task)} | "
                    + " | ".join(f"**{p:.1f}** [{lo:.1f}, {hi:.1f}]" for p, lo, hi in cells) + " |")
    if not rows:
        return []
    return ["Over the four sets (arms with at least two seeds on every set): interquartile mean and mean of the "
            "final scores over tasks × seeds, with 95 % stratified-bootstrap intervals (`torchrl_tels/stats.py`):",
            "", "| arm | seeds × tasks | IQM [95 % CI] | mean [95 % CI] |", "|---|---|---|---|", *rows, ""]


#: Arms whose saved runs ``action_error`` read (results/action_error/<folder>-<task>-seed<k>.json).
ACTION_ERROR_ARMS = (("standardized", "scale_standardized"), ("relative", "scale_relative"),
                     ("standardized, guide ℓ_Tsym ×50", "scale_standardized_tsym50"),
                     ("TSRL-style weighting", "tsrl_weighting"), ("`ae`, guide ℓ_Tsym off", "tsidm_ae_reencode_notsym"),
                     ("preset", "heldout_preset"), ("standardized", "heldout_standardized"),
                     ("standardized, guide ℓ_Tsym ×50", "heldout_standardized_tsym50"))


#: ``<arm>-<task>-seed<k>``: the file name of a per-run diagnostic (arm folder names hold no '-').
RUN_RESULT_NAME = re.compile(r"(?P<arm>[^-]+)-(?P<task>.+)-seed(?P<seed>\d+)")


def run_results(folder) -> dict[tuple[str, str, int], dict]:
    """``{(arm, task, seed): record}`` of the per-run diagnostics in ``folder``."""
    found = {}
    for path in sorted(folder.glob("*.json")):
        match = RUN_RESULT_NAME.fullmatch(path.stem)
        if match is None:
            raise SystemExit(f"error: {path} is not named <arm>-<task>-seed<k>.json")
        found[match["arm"], match["task"], int(match["seed"])] = json.loads(path.read_text())
    return found


def action_error_table(arms=ACTION_ERROR_ARMS, tasks=(*summary.TASKS, HELD_OUT[0])) -> list[str]:
    """Where each arm's action error comes from, per seed (``python -m study.action_error``)."""
    records = run_results(summary.HERE / "results" / "action_error")
    rows = []
    for task in tasks:
        for label, arm in arms:
            for seed in sorted(s for a, t, s in records if (a, t) == (arm, task)):
                record = records[arm, task, seed]
                run = summary.seed_results(summary.HERE / "results" / arm / task, lambda r: True).get(seed)
                train = record["train"]
                mse = train["action_mse"]
                rows.append(f"| {task} | {label} | {seed} | {run['final_normalized_score_mean']:.1f} | "
                            f"{mse['oracle']:.4f} | {mse[record['acting']]:.4f} | {mse['bc']:.4f} | "
                            f"{train['guide_step_ratio']:.2f} | {train['guide_step_cosine']:.2f} |"
                            if run else f"| {task} | {label} | {seed} | (no result) | | | | | |")
    if not rows:
        return []
    return ["Where the action error comes from, on each run's own training transitions "
            "(`python -m study.action_error --run-dir <run> --name <arm>-<task>-seed<k>` on the saved "
            "runs): mean squared action error of Eq. (11) fed the true next latent (the TS-IDM's part), of the actor "
            "as it acts (guide proposal, re-encoded where the arm re-encodes), and of BC fitted by MSE on the same "
            "transitions (5k steps); then the guide's proposed latent step over the data's (RMS) and the mean "
            "cosine between the two steps:", "",
            "| task | arm | seed | score | ψ_a(h_inv(z, z')) | actor | BC | proposed / data step | cosine |",
            "|---|---|---|---|---|---|---|---|---|", *rows, ""]


def proposal_cap_table(arms=ACTION_ERROR_ARMS) -> list[str]:
    """The runs whose proposals left the data's step scale, re-evaluated with the step capped
    (``python -m study.proposal_cap``)."""
    labels = dict((arm, label) for label, arm in arms)
    rows, caps = [], []
    records = {key: record for key, record in run_results(summary.HERE / "results" / "proposal_cap").items()
               if key[0] in labels}  # not another study's readings (the Adroit runs: study/domains.py)
    errors = run_results(summary.HERE / "results" / "action_error")
    for record in records.values():
        caps += [name for name in record["scores"] if name not in caps]
    for (arm, task, seed), record in records.items():
        ratio = errors[arm, task, seed]["train"].get("guide_step_ratio") if (arm, task, seed) in errors else None
        cells = [f"{record['scores'][c]:.1f}" if c in record["scores"] else "—" for c in caps]
        rows.append(f"| {task} | {labels.get(arm, arm)} | {seed} | {'—' if ratio is None else f'{ratio:.2f}'} | "
                    f"{' | '.join(cells)} |")
    if not rows:
        return []
    return ["The same saved runs re-evaluated with the guide's proposed step capped at k times the data's RMS latent "
            "step (`python -m study.proposal_cap --run-dir <run> --name <arm>-<task>-seed<k>`; no "
            "training; ten episodes per reading, the same episodes for every cap):", "",
            "| task | arm | seed | proposed / data step | " + " | ".join(caps) + " |",
            "|---|---|---|---|" + "---|" * len(caps), *rows, ""]


def report() -> str:
    lines = shrink_table() + aggregate_table() + untangle_table() + action_error_table() + proposal_cap_table()
    lines += ["Per task: \"vs preset\" is the mean change over the seeds both have against the preset's runs on the "
              "same kind of CPU (`alpha1` on the Intel Xeon, `alpha1_epyc` on the AMD EPYC; the preset row shows "
              "`alpha1`); \"rollout realized error ratio\": the mean over a run's evaluations of "
              "`realized_error_ratio` (`torchrl_tels.diagnostics.rollout_statistics`), where the run recorded it.", ""]
    for task in summary.TASKS:
        lines += task_table(task)
    task, arms = HELD_OUT
    if any(_runs(sources, task) for _, sources in arms):
        lines += ["Held out from every choice of the study (10 episodes of the HalfCheetah-v5 SAC set, "
                  "evaluated on HalfCheetah-v5 with the halfcheetah references):", ""]
        lines += task_table(task, arms)
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.parse_args()
    print(report())


if __name__ == "__main__":
    main()
