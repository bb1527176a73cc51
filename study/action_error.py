"""Where a trained TELS actor's actions go wrong, measured on its own dataset.

The Eq. (11) actor chains two learned maps: the guide proposes z' = π_g(z), then
ψ_a(h_inv(z, z')) turns the pair into an action. Plain BC beats the actor on the
D4RL-10k files, so this script splits the actor's action error on the dataset's
own transitions into its parts:

* ``oracle``: ψ_a(h_inv(z, φ_s(s'))) with the dataset's true next state, the best
  the guide could do (the TS-IDM's own inverse-dynamics error);
* ``guide``: ψ_a(h_inv(z, π_g(z))), the actor as it acts (Eq. 11);
* ``reencode``: ψ_a(h_inv(z, φ_s(ψ_s(π_g(z))))), choice 7;
* ``no_step``: ψ_a(h_inv(z, z)), an action inferred from no move at all;
* ``mean_action``: the dataset's mean action for every state;
* ``bc``: an MLP fitted to (s, a) by MSE on the same transitions (torchrl MLP, 256x256, 5k Adam steps);

the same errors over the action entries at a bound (exactly ±1) and inside, and the guide's latent error
||π_g(z) - z'||² next to the size of the step
||z' - z||² it has to predict, with the size and direction of the step it proposes
(``torchrl_tels.diagnostics.action_chain_statistics``). All errors are mean squared over action
dimensions; ``acting`` names the prediction the actor acts with (``reencode`` or ``guide``). A run
trained on a ``dataset.size`` subset is also scored on the transitions it never saw (``held_out``),
which separates fit from generalization::

    python -m study.action_error --run-dir runs/full-default-seed0 --name paper_full-hopper-medium-seed0

writes ``study/results/action_error/<name>.json`` (temp file + rename; skipped if it
exists unless ``--force``).
"""
from __future__ import annotations

import argparse
from datetime import datetime, timezone
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.modules import MLP

from benchmarks.harness import invocation, machine_description, REPO, skip_existing, write_result
from torchrl_tels.data import load_dataset, subset_dataset
from torchrl_tels.diagnostics import action_chain_statistics
from torchrl_tels.modules import TSIDM, load_tels_actor
from torchrl_tels.modules.actors import GUIDE_KEY, LATENT_KEY
from torchrl_tels.run_folder import RunFolder


def fit_bc(observation: torch.Tensor, action: torch.Tensor, steps: int, seed: int, apply_to: torch.Tensor) -> torch.Tensor:
    """BC fitted on the run's training transitions, then applied to ``apply_to``: the error the actor's chain has to beat."""
    policy = train_bc(observation, action, steps, seed)  # trained with gradients, applied without
    with torch.no_grad():
        return policy(apply_to)


def train_bc(observation: torch.Tensor, action: torch.Tensor, steps: int, seed: int):
    """A tanh MLP (256, 256) on standardized observations, fitted to ``action`` by MSE for ``steps`` batches of
    256: returns the policy, observations → actions."""
    torch.manual_seed(seed)
    loc, scale = observation.mean(0), observation.std(0).clamp_min(1e-3)
    x = (observation - loc) / scale
    net = MLP(in_features=x.shape[-1], out_features=action.shape[-1], num_cells=[256, 256], activation_class=torch.nn.ReLU)
    optim = torch.optim.Adam(net.parameters(), lr=3e-4)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(0, x.shape[0], (256,), generator=generator)
        loss = (torch.tanh(net(x[idx])) - action[idx]).pow(2).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()
    return lambda observations: torch.tanh(net((observations - loc) / scale))


def training_rows(data: TensorDict, dataset_cfg: dict, seed: int) -> torch.Tensor:
    """The rows the run trained on: all of them, or the recipe's ``dataset.size`` subset (same draw)."""
    if dataset_cfg.get("delete_boxes"):
        # The recipe deletes regions after subsetting; telling those rows apart is not implemented.
        raise SystemExit("error: the run deleted dataset regions (dataset.delete_boxes): its training rows are not known here")
    if not dataset_cfg.get("size"):
        return torch.ones(len(data), dtype=torch.bool)
    tagged = data.clone(False)
    tagged.set("row", torch.arange(len(data)))
    kept = torch.zeros(len(data), dtype=torch.bool)
    kept[subset_dataset(tagged, int(dataset_cfg["size"]), seed=seed, mode=dataset_cfg.get("subset", "trajectories"))["row"]] = True
    return kept


