"""bf16 against fp32: the default at the study budget, the same seeds, the final scores paired.

    python -m study.precision

The bf16 arm (``bf16_preset``: ``precision=bf16`` on top of the ``mujoco`` preset, run on a CPU that
multiplies bf16 natively) against the fp32 runs of the same settings and seeds (``alpha1``). bf16 changes
every rounding, so a pair differs as two CPUs' runs of one seed do; the scale of that is the same settings
and seeds in fp32 on two kinds of CPU (``alpha1_epyc`` against ``alpha1``). bf16 shows no loss of score
beyond seed noise when its mean paired change has a 95 % interval that reaches 0 or lies above it.
"""
from __future__ import annotations

import argparse

from torchrl_tels.stats import t_interval
from study.summary import HERE, seed_results, TASKS

BF16_ARM, FP32_ARM, OTHER_CPU_ARM = "bf16_preset", "alpha1", "alpha1_epyc"


def final_scores(arm: str) -> dict[str, dict[int, float]]:
    """{task: {seed: final score}} of an arm's runs."""
    return {task: {seed: r["final_normalized_score_mean"] for seed, r in runs.items()}
            for task in TASKS if (runs := seed_results(HERE / "results" / arm / task, lambda r: True))}


def paired(arm: str, against: str) -> dict[str, dict[int, float]]:
    """{task: {seed: score of ``arm`` minus score of ``against``}} over the seeds both ran."""
    mine, theirs = final_scores(arm), final_scores(against)
    return {task: {s: mine[task][s] - theirs[task][s] for s in sorted(mine[task]) if s in theirs.get(task, {})}
            for task in mine if task in theirs}


def _interval(values: list[float]) -> str:
    if not values:
        return "—"
    mean, low, high = t_interval(values)
    return f"{mean:+.1f}" + (f" [{low:+.1f}, {high:+.1f}]" if len(values) > 1 else "") + f" (n={len(values)})"


def report() -> str:
    bf16, fp32 = final_scores(BF16_ARM), final_scores(FP32_ARM)
    changes, cpu_changes = paired(BF16_ARM, FP32_ARM), paired(OTHER_CPU_ARM, FP32_ARM)
    lines = ["| task | fp32 (`alpha1`) | bf16 (`bf16_preset`) | bf16 − fp32, mean [95 % t-interval] | "
             "other CPU − this one, fp32 |", "|---|---|---|---|---|"]
    for task in TASKS:
        scores = lambda arm: ", ".join(f"{arm[task][s]:.1f}" for s in sorted(arm.get(task, {}))) or "—"
        lines.append(f"| {task} | {scores(fp32)} | {scores(bf16)} | {_interval(list(changes.get(task, {}).values()))} "
                     f"| {_interval(list(cpu_changes.get(task, {}).values()))} |")
    pooled = [change for by_seed in changes.values() for change in by_seed.values()]
    pooled_cpu = [change for by_seed in cpu_changes.values() for change in by_seed.values()]
    lines.append(f"| all pairs | | | {_interval(pooled)} | {_interval(pooled_cpu)} |")
    if len(pooled) > 1:
        mean, low, high = t_interval(pooled)
        verdict = ("no loss of score beyond seed noise: the interval of the mean change reaches 0 or lies above it"
                   if high >= 0 else "a loss of score: the interval of the mean change lies below 0")
        lines += ["", f"Over {len(pooled)} pairs, bf16 shows {verdict}."]
    return "\n".join(lines)


def main() -> None:
    argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0]).parse_args()
    print(report())


if __name__ == "__main__":
    main()
