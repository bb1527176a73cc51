"""Does the latent space shrink as stage 1 trains longer? Eq. (7) as written against the two scale fixes.

    python -m study.latent_shrink --steps 9000 --seed 0

trains stage 1 alone (the recipe's TS-IDM and Eq. (7), ``torchrl_tels.trainer.fit_tsidm``) on
hopper-medium-v2 10k with beta = 1 for each ``tsidm.latent_scale`` (``free``: Eq. (7) as written;
``standardized``; ``relative``) and records, every 250 steps, the batch's latent RMS spread and RMS
latent step and the unweighted ℓ_dyn and ℓ_Tsym. Under the free latent, Eq. (7) lowers ℓ_dyn and
ℓ_Tsym by shrinking the latents (they scale as c²), so the latent step falls as training goes on;
under a fix it has no reason to. Writes ``results/latent_shrink/<option>/seed<k>.json``; the
table in RESULTS.md compares the step at 3k steps with the step at the end.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from benchmarks.harness import machine_description, REPO, skip_existing, write_result
from torchrl_tels.data import load_dataset
from torchrl_tels.trainer import fit_tsidm, RunState

OPTIONS = ("free", "standardized", "relative")
RESULTS = REPO / "study" / "results" / "latent_shrink"


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=9000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--options", nargs="+", default=list(OPTIONS), choices=OPTIONS)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--force", action="store_true", help="rewrite a result that exists")
    parser.add_argument("--tsidm-dir", type=Path, default=None,
                        help="also save each trained TS-IDM as DIR/<option>/seed<k>/tsidm.pt, for a stage 2 run "
                             "from it (tsidm.checkpoint=...)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    data = load_dataset("hopper-medium-v2-10k")
    for option in args.options:
        out = RESULTS / option / f"seed{args.seed}.json"
        if skip_existing(out, args.force):
            if args.tsidm_dir is not None:
                print(f"{option}: no TS-IDM saved to {args.tsidm_dir}, since the run was skipped (--force reruns it)")
            continue
        overrides = ["domain=paper", f"tsidm.latent_scale={option}", f"tsidm.steps={args.steps}",
                     "logger.log_interval=250", f"checkpoint.interval={args.steps + 1}", f"seed={args.seed}"]
        with initialize_config_dir(str(REPO / "recipes" / "config"), version_base="1.3"):
            cfg = compose("config", overrides=overrides)
        torch.manual_seed(args.seed)
        start = time.time()
        with tempfile.TemporaryDirectory() as folder:
            tsidm, final, history = fit_tsidm(cfg, data, 1.0, RunState(config={}), Path(folder))
        if args.tsidm_dir is not None:
            tsidm_folder = args.tsidm_dir / option / f"seed{args.seed}"
            tsidm_folder.mkdir(parents=True, exist_ok=True)
            tsidm.save(tsidm_folder / "tsidm.pt",
                       metadata={"dataset": "hopper-medium-v2-10k", "latent_scale": option, "beta": 1.0,
                                 "steps": args.steps, "seed": args.seed})
        write_result(out, {"option": option, "seed": args.seed, "steps": args.steps, "history": history,
                           "final": final, "elapsed_s": time.time() - start, "machine": machine_description(),
                           "command": f"python -m {__spec__.name} --steps {args.steps} --seed {args.seed} "
                                      f"--options {option}", "date": time.strftime("%Y-%m-%d")}, force=True)
        step = dict(history["latent_step_rms"])
        print(f"{option}: latent step RMS {step.get(3000, float('nan')):.3f} at 3k, {step[args.steps]:.3f} at "
              f"{args.steps}; latent RMS {dict(history['latent_rms'])[args.steps]:.3f}")


if __name__ == "__main__":
    main()
