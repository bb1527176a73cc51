"""Pictures of the TS-IDM's latent space (the paper's Fig. 12): t-SNE of z_s on a dataset, coloured by
return-to-go and by time in the episode, one row per TS-IDM variant.

Variants, each stage 1 of the recipe at the same budget and seed: ``paper`` (``domain=paper``: Eq. 7 as
written, beta = 1), ``preset`` (the default ``mujoco`` domain, beta = 0.01) and ``ae`` (``tsidm.ablation=ae``:
the inverse-dynamics autoencoder alone). Each is trained once into
``runs/latent_pictures/<dataset>/<variant>_<steps>steps_seed<k>/`` (the recipe with a one-step stage 2) and reused after.
``--points`` states are drawn from the dataset; t-SNE is scikit-learn's (``pip install scikit-learn``),
perplexity 30, PCA start, seeded. Writes ``benchmarks/results/plots/latents_<dataset>.png`` and prints each
variant's latent RMS spread and step, the scale Eq. (7)'s symmetry shrinks.

    python -m benchmarks.latent_pictures --dataset hopper-medium-v2-10k --threads 1
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from benchmarks.harness import REPO, repo_relative, run_recipe, save_figure
from torchrl_tels.run_folder import RunFolder

VARIANTS = {"paper": ["domain=paper"], "preset": [], "ae": ["tsidm.ablation=ae"]}


def train_tsidm(dataset: str, variant: str, steps: int, seed: int, threads: int) -> Path:
    run_dir = REPO / "runs" / "latent_pictures" / dataset / f"{variant}_{steps}steps_seed{seed}"
    if not RunFolder(run_dir).tsidm_path.exists():
        run_recipe([f"dataset.name={dataset}", f"seed={seed}", f"run_dir={run_dir}", "resume=true",
                    f"tsidm.steps={steps}", "policy.steps=1", "eval.interval=1", "eval.episodes=1",
                    "eval.max_steps=1", "logger.wandb_mode=disabled", *VARIANTS[variant]], threads, quiet=True)
    return RunFolder(run_dir).tsidm_path


def episode_features(data) -> tuple[torch.Tensor, torch.Tensor]:
    """Undiscounted return-to-go and step index of every transition, within its episode."""
    episode, reward = data["episode"], data["next", "reward"].reshape(-1)
    rtg, time = torch.empty_like(reward), torch.empty_like(reward)
    for ep in episode.unique():
        idx = (episode == ep).nonzero().squeeze(-1)
        rtg[idx] = reward[idx].flip(0).cumsum(0).flip(0)
        time[idx] = torch.arange(len(idx), dtype=reward.dtype)
    return rtg, time


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="hopper-medium-v2-10k")
    parser.add_argument("--steps", type=int, default=3000, help="TS-IDM steps per variant (the study's budget)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--points", type=int, default=2000)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    try:
        from sklearn.manifold import TSNE
    except ImportError:
        parser.error("t-SNE needs scikit-learn: pip install scikit-learn")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_tels.data import load_dataset
    from torchrl_tels.diagnostics import latent_statistics
    from torchrl_tels.modules import TSIDM

    data = load_dataset(args.dataset)
    rtg, time = episode_features(data)
    rows = torch.randperm(len(data), generator=torch.Generator().manual_seed(args.seed))[: args.points]
    fig, axes = plt.subplots(len(VARIANTS), 2, figsize=(9, 3.6 * len(VARIANTS)), squeeze=False)
    for row, variant in enumerate(VARIANTS):
        path = train_tsidm(args.dataset, variant, args.steps, args.seed, args.threads)
        tsidm = TSIDM.load(path, observation_dim=data["observation"].shape[-1], action_dim=data["action"].shape[-1])
        with torch.no_grad():
            stats = latent_statistics(tsidm, data["observation"], data["next", "observation"])
            latent = tsidm.encode_state(data["observation"][rows])
        embedded = TSNE(n_components=2, perplexity=30, init="pca", random_state=args.seed).fit_transform(
            latent.numpy())
        print(f"{variant}: latent RMS spread {stats['latent_rms']:.3f}, RMS step {stats['latent_step_rms']:.3f}")
        for col, (values, name) in enumerate(((rtg, "return-to-go"), (time, "time in episode"))):
            ax = axes[row, col]
            points = ax.scatter(embedded[:, 0], embedded[:, 1], c=values[rows].numpy(), s=3, cmap="viridis")
            fig.colorbar(points, ax=ax, label=name)
            ax.set_title(f"{variant} (latent RMS {stats['latent_rms']:.2f}): {name}", fontsize=9)
            ax.set_xticks([]), ax.set_yticks([])
    fig.suptitle(f"t-SNE of the TS-IDM latent z_s, {args.dataset}, {args.steps} TS-IDM steps, seed {args.seed}")
    fig.tight_layout()
    out = save_figure(fig, REPO / "benchmarks" / "results" / "plots" / f"latents_{args.dataset}.png")
    print(f"wrote {repo_relative(out)}")


if __name__ == "__main__":
    main()
