"""One table of every training-time variant of the reproduction study, at the shared budget.

    python -m study.summary

prints it (``study.tables`` writes it into RESULTS.md with the study's other tables).

Rows are the variants under ``results/<variant>/`` that ran with the shared budget
(``run_choice --budget tsidm.steps=3000 optim.steps=5000 eval.interval=500 eval.episodes=10``)
and the Table 3 ablations of the baseline grid (``benchmarks/results/``, ``run_grid`` at the same
budget); columns are tasks. A cell lists the score of each seed (final = mean of the last 10
evaluations) and, after the arrow, the mean change over the seeds both have against the arm the
variant was built on: the paper-default arm (the grid's TELS runs), the ``reencode`` arm
(re-encoded proposals, beta = 1) for variants that ran with ``guide.reencode_proposal=true`` on
top, or the ``beta0.01`` arm (re-encoding and beta = 0.01) for variants that ran on top of both.
Same-seed runs are exact only on one kind of CPU, so on a task where a variant's runs all recorded
an Intel Xeon, it is paired against ``preset_avx512``, the ``beta0.01`` settings rerun on that
machine. (The AMD EPYC machines also report AVX-512, but they reproduce the ``beta0.01`` arm's
stage-1 losses bit for bit, so they pair with it: the CPU model decides, not the AVX level.)
Variants that also ran with alpha = 1 are paired, task by task, against the alpha = 1 arm run on
the same kind of CPU: ``alpha1`` or ``alpha1_epyc``. A preset value a variant did not set itself
is shown in its overrides with "(preset)".
BC on the same file and budget closes the table.
Variants that change which transitions are trained on (``dataset.size`` hold-outs) or the budget
are diagnostics, not choices, and are left out; reward scaling (``dataset.reward_scale``) is
choice 6 and stays.
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from benchmarks.harness import recorded_cpu, REPO

HERE = Path(__file__).resolve().parent
GRID = REPO / "benchmarks" / "results"  # the baseline grid's results
SHARED_BUDGET = ["tsidm.steps=3000", "optim.steps=5000", "eval.interval=500", "eval.episodes=10"]
GRID_BUDGET = ("--steps=5000", "--tsidm-steps=3000", "--eval-interval=500", "--eval-episodes=10")
TASKS = ("hopper-medium-v2-10k", "hopper-medium-replay-v2-10k", "walker2d-medium-v2-10k", "halfcheetah-medium-v2-10k")
ABLATIONS = ("tels_ae", "tels_dyn", "tels_ode")  # Table 3 rows of the baseline grid
DATA_SUBSETS = ("dataset.size=", "dataset.delete_")  # hold-out diagnostics, not choices
REENCODE_ARM = "reencode"  # choice 7 alone: re-encoded proposals, beta = 1, alpha = 0.01
BETA_ARM = "beta0.01"  # choice 5 on top of choice 7: re-encoding and beta = 0.01, alpha = 0.01
# The beta0.01 settings again, on an Intel Xeon (AVX-512): same-seed runs on another CPU differ in
# their numerics, so that machine's runs are compared against this arm.
AVX512_PRESET_ARM = "preset_avx512"
XEON = "Intel(R) Xeon(R)"  # how harness.machine_description() names that machine's CPU
# alpha = 1 on top of beta0.01 (the mujoco preset's values), run on both kinds of CPU.
ALPHA1_ARMS = ("alpha1", "alpha1_epyc")
ALPHA1 = ("guide.alpha=1", "guide.alpha=1.0")


def seed_results(folder: Path, wanted) -> dict[int, dict]:
    """{seed: result} of the ``seed*.json`` runs in ``folder`` (one arm, one task) that ``wanted`` accepts."""
    found = {}
    for path in sorted(folder.glob("seed*.json")):
        result = json.loads(path.read_text())
        if wanted(result):
            found[int(result["seed"])] = result
    return found


def evaluation_scores(result: dict) -> list[float]:
    """The normalized score of each of a run's evaluations, in order."""
    return [evaluation["score"] for evaluation in result["evaluations"]]


def on_grid_budget(result: dict) -> bool:
    """Whether a baseline grid result ran at the study's shared budget."""
    return all(flag in result.get("command", "") for flag in GRID_BUDGET)


