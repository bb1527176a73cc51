"""Representations compared (the paper's Fig. 4 right): IQL on the latents of four encoders.

Each encoder is φ_s of a TS-IDM of the recipe's shape (Table 10 widths, latent size = observation
size), trained for the same number of steps on the same data, then frozen; IQL (``iql_latent`` of
``benchmarks/baselines.py``, its paper's hyperparameters) trains on φ_s(s). Only the encoder's
objective differs:

``tsidm``        Eq. (7) with the preset's β (``torchrl_tels.trainer.fit_tsidm``): T-symmetry;
``ae``           a plain autoencoder, :math:`\\|\\psi_s(\\phi_s(s)) - s\\|^2`;
``vae``          a VAE: φ_s is the posterior mean, a second MLP its log-variance,
                 :math:`\\|\\psi_s(\\mu + \\sigma\\epsilon) - s\\|^2 + \\mathrm{KL}(q\\,\\|\\,\\mathcal N(0, I))`;
                 IQL reads the mean;
``contrastive``  temporal InfoNCE: (φ_s(s), φ_s(s')) of one transition is the positive pair, the
                 batch's other next states the negatives; cosine similarity, temperature 0.1.

Norms are sums over the normalized state's entries, averaged over the batch, as Eq. (7)'s.
If T-symmetry is what helps, the ``tsidm`` row should beat the other three.

The encoders' output scales differ by an order of magnitude (the contrastive objective sees only
directions; the VAE's KL pulls its mean towards 0), and IQL reads the latent unnormalized, so a row can
lose to its scale rather than its content. ``--standardize-latents`` standardizes each dimension of
φ_s(s) over the data before IQL (the TS-IDM's ``latent_standardization`` buffers, fitted after training)
and writes under ``standardized/``; the table shows both protocols.

    python -m benchmarks.representations --encoder ae --task hopper-medium-v2-10k --seed 0
    python -m benchmarks.representations --encoder vae --task hopper-medium-v2-10k --seed 0 --standardize-latents
    python -m benchmarks.representations --table

writes ``benchmarks/results/representations/[standardized/]<encoder>/<task>/seed<k>.json``; ``--table`` writes
``benchmarks/results/representations/REPRESENTATIONS.md`` and ``benchmarks/results/plots/representations.png``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch
from torch import nn

from benchmarks.harness import (invocation, machine_description, recipe_config, REPO, save_figure, skip_existing,
                                write_result)

ENCODERS = ("tsidm", "ae", "vae", "contrastive")
TASKS = ("hopper-medium-v2-10k", "hopper-medium-replay-v2-10k", "walker2d-medium-v2-10k", "halfcheetah-medium-v2-10k")
RESULTS = REPO / "benchmarks" / "results" / "representations"
ENCODER_STEPS, POLICY_STEPS, EVAL_INTERVAL, EPISODES = 3000, 5000, 500, 10
CONTRASTIVE_TEMPERATURE = 0.1


def squared_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    r"""Eq. (3)'s :math:`\|a - b\|^2`, summed over the vector (:func:`~torchrl_tels.modules.squared_norm`), batch mean."""
    from torchrl_tels.modules import squared_norm

    return squared_norm(a - b).mean()


def autoencoder_loss(tsidm, batch, extra) -> torch.Tensor:
    s = tsidm.normalize_state(batch["observation"])
    return squared_error(tsidm.decode_state(tsidm.embed_state(s)), s)


def vae_loss(tsidm, batch, log_variance_net) -> torch.Tensor:
    s = tsidm.normalize_state(batch["observation"])
    mean, log_variance = tsidm.embed_state(s), log_variance_net(s)
    sample = mean + torch.randn_like(mean) * (0.5 * log_variance).exp()
    kl = 0.5 * (mean.pow(2) + log_variance.exp() - 1.0 - log_variance).sum(-1).mean()
    return squared_error(tsidm.decode_state(sample), s) + kl


def contrastive_loss(tsidm, batch, extra) -> torch.Tensor:
    z = nn.functional.normalize(tsidm.encode_state(batch["observation"]), dim=-1)
    z_next = nn.functional.normalize(tsidm.encode_state(batch["next", "observation"]), dim=-1)
    logits = z @ z_next.T / CONTRASTIVE_TEMPERATURE
    return nn.functional.cross_entropy(logits, torch.arange(len(z)))


OBJECTIVES = {"ae": autoencoder_loss, "vae": vae_loss, "contrastive": contrastive_loss}


