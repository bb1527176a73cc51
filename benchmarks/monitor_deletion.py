"""Does the T-symmetry monitor flag the regions a maze dataset never covered? (the deletion test's data, AUROC)

The third shift of the monitor benchmark (``benchmarks.monitor_auroc`` measures the other two): the
transitions inside the deleted regions of the OOD deletion test (``benchmarks.ood_deletion``, paper
Fig. 3) are removed from a maze dataset; a TS-IDM (the recipe's ``domain=maze`` configuration,
``--tsidm-steps`` steps) and the two simple detectors of ``monitor_auroc`` (a one-step dynamics model's
residual, the distance to the nearest training state) are trained on 80 % of the remaining trajectories.
Each detector then scores ``--points`` held-out remaining transitions (in distribution) and as many
transitions from inside the regions (never seen), and the AUROC of telling them apart is reported.

    python -m benchmarks.monitor_deletion --setup pointmaze-medium --threads 1

Writes ``benchmarks/results/monitor/deletion_<setup>_seed<k>.json`` (skipped when it exists unless
``--force``).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from benchmarks.harness import invocation, machine_description, repo_relative, skip_existing, write_result
from benchmarks.monitor_auroc import auroc, DEFAULT_RESULTS, DETECTORS, fit_detectors, split_trajectories, subsample
from benchmarks.ood_deletion import ensure_dataset, SETUPS
from torchrl_tels.data import delete_regions, load_dataset, points_in_boxes


def run(args) -> dict:
    torch.set_num_threads(args.threads)
    setup, boxes = SETUPS[args.setup]()
    ensure_dataset(setup)
    full = load_dataset(setup.dataset)
    inside = full[points_in_boxes(full, boxes)]
    kept = delete_regions(full, boxes, 1.0, seed=args.seed)
    train, held = split_trajectories(kept, 0.8, args.seed)
    print(f"{args.setup}: {len(inside)} transitions in the regions, {len(train)} training, {len(held)} held out",
          flush=True)
    detectors = fit_detectors(train, ["domain=maze"], seed=args.seed, tsidm_steps=args.tsidm_steps,
                              model_steps=args.model_steps, quantile=args.quantile)
    monitor, threshold = detectors.monitor, detectors.threshold
    sets = {"held_out": subsample(held, args.points, args.seed),
            "deleted_regions": subsample(inside, args.points, args.seed)}
    scores = {name: detectors.scores(td) for name, td in sets.items()}
    return {
        "command": invocation(),
        "setup": args.setup,
        "dataset": setup.dataset,
        "boxes": [list(map(float, box)) for box in boxes],
        "seed": args.seed,
        "tsidm_steps": args.tsidm_steps,
        "tsidm_beta": detectors.beta,
        "tsidm_final_loss": detectors.tsidm_final_loss,
        "dynamics_model_steps": args.model_steps,
        "sizes": {name: len(td) for name, td in sets.items()},
        "monitor": {"score": monitor.score_key, "quantile": args.quantile, "threshold": threshold,
                    "flag_rate": {name: float((scores[name][monitor.score_key] > threshold).mean()) for name in sets}},
        "auroc": {"deleted_regions": {d: auroc(scores["held_out"][d], scores["deleted_regions"][d]) for d in DETECTORS}},
        "wall_s": detectors.wall_s,
        "threads": args.threads,
        "machine": machine_description(),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.split("\n\n")[0])
    parser.add_argument("--setup", choices=sorted(SETUPS), default="pointmaze-medium")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tsidm-steps", type=int, default=3000)
    parser.add_argument("--model-steps", type=int, default=3000)
    parser.add_argument("--points", type=int, default=2000, help="transitions scored per set")
    parser.add_argument("--quantile", type=float, default=0.99)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=DEFAULT_RESULTS)
    parser.add_argument("--force", action="store_true")
    args = parser.parse_args(argv)
    path = args.out / f"deletion_{args.setup}_seed{args.seed}.json"
    if skip_existing(path, args.force):
        return
    result = run(args)
    write_result(path, result, force=True)
    print("AUROC, deleted regions vs held-out: " +
          ", ".join(f"{d} {v:.3f}" for d, v in result["auroc"]["deleted_regions"].items()))
    print(f"monitor flag rate at q={args.quantile}: " +
          ", ".join(f"{k} {v:.1%}" for k, v in result["monitor"]["flag_rate"].items()))
    print(f"wrote {repo_relative(path)}")


if __name__ == "__main__":
    main()
