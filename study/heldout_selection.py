"""Is TELS's late decline the guide overfitting, and can held-out transitions pick the policy without an environment?

    python -m study.heldout_selection --task hopper-medium-v2-10k --seed 0

Hypothesis: on hopper-medium the score peaks at 4k-8k policy steps and then falls, while the
guide's training state loss keeps falling (``benchmarks/results/long20k``), because the guide
fits the trained transitions at the cost of the states it never saw. If so, the actor's action
error on transitions held out from training rises as the score falls, and the policy with the
lowest held-out error scores near the best one, which is an offline stopping rule. If the
held-out error keeps falling while the score falls, the decline is not overfitting in this sense.

The run is the recipe's default (the task's domain preset) at the 20k budget of
``run_grid --steps 20000 --tsidm-steps 3000``, trained on a whole-trajectory subset of
``--size`` transitions (``dataset.size``, the recipe's own draw); the other trajectories of the
file are held out. At every evaluation (each 2k steps, ten deterministic episodes as one batch)
it records the score and, on the trained and on the held-out transitions:

* ``actor_action_mse``, the actor's Eq. (11) action error;
* ``guide_error_ratio``, the guide's error in predicting the next latent over the latent step
  (1: no better than "stay put");
* ``guide_step_ratio`` and ``guide_step_cosine``

(all from :func:`~torchrl_tels.diagnostics.action_chain_statistics`).

Writes ``study/results/heldout_selection/<task>-seed<k>.json`` (temp file +
rename; skipped if it exists unless ``--force``); ``--table`` prints the table RESULTS.md holds and draws
``heldout_selection.png`` beside the JSONs.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch
import tqdm
from hydra import compose, initialize_config_dir

from benchmarks.harness import (invocation, machine_description, REPO, repo_relative, save_figure, skip_existing,
                                write_result)
from study.action_error import training_rows
from torchrl_tels.data import load_dataset
from torchrl_tels.diagnostics import action_chain_statistics
from torchrl_tels.envs import make_eval_envs
from torchrl_tels.record import second_half_mean
from torchrl_tels.trainer import evaluate, make_data, make_stage1, make_stage2, RunState

RESULTS = REPO / "study" / "results" / "heldout_selection"


def run(task: str, seed: int, size: int, steps: int, interval: int, tsidm_steps: int) -> dict:
    overrides = [f"dataset.name={task}", f"dataset.size={size}", f"seed={seed}", f"tsidm.steps={tsidm_steps}",
                 f"policy.steps={steps}", "policy.batch_size=256", f"eval.interval={interval}", "eval.episodes=10",
                 "eval.batched=true", "logger.wandb_mode=disabled"]
    with initialize_config_dir(str(REPO / "recipes" / "config"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    torch.manual_seed(seed)
    data, env_task = make_data(cfg)
    every = load_dataset(task)
    heldout = every[~training_rows(every, {"size": size, "subset": cfg.dataset.subset}, seed)]
    with tempfile.TemporaryDirectory() as folder:
        tsidm = make_stage1(cfg, data, RunState(config={}), Path(folder))
    env = make_eval_envs(env_task.env_id, cfg.eval.episodes)
    stage2 = make_stage2(cfg, data, tsidm, env.action_spec_unbatched)
    evaluations = []
    for step in tqdm.trange(steps, desc="stage 2", file=sys.stdout, mininterval=5.0):
        _, guide_losses = stage2.update(stage2.buffer.sample(), step)
        if (step + 1) % interval == 0:
            reading = evaluate(cfg, stage2.actor, env, env_task, step + 1, stage2.latent_stats)
            evaluations.append({"step": step + 1, "score": reading["score"], "scores": reading["scores"],
                                "guide_state_loss": guide_losses["loss_guide_state"].item(),
                                "trained": action_chain_statistics(stage2.actor, data),
                                "heldout": action_chain_statistics(stage2.actor, heldout)})
            print(f"step {step + 1}: score {reading['score']:.1f}, held-out action MSE "
                  f"{evaluations[-1]['heldout']['actor_action_mse']:.4f}, trained "
                  f"{evaluations[-1]['trained']['actor_action_mse']:.4f}")
    return {"task": task, "seed": seed, "size": size, "trained_rows": len(data), "heldout_rows": len(heldout),
            "recipe_overrides": overrides, "evaluations": evaluations}


def spearman(x: list[float], y: list[float]) -> float:
    """Rank correlation (no ties expected among float readings)."""
    rx, ry = (torch.tensor(v).argsort().argsort().double() for v in (x, y))
    return torch.corrcoef(torch.stack([rx, ry]))[0, 1].item()


def selection_row(result: dict) -> str:
    evaluations = result["evaluations"]
    scores = [e["score"] for e in evaluations]
    heldout = [e["heldout"]["actor_action_mse"] for e in evaluations]
    chosen = min(range(len(evaluations)), key=heldout.__getitem__)
    best = max(range(len(evaluations)), key=scores.__getitem__)
    first, last = evaluations[0], evaluations[-1]
    return (f"| {result['task']} | {result['seed']} | {result['trained_rows']} / {result['heldout_rows']} "
            f"| {scores[best]:.1f} at {evaluations[best]['step']} | {scores[-1]:.1f} "
            f"| {second_half_mean(evaluations):.1f} "
            f"| {scores[chosen]:.1f} at {evaluations[chosen]['step']} | {spearman(heldout, scores):+.2f} "
            f"| {first['trained']['actor_action_mse']:.4f} → {last['trained']['actor_action_mse']:.4f} "
            f"| {first['heldout']['actor_action_mse']:.4f} → {last['heldout']['actor_action_mse']:.4f} "
            f"| {first['heldout']['guide_error_ratio']:.2f} → {last['heldout']['guide_error_ratio']:.2f} |")


def results() -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(RESULTS.glob("*.json"))]


def table() -> str:
    rows = [selection_row(result) for result in results()]
    head = ("| task | seed | trained / held-out rows | best score (step) | final score | second-half mean "
            "| score at least held-out action MSE (step) | rank corr. held-out MSE vs score "
            "| trained action MSE first → last | held-out action MSE first → last "
            "| held-out guide error / step first → last |\n|" + "---|" * 11)
    return "\n".join([head, *rows])


def plot() -> Path:
    """Score and held-out action MSE against policy steps, one panel per result."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    readings = results()
    fig, axes = plt.subplots(1, len(readings), figsize=(4.5 * len(readings), 3.4), squeeze=False)
    for ax, result in zip(axes[0], readings):
        steps = [e["step"] / 1000 for e in result["evaluations"]]
        ax.plot(steps, [e["score"] for e in result["evaluations"]], "o-", color="C0")
        ax.set_xlabel("policy steps (k)")
        ax.set_ylabel("D4RL normalized score", color="C0")
        ax.set_title(f"{result['task']} seed {result['seed']}", fontsize=9)
        twin = ax.twinx()
        for split, style in (("heldout", "s-"), ("trained", "^--")):
            twin.plot(steps, [e[split]["actor_action_mse"] for e in result["evaluations"]], style, color="C3",
                      label=f"{split} action MSE")
        twin.set_ylabel("Eq. (11) action MSE", color="C3")
        twin.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, RESULTS / "heldout_selection.png")


def main():
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="hopper-medium-v2-10k")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=7000, help="transitions kept for training (whole trajectories)")
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--eval-interval", type=int, default=2000)
    parser.add_argument("--tsidm-steps", type=int, default=3000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--force", action="store_true", help="rewrite a result that exists")
    parser.add_argument("--table", action="store_true", help="print the table of every result and exit")
    args = parser.parse_args()
    if args.table:
        print(table())
        print(f"wrote {repo_relative(plot())}")
        return
    out = RESULTS / f"{args.task}-seed{args.seed}.json"
    if skip_existing(out, args.force):
        return
    torch.set_num_threads(args.threads)
    start = time.time()
    result = run(args.task, args.seed, args.size, args.steps, args.eval_interval, args.tsidm_steps)
    write_result(out, {**result, "elapsed_s": time.time() - start, "threads": args.threads,
                       "machine": machine_description(), "command": invocation(),
                       "date": time.strftime("%Y-%m-%d")}, force=True)
    print(table())


if __name__ == "__main__":
    main()