def train_encoder(encoder: str, data, seed: int, steps: int = ENCODER_STEPS, overrides=()):
    """A TS-IDM whose φ_s was trained ``steps`` steps by ``encoder``'s objective; its losses and latent scale.

    Returns ``(tsidm, losses, latent statistics)``; ``losses`` holds every step's loss (for ``tsidm``,
    the final Eq. (7) value only: :func:`~torchrl_tels.trainer.fit_tsidm` keeps its history)."""
    from torchrl_tels.data import make_offline_replay_buffer
    from torchrl_tels.diagnostics import latent_statistics
    from torchrl_tels.trainer import fit_tsidm, make_tsidm, RunState

    cfg = recipe_config(["device=cpu", f"seed={seed}", f"tsidm.steps={steps}", *overrides])
    torch.manual_seed(seed)
    if encoder == "tsidm":
        with tempfile.TemporaryDirectory() as tmp:
            tsidm, final, _ = fit_tsidm(cfg, data, float(cfg.tsidm.beta), RunState(config={}), Path(tmp))
        losses = [final["final_loss"]]
    else:
        tsidm = make_tsidm(cfg, data)
        extra = None
        parameters = list(tsidm.state_encoder.parameters())
        if encoder in ("ae", "vae"):
            parameters += list(tsidm.state_decoder.parameters())
        if encoder == "vae":
            extra = nn.Sequential(nn.Linear(tsidm.observation_dim, 256), nn.ReLU(),
                                  nn.Linear(256, tsidm.latent_state_dim))
            parameters += list(extra.parameters())
        optim = torch.optim.Adam(parameters, lr=cfg.tsidm.lr)
        buffer = make_offline_replay_buffer(data, cfg.tsidm.batch_size)
        losses = []
        for _ in range(steps):
            loss = OBJECTIVES[encoder](tsidm, buffer.sample(), extra)
            optim.zero_grad()
            loss.backward()
            optim.step()
            losses.append(loss.item())
        tsidm.eval()
    stats = latent_statistics(tsidm, data["observation"], data["next", "observation"])
    return tsidm, losses, stats


def with_standardized_latent(tsidm, observations: torch.Tensor):
    """A copy of ``tsidm`` whose z_s is φ_s(s) standardized per dimension over ``observations``."""
    from torchrl_tels.modules import TSIDM

    copy = TSIDM(**{**tsidm.config(), "latent_standardization": True})
    missing, unexpected = copy.load_state_dict(tsidm.state_dict(), strict=False)
    if unexpected or set(missing) - {"latent_loc", "latent_scale"}:
        raise RuntimeError(f"with_standardized_latent: state dicts differ: {missing}, {unexpected}")
    copy.fit_latent_standardization(observations)
    return copy.eval()


def run_one(encoder: str, task: str, seed: int, force: bool, standardize: bool = False) -> None:
    out = (RESULTS / "standardized" if standardize else RESULTS) / encoder / task / f"seed{seed}.json"
    if skip_existing(out, force):
        return
    from benchmarks.baselines import train_baseline
    from torchrl_tels.data import load_dataset

    torch.set_num_threads(1)
    start = time.time()
    data = load_dataset(task)
    tsidm, losses, stats = train_encoder(encoder, data, seed)
    tail = losses[int(0.9 * len(losses)):]
    final_loss = sum(tail) / len(tail)
    encoder_s = time.time() - start
    if standardize:
        tsidm = with_standardized_latent(tsidm, data["observation"])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "encoder.pt"
        tsidm.save(path)
        result = train_baseline("iql_latent", task, steps=POLICY_STEPS, seed=seed, eval_interval=EVAL_INTERVAL,
                                eval_episodes=EPISODES, eval_last_n=POLICY_STEPS // EVAL_INTERVAL, eval_batched=False,
                                threads=1, device="cpu", tsidm_path=path, progress=False)
    result.pop("tsidm", None)  # a temporary file; the encoder is described below
    result.update({"encoder": encoder, "latent_standardized": standardize, "encoder_steps": ENCODER_STEPS,
                   "encoder_final_loss": final_loss,
                   "encoder_wall_s": encoder_s, "latent": stats, "command": invocation(),
                   "date": time.strftime("%Y-%m-%d"), "machine": machine_description()})
    write_result(out, result, force=True)
    print(f"{encoder} {task} seed {seed}: IQL on the latents {result['final_normalized_score_mean']:.1f}; "
          f"encoder loss {final_loss:.4g}, latent RMS {stats['latent_rms']:.3g}")


def _scores(root: Path) -> dict:
    return {(e, t): [json.loads(p.read_text())["final_normalized_score_mean"]
                     for p in sorted((root / e / t).glob("seed*.json"))] for e in ENCODERS for t in TASKS}