def _masked_mse(prediction: torch.Tensor, action: torch.Tensor, mask: torch.Tensor) -> float | None:
    """Mean squared error over the action entries ``mask`` selects; None where it selects none."""
    return (prediction - action)[mask].pow(2).mean().item() if mask.any() else None


def action_errors(run_dir: Path, bc_steps: int, seed: int) -> dict:
    folder = RunFolder(run_dir)
    config = folder.read_config()
    data = load_dataset(config["dataset"]["name"])
    train = training_rows(data, config["dataset"], config["seed"])
    observation, next_observation, action = data["observation"], data["next", "observation"], data["action"]
    tsidm = TSIDM.load(folder.tsidm_path).eval()
    actor = load_tels_actor(folder.policy_path, tsidm)  # no action spec: clipped below, as the env's [-1, 1]
    with torch.no_grad():
        out = actor(TensorDict({"observation": observation}, batch_size=observation.shape[:1]))
        z, proposal = out[LATENT_KEY], out[GUIDE_KEY]
        z_next = tsidm.encode_state(next_observation)
        reencoded = tsidm.embed_state(tsidm.decode_state(proposal))

        def act(z_prime):
            return tsidm.decode_action(tsidm.infer_latent_action(z, z_prime)).clamp(-1, 1)

        predictions = {
            "oracle": act(z_next),
            "guide": act(proposal),
            "reencode": act(reencoded),
            "no_step": act(z),
            "mean_action": action[train].mean(0).expand_as(action),
        }
    predictions["bc"] = fit_bc(observation[train], action[train], bc_steps, seed, apply_to=observation)
    at_bound = action.abs() == 1
    splits = {"train": train} if train.all() else {"train": train, "held_out": ~train}
    record = {"dataset": config["dataset"]["name"], "transitions": {k: int(m.sum()) for k, m in splits.items()},
              "acting": "reencode" if config["guide"].get("reencode_proposal") else "guide"}
    for split, rows in splits.items():
        chain_statistics = action_chain_statistics(actor, data[rows])
        step = (z_next[rows] - z[rows]).pow(2).sum(-1).mean()
        guide_error = (proposal[rows] - z_next[rows]).pow(2).sum(-1).mean()
        record[split] = {
            "action_mse": {name: (pred[rows] - action[rows]).pow(2).mean().item() for name, pred in predictions.items()},
            # Where the data's action sits at a bound (|a| = 1) the plant may not show it in s' (a joint at its
            # stop moves the same under any push past it), so inverse dynamics cannot recover it and BC can.
            "at_bound_share": at_bound[rows].float().mean().item(),
            "action_mse_at_bound": {name: _masked_mse(pred[rows], action[rows], at_bound[rows])
                                    for name, pred in predictions.items()},
            "action_mse_inside": {name: _masked_mse(pred[rows], action[rows], ~at_bound[rows])
                                  for name, pred in predictions.items()},
            "latent_step_sq": step.item(),
            "guide_latent_error_sq": guide_error.item(),
            "guide_error_over_step": (guide_error / step).item(),
            "guide_step_ratio": chain_statistics["guide_step_ratio"],
            "guide_step_cosine": chain_statistics["guide_step_cosine"],
        }
    return record


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, required=True, help="a finished recipe run: config.yaml, tsidm.pt, policy.pt")
    parser.add_argument("--name", required=True, help="results land in results/action_error/<name>.json")
    parser.add_argument("--bc-steps", type=int, default=5000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--force", action="store_true", help="rewrite the result if it exists")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = REPO / "study" / "results" / "action_error" / f"{args.name}.json"
    if skip_existing(out, args.force):
        return
    for required in RunFolder(args.run_dir).missing((RunFolder.CONFIG, RunFolder.TSIDM, RunFolder.POLICY))[:1]:
        raise SystemExit(f"error: {args.run_dir / required} is missing: pass a finished run folder")
    record = action_errors(args.run_dir, args.bc_steps, args.seed)
    record.update(run_dir=args.run_dir, command=invocation(),
                  date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                  machine={**machine_description(), "threads": args.threads})
    for split in ("train", "held_out"):
        if split not in record:
            continue
        r = record[split]
        print(f"{split} ({record['transitions'][split]} transitions): action MSE "
              + ", ".join(f"{name} {value:.4f}" for name, value in r["action_mse"].items()))
        print(f"{split}: guide latent error / latent step = {r['guide_latent_error_sq']:.4f} / "
              f"{r['latent_step_sq']:.4f} = {r['guide_error_over_step']:.3f}")
    write_result(out, record, args.force)


if __name__ == "__main__":
    main()
