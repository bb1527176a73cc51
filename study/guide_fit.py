"""Does the guide generalize to states it never saw, and does a residual parametrization help?

Takes a finished TELS run trained on a ``dataset.size`` subset (e.g. ``run_choice --name
holdout7500 ... --override dataset.size=7500``) and, with its TS-IDM frozen, fits fresh guides
(Table 11's 1024x1024 ReLU MLP, Adam 1e-4, batch 256) on the training rows to Eq. (9)'s state
term alone, η‖ψ_s(π_g(z_s)) − s'‖² with η = 1 (at α = 0.01 the value term is inert, see LOG.md),
in two parametrizations:

* ``absolute``: π_g(z) = MLP(z), as the recipe builds it;
* ``residual``: π_g(z) = z + MLP(z), so the network learns only the latent step.

It prints, on the training rows and on the held-out rows, the guide's latent error next to the
latent step, its decoded state error and the Eq. (11) action error ψ_a(h_inv(z, π_g(z)))::

    python -m study.guide_fit --run-dir runs/reproduction/holdout7500/hopper-medium-v2-10k/seed0

writes ``study/results/guide_fit/<task>-seed<k>.json`` (temp file + rename; skipped
if it exists unless ``--force``).
"""
from __future__ import annotations

import argparse
from datetime import datetime, timezone
from pathlib import Path

import torch
import yaml
from torchrl.modules import MLP

from benchmarks.harness import invocation, machine_description, REPO, skip_existing, write_result
from study.action_error import training_rows
from torchrl_tels.data import load_dataset
from torchrl_tels.modules import TSIDM


def fit_guide(tsidm: TSIDM, z: torch.Tensor, next_state: torch.Tensor, rows: torch.Tensor,
              residual: bool, steps: int, seed: int):
    torch.manual_seed(seed)
    net = MLP(in_features=z.shape[-1], out_features=z.shape[-1], num_cells=[1024, 1024], activation_class=torch.nn.ReLU)
    optim = torch.optim.Adam(net.parameters(), lr=1e-4)
    generator = torch.Generator().manual_seed(seed)

    def guide(latent):
        return latent + net(latent) if residual else net(latent)

    for _ in range(steps):
        batch = rows[torch.randint(0, len(rows), (256,), generator=generator)]
        # Eq. (9)'s state term, summed over state dims as the recipe's default reduction.
        loss = (tsidm.decode_state(guide(z[batch])) - next_state[batch]).pow(2).sum(-1).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()
    return guide


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--force", action="store_true", help="rewrite the result if it exists")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    config = yaml.safe_load((args.run_dir / "config.yaml").read_text())
    task = config["dataset"]["name"]
    out = REPO / "study" / "results" / "guide_fit" / f"{task}-seed{config['seed']}.json"
    if skip_existing(out, args.force):
        return
    if not config["dataset"].get("size"):
        raise SystemExit(f"error: {args.run_dir} trained on the whole dataset: there are no held-out rows to score")
    data = load_dataset(config["dataset"]["name"])
    train = training_rows(data, config["dataset"], config["seed"])
    tsidm = TSIDM.load(args.run_dir / "tsidm.pt").eval().requires_grad_(False)
    action = data["action"]
    with torch.no_grad():
        z = tsidm.encode_state(data["observation"])
        z_next = tsidm.encode_state(data["next", "observation"])
        next_state = tsidm.normalize_state(data["next", "observation"])
    record = {"run_dir": args.run_dir, "dataset": config["dataset"]["name"], "steps": args.steps,
              "transitions": {"train": int(train.sum()), "held_out": int((~train).sum())}, "variants": {},
              "command": invocation(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "machine": {**machine_description(), "threads": args.threads}}
    for name in ("absolute", "residual"):
        guide = fit_guide(tsidm, z, next_state, train.nonzero().squeeze(-1), name == "residual", args.steps, args.seed)
        with torch.no_grad():
            proposal = guide(z)
            predicted_action = tsidm.decode_action(tsidm.infer_latent_action(z, proposal)).clamp(-1, 1)
        record["variants"][name] = {}
        for split, rows in (("train", train), ("held_out", ~train)):
            entry = {
                "latent_error_sq": (proposal[rows] - z_next[rows]).pow(2).sum(-1).mean().item(),
                "latent_step_sq": (z_next[rows] - z[rows]).pow(2).sum(-1).mean().item(),
                "state_error_sq": (tsidm.decode_state(proposal[rows]) - next_state[rows]).pow(2).sum(-1).mean().item(),
                "action_mse": (predicted_action[rows] - action[rows]).pow(2).mean().item(),
            }
            record["variants"][name][split] = entry
            print(f"{name:8s} {split:8s} " + ", ".join(f"{k} {v:.4f}" for k, v in entry.items()), flush=True)
    write_result(out, record, args.force)


if __name__ == "__main__":
    main()