def _score_rows(found: dict) -> list[str]:
    lines = ["| encoder | " + " | ".join(TASKS) + " | mean over sets |", "|---" * (len(TASKS) + 2) + "|"]
    for encoder in ENCODERS:
        cells, means = [], []
        for task in TASKS:
            scores = found[encoder, task]
            if scores:
                means.append(statistics.mean(scores))
                cells.append(f"{means[-1]:.1f} ± {statistics.pstdev(scores):.1f} ({len(scores)})")
            else:
                cells.append("—")
        overall = f"{statistics.mean(means):.1f}" if len(means) == len(TASKS) else "—"
        lines.append(f"| {encoder} | " + " | ".join(cells) + f" | {overall} |")
    return lines


def table() -> None:
    import numpy as np

    found = _scores(RESULTS)
    lines = ["# IQL on four representations of the same data (the paper's Fig. 4 right)", "",
             "Generated by `python -m benchmarks.representations --table` from `benchmarks/results/representations`; "
             "do not edit. D4RL normalized score of IQL (its paper's hyperparameters) on φ_s(s) of a frozen encoder "
             f"of the recipe's TS-IDM shape, trained {ENCODER_STEPS} steps by the objective of its row; IQL trains "
             f"{POLICY_STEPS} steps, and per seed the score is the mean of {POLICY_STEPS // EVAL_INTERVAL} evaluations "
             f"of {EPISODES} episodes. Each cell: mean ± population std over seeds (n). '—': not run.", "",
             *_score_rows(found)]
    standardized = _scores(RESULTS / "standardized")
    if any(standardized.values()):
        lines += ["", "The same, with each dimension of φ_s(s) standardized over the data before IQL "
                  "(`--standardize-latents`; results under `standardized/`), so that no row is read at another "
                  "scale:", "", *_score_rows(standardized)]
    lines += ["", "What each encoder learned: its objective at the end (mean of the last 10 % of steps; for `tsidm`, "
              "Eq. (7)) and the latent scale IQL reads (RMS spread per dimension over the data):", "",
              "| encoder | task | seed | final encoder loss | latent RMS |", "|---|---|---|---|---|"]
    for encoder in ENCODERS:
        for task in TASKS:
            for path in sorted((RESULTS / encoder / task).glob("seed*.json")):
                run = json.loads(path.read_text())
                lines.append(f"| {encoder} | {task} | {run['seed']} | {run['encoder_final_loss']:.4g} | "
                             f"{run['latent']['latent_rms']:.3g} |")
    lines += ["", "![representations](../plots/representations.png)", ""]
    (RESULTS / "REPRESENTATIONS.md").parent.mkdir(parents=True, exist_ok=True)
    from torchrl_tels.training import write_text

    write_text(RESULTS / "REPRESENTATIONS.md", "\n".join(lines))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / len(ENCODERS)
    for i, encoder in enumerate(ENCODERS):
        for j, task in enumerate(TASKS):
            scores = found[encoder, task]
            if scores:
                x = j + (i - (len(ENCODERS) - 1) / 2) * width
                ax.bar(x, np.mean(scores), width, color=f"C{i}")
                ax.scatter([x] * len(scores), scores, color="k", s=6, zorder=3)
    handles = [plt.Rectangle((0, 0), 1, 1, color=f"C{i}") for i in range(len(ENCODERS))]
    ax.legend(handles, ENCODERS, fontsize=8)
    ax.set_xticks(range(len(TASKS)), [t.replace("-v2-10k", "") for t in TASKS], fontsize=8)
    ax.set_ylabel("D4RL normalized score (IQL on the latents)")
    ax.grid(alpha=0.3, axis="y")
    save_figure(fig, REPO / "benchmarks" / "results" / "plots" / "representations.png")
    print(f"wrote {RESULTS / 'REPRESENTATIONS.md'}")


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--encoder", choices=ENCODERS)
    parser.add_argument("--task", choices=TASKS)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--force", action="store_true", help="rewrite the result if it exists")
    parser.add_argument("--standardize-latents", action="store_true",
                        help="standardize each latent dimension over the data before IQL (results under standardized/)")
    parser.add_argument("--table", action="store_true", help="render REPRESENTATIONS.md and the plot from the JSONs")
    args = parser.parse_args()
    if args.table:
        table()
    elif args.encoder and args.task:
        run_one(args.encoder, args.task, args.seed, args.force, standardize=args.standardize_latents)
    else:
        parser.error("give --encoder and --task for a run, or --table")


if __name__ == "__main__":
    main()