def _grid_arm(method: str) -> dict[str, dict[int, float]]:
    """{task: {seed: final score}} of the baseline grid's runs of ``method`` at the shared budget."""
    found: dict[str, dict[int, float]] = {}
    for path in sorted((GRID / method).glob("*/seed*.json")):
        result = json.loads(path.read_text())
        if on_grid_budget(result):
            found.setdefault(path.parent.name, {})[int(result["seed"])] = result["final_normalized_score_mean"]
    return found


def _variant_arms() -> dict[str, tuple[str, dict, dict[str, set[str]]]]:
    """{variant: (its overrides, {task: {seed: final score}}, {task: the CPUs its runs recorded})}."""
    arms = {}
    for folder in sorted(p for p in (HERE / "results").iterdir() if p.is_dir()):
        found: dict[str, dict[int, float]] = {}
        overrides: dict[str, None] = {}  # ordered set: sizes that follow the task differ per task
        cpus: dict[str, set[str]] = {}
        for path in sorted(folder.glob("*/seed*.json")):
            result = json.loads(path.read_text())
            if (result.get("budget") == SHARED_BUDGET and "variant" in result
                    and not any(o.startswith(DATA_SUBSETS) for o in result["overrides"])):
                found.setdefault(path.parent.name, {})[int(result["seed"])] = result["final_normalized_score_mean"]
                given = list(result["overrides"])
                if not any(o.startswith("tsidm.beta=") for o in given) and result.get("beta", 1.0) != 1.0:
                    given.append(f"tsidm.beta={result['beta']:g} (preset)")  # the preset's beta, not an override
                if not any(o.startswith("guide.alpha=") for o in given) and result.get("alpha", 0.01) != 0.01:
                    given.append(f"guide.alpha={result['alpha']:g} (preset)")  # the preset's alpha, not an override
                overrides[" ".join(given)] = None
                cpus.setdefault(path.parent.name, set()).add(recorded_cpu(result))
        if found:
            arms[folder.name] = ("` / `".join(overrides), found, cpus)
    return arms


def _on_xeon(seen: set[str]) -> bool | None:
    """True or False when every run recorded an Intel Xeon or none did; None for a mix."""
    xeon = {XEON in cpu for cpu in seen}
    return next(iter(xeon)) if len(xeon) == 1 else None


def _alpha1_bases(variants: dict, cpus: dict[str, set[str]]) -> dict[str, tuple[str, dict]]:
    """{task: (arm, its scores)}: the alpha = 1 arm whose runs on the task used the same kind of CPU."""
    bases = {}
    for task, seen in cpus.items():
        for arm in ALPHA1_ARMS:
            if arm in variants and task in variants[arm][1] and _on_xeon(variants[arm][2][task]) is not None \
                    and _on_xeon(variants[arm][2][task]) == _on_xeon(seen):
                bases[task] = (arm, variants[arm][1])
    return bases


def _cell(scores: dict[int, float], default: dict[int, float] | None) -> str:
    if not scores:
        return ""
    seeds = sorted(scores)
    label = (lambda s: "") if seeds == list(range(len(seeds))) else (lambda s: f"s{s} ")
    text = ", ".join(f"{label(s)}{scores[s]:.1f}" for s in seeds)
    if default is not None:
        paired = [scores[s] - default[s] for s in scores if s in default]
        if paired:
            text += f" → {statistics.mean(paired):+.1f}"
    return text


def _means(arm: dict[str, dict[int, float]]) -> str:
    return " / ".join(f"{statistics.mean(arm[t].values()):.1f}" if t in arm else "—" for t in TASKS)


def _bases(name: str, overrides: str, cpus: dict[str, set[str]], variants: dict,
           default: dict) -> tuple[tuple[str, dict], dict[str, tuple[str, dict]]]:
    """The arm a variant is paired against, ``(name, {task: {seed: score}})``, and the tasks where another arm
    replaces it (``{task: (name, scores)}``): the arm it was built on, or the same settings on the same kind of
    CPU (module docstring)."""
    reencode = variants.get(REENCODE_ARM, ("", {}, {}))[1]
    beta_arm = variants.get(BETA_ARM, ("", {}, {}))[1]
    avx512_arm = variants.get(AVX512_PRESET_ARM, ("", {}, {}))[1]
    on_reencode = name != REENCODE_ARM and "guide.reencode_proposal=true" in overrides
    on_beta = name != BETA_ARM and on_reencode and "tsidm.beta=0.01" in overrides
    base = ((BETA_ARM, beta_arm) if on_beta else ("reencode", reencode) if on_reencode else ("paper", default))
    # Same-seed pairs are exact only on one kind of CPU: a task whose runs all recorded an
    # Intel Xeon CPU is paired against the preset rerun on that machine.
    per_task = {t: (AVX512_PRESET_ARM, avx512_arm) for t, seen in cpus.items()
                if name != AVX512_PRESET_ARM and on_reencode and avx512_arm
                and all(XEON in cpu for cpu in seen)}
    if on_beta and name not in ALPHA1_ARMS and any(o in ALPHA1 for o in overrides.split()):
        per_task = _alpha1_bases(variants, cpus)
    return base, per_task


