"""One run of the reproduction study: the TELS recipe on one task and seed with a named set of overrides.

    python -m study.run_choice --name alpha0.1 --task hopper-medium-v2-10k --seed 0 \
        --budget budget=study eval.episodes=10 --override guide.alpha=0.1

writes study/results/<name>/<task>/seed<k>.json (the run's results.json plus
the command, the guide options the config chose and the machine), and skips the run if that file
exists unless ``--force`` (which rewrites it from the run folder under ``runs/reproduction/``,
resumed rather than retrained). The baseline of a comparison is the same budget with no
--override (the recipe's defaults, name it "default"). The ``domain=mujoco`` departures from the
paper are README's deviation table; ``--override domain=paper`` gives the paper-literal arm.
Runs made before the config had groups recorded their budget as ``tsidm.steps=3000
optim.steps=5000 eval.interval=500 eval.episodes=10``, which ``budget=study`` now sets.
"""
from __future__ import annotations

import argparse
import time

from omegaconf import OmegaConf

from benchmarks.harness import (code_version, command_line, machine_description, REPO, run_recipe, skip_existing,
                                write_result)
from torchrl_tels.run_folder import RunFolder

RESULTS = REPO / "study" / "results"
#: What the recorded arms of a budget ran with beyond the budget group itself: at the study budget,
#: one evaluation episode at a time (the recipe now batches them by default).
PROTOCOL = {"budget=study": ["eval.batched=false"]}


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--name", required=True, help="what this variant tests, e.g. alpha0.1")
    parser.add_argument("--task", required=True)
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--budget", nargs="*", default=[], help="hydra overrides shared by a comparison")
    parser.add_argument("--override", nargs="*", default=[], help="hydra overrides of this variant")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--force", action="store_true", help="rewrite the result if it exists")
    args = parser.parse_args()

    out = RESULTS / args.name / args.task / f"seed{args.seed}.json"
    if skip_existing(out, args.force):
        return
    run_dir = REPO / "runs" / "reproduction" / args.name / args.task / f"seed{args.seed}"
    start = time.time()
    protocol = [pin for budget in args.budget for pin in PROTOCOL.get(budget, [])]
    cmd = run_recipe([f"dataset.name={args.task}", f"seed={args.seed}", f"run_dir={run_dir}", "resume=true",
                      "logger.wandb_mode=disabled", *args.budget, *protocol, *args.override], args.threads)
    folder = RunFolder(run_dir)
    results = folder.read_results()
    # The preset's choices are not in --override, so a later change of the preset would otherwise
    # leave no trace in the JSON (results.json already records the beta used).
    config = OmegaConf.load(folder.config_path)
    results.update(alpha=float(config.guide.alpha), reencode_proposal=bool(config.guide.reencode_proposal))
    results.update(variant=args.name, overrides=args.override, budget=args.budget, command=command_line(cmd),
                   date=time.strftime("%Y-%m-%d"), elapsed_s=time.time() - start, machine=machine_description(),
                   code=code_version())
    write_result(out, results, args.force)
    print(f"{args.name} {args.task} seed {args.seed}: {results['final_normalized_score_mean']:.1f}")


if __name__ == "__main__":
    main()