def paired_changes() -> dict[str, dict[str, tuple[str, dict[int, float]]]]:
    """``{variant: {task: (the arm it is paired against, {seed: change of the final score})}}``, the numbers
    behind :func:`render`'s arrows, for the variants at the shared budget (the grid's Table 3 ablations and BC
    are paired against the paper defaults)."""
    default, variants = _grid_arm("tels"), _variant_arms()
    arms = {name: (overrides, found, cpus) for name, (overrides, found, cpus) in variants.items()}
    arms.update({method: ("", _grid_arm(method), {}) for method in (*ABLATIONS, "bc")})
    changes = {}
    for name, (overrides, found, cpus) in arms.items():
        base, per_task = _bases(name, overrides, cpus, variants, default)
        for task, scores in found.items():
            against, base_scores = per_task.get(task, base)
            paired = {s: scores[s] - base_scores[task][s] for s in scores if s in base_scores.get(task, {})}
            if paired:
                changes.setdefault(name, {})[task] = (against, paired)
    return changes


def render() -> str:
    default, bc, variants = _grid_arm("tels"), _grid_arm("bc"), _variant_arms()
    reencode = variants.get(REENCODE_ARM, ("", {}, {}))[1]
    beta_arm = variants.get(BETA_ARM, ("", {}, {}))[1]
    avx512_arm = variants.get(AVX512_PRESET_ARM, ("", {}, {}))[1]
    lines = ["| variant | overrides | against | " + " | ".join(TASKS) + " |", "|---" * (len(TASKS) + 3) + "|"]

    def row(name: str, overrides: str, found: dict, base: tuple[str, dict] | None = ("paper", default),
            per_task: dict[str, tuple[str, dict]] | None = None) -> None:
        bases = {t: (per_task or {}).get(t, base) for t in TASKS}
        cells = [_cell(found.get(t, {}), bases[t][1].get(t, {}) if bases[t] else None) for t in TASKS]
        groups: dict[str, list[str]] = {}
        for t in TASKS:
            if bases[t] and t in found:
                groups.setdefault(bases[t][0], []).append(t.removesuffix("-v2-10k"))
        if len(groups) > 1:
            against = " / ".join(f"{arm} ({', '.join(tasks)})" for arm, tasks in groups.items())
        else:
            against = next(iter(groups), base[0] if base else "")
        lines.append(f"| {name} | {overrides} | {against} | " + " | ".join(cells) + " |")

    row("paper defaults (grid TELS)", "(none)", default, base=None)
    for name, (overrides, found, cpus) in variants.items():
        base, per_task = _bases(name, overrides, cpus, variants, default)
        row(name, f"`{overrides}`", found, base, per_task)
    for method in ABLATIONS:
        row(f"Table 3 ablation {method}", f"`tsidm.ablation={method.removeprefix('tels_')}`", _grid_arm(method))
    row("BC (grid)", "", bc)
    return "\n".join(lines) + (
        "\n\nCells: score per seed (seeds 0, 1, ... unless marked sK) → mean paired change against the arm"
        " named in 'against'.\n"
        f"Means per task ({', '.join(TASKS)}): paper defaults {_means(default)}; "
        f"re-encode arm (re-encoding, beta = 1) {_means(reencode)}; "
        f"beta0.01 arm (re-encoding, beta = 0.01) {_means(beta_arm)}; "
        f"the preset on the Intel Xeon machine {_means(avx512_arm)}; BC {_means(bc)}.\n")


def main() -> None:
    argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0]).parse_args()
    print(render())


if __name__ == "__main__":
    main()
