"""How well the T-symmetry consistency monitor tells shifted transitions from in-distribution ones (AUROC).

A TS-IDM is trained (the recipe's configuration and helpers, ``--tsidm-steps`` steps) on 80 % of a
dataset's trajectories; the held-out 20 % are the in-distribution transitions. Each shifted set is
scored by the monitor (``torchrl_tels.envs.TSymConsistencyMonitor``: its three scores, the first being
its ``ood_score``) and by two simple detectors trained on the same 80 %:

* ``dynamics_model``: the residual ||f(s, a) - (s' - s)||^2 of a one-step MLP model in normalized
  state space;
* ``nearest_state``: the distance from s' to the nearest training state (normalized).

The shifted sets, all built from held-out states:

* ``random_actions``: uniform random actions replayed in Hopper-v4 from the data's states (another
  behaviour);
* ``other_dataset``: transitions of another shared dataset of the same env (``--other``, default
  hopper-medium-replay-v2-10k), when it is present;
* ``mass_x1.3``, ``mass_x0.7``, ``friction_x1.3``, ``friction_x0.7``: the data's own actions replayed
  from the data's states in a changed plant (every body mass, or the sliding friction of every geom,
  scaled through ``env.unwrapped.model``).

Every set is compared with the held-out data; the changed plants also with ``nominal_replay``, the
same states and actions replayed in the unchanged plant, so that what the simulator does not
reproduce of the data is not counted as detection. ``nominal_replay`` against the held-out data is
that control itself (0.5 when the replay is exact). A changed plant acts for one control step (four
MuJoCo steps) per transition, so its effect on s' is of the order of the nominal replay's own mismatch
with the data: a hard test for any one-step detector. AUROC is the Mann-Whitney statistic:
P(shifted score > in-distribution score) + P(tie) / 2. The paper's third OOD test (deleted maze
regions, Fig. 3) is not part of this benchmark. Run from the repository root::

    python -m benchmarks.monitor_auroc --threads 2
    python -m benchmarks.monitor_auroc --tsidm-steps 20 --model-steps 20 --replay 100 --out /tmp/m   # smoke

Writes ``benchmarks/results/monitor/<dataset>_seed<k>.json`` (skipped when it exists unless
``--force``) and a PNG beside it.
"""
from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.modules import MLP

from benchmarks.harness import invocation, machine_description, REPO, repo_relative, save_figure, skip_existing, \
    write_result
from benchmarks.step_floor import recipe_config
from torchrl_tels.data import load_dataset
from torchrl_tels.envs import TSymConsistencyMonitor
from torchrl_tels.envs.monitor import SCORE_TERMS
from torchrl_tels.trainer import fit_tsidm, RunState

DEFAULT_RESULTS = REPO / "benchmarks" / "results" / "monitor"
ENV_ID = "Hopper-v4"
PLANTS = {"mass_x1.3": ("mass", 1.3), "mass_x0.7": ("mass", 0.7),
          "friction_x1.3": ("friction", 1.3), "friction_x0.7": ("friction", 0.7)}
DETECTORS = (*SCORE_TERMS, "dynamics_model", "nearest_state")


# ---------------------------------------------------------------------- AUROC
def auroc(negatives, positives) -> float:
    """P(positive score > negative score) + P(tie) / 2: the Mann-Whitney U divided by n_pos * n_neg.

    Ranks with ties averaged; a detector that scores the positives (shifted) higher is above 0.5.
    """
    negatives, positives = np.asarray(negatives, float).ravel(), np.asarray(positives, float).ravel()
    if not len(negatives) or not len(positives):
        raise ValueError("auroc needs at least one negative and one positive score.")
    scores = np.concatenate([negatives, positives])
    if not np.isfinite(scores).all():
        raise ValueError("auroc: the scores hold NaN or inf.")
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    ends = np.cumsum(counts)
    ranks = ((ends - counts + 1 + ends) / 2)[inverse]  # average rank of each distinct value, 1-based
    n_pos, n_neg = len(positives), len(negatives)
    u = ranks[n_neg:].sum() - n_pos * (n_pos + 1) / 2
    return float(u / (n_pos * n_neg))


# ----------------------------------------------------------------------- data
def split_trajectories(data: TensorDictBase, fraction: float, seed: int) -> tuple[TensorDictBase, TensorDictBase]:
    """Whole trajectories (runs of equal ``"episode"``) in a seeded random order until ``fraction`` of the
    transitions; returns (those, the rest)."""
    episode = data["episode"]
    start = torch.ones(len(episode), dtype=torch.bool)
    start[1:] = episode[1:] != episode[:-1]
    run_id = start.cumsum(0) - 1
    order = torch.randperm(int(run_id[-1]) + 1, generator=torch.Generator().manual_seed(seed))
    lengths = torch.bincount(run_id)[order]
    kept = order[: int(torch.searchsorted(lengths.cumsum(0), fraction * len(episode))) + 1]
    mask = torch.isin(run_id, kept)
    return data[mask], data[~mask]


def transitions(observation, action, next_observation) -> TensorDict:
    as_tensor = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)
    observation = as_tensor(observation)
    return TensorDict({"observation": observation, "action": as_tensor(action),
                       ("next", "observation"): as_tensor(next_observation)}, batch_size=[len(observation)])


def replay(states: TensorDictBase, actions: np.ndarray, *, plant: tuple[str, float] | None = None) -> TensorDict:
    """One Hopper-v4 step from each data state (set through ``set_state``) with ``actions``, in the plant
    scaled by ``plant = ("mass" | "friction", factor)``. The x position, absent from the observation,
    does not change the dynamics."""
    import gymnasium as gym

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Hopper-v4 "is out of date"
        env = gym.make(ENV_ID).unwrapped
    env.reset(seed=0)
    if plant is not None:
        what, factor = plant
        if what == "mass":
            env.model.body_mass[:] *= factor
        else:
            env.model.geom_friction[:, 0] *= factor
    observation = states["observation"].double().numpy()
    next_observation = np.empty_like(observation)
    for i, (obs, act) in enumerate(zip(observation, actions)):
        env.set_state(np.concatenate([[0.0], obs[:5]]), obs[5:])
        next_observation[i] = env.step(np.asarray(act, dtype=np.float64))[0]
    env.close()
    return transitions(observation, actions, next_observation)


# ------------------------------------------------------------------ detectors
def train_dynamics_model(train: TensorDictBase, loc, scale, steps: int, seed: int) -> nn.Module:
    """A one-step model f(s, a) ≈ s' - s in normalized state space (MLP 256x256, Adam 3e-4, batch 256)."""
    torch.manual_seed(seed)
    s, a = (train["observation"] - loc) / scale, train["action"]
    target = (train["next", "observation"] - loc) / scale - s
    model = MLP(in_features=s.shape[-1] + a.shape[-1], out_features=s.shape[-1], num_cells=[256, 256],
                activation_class=nn.ReLU)
    optim = torch.optim.Adam(model.parameters(), lr=3e-4)
    for _ in range(steps):
        idx = torch.randint(len(s), (256,))
        loss = (model(s[idx], a[idx]) - target[idx]).pow(2).sum(-1).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()
    return model.eval()


@torch.no_grad()
def detector_scores(td: TensorDictBase, monitor: TSymConsistencyMonitor, model: nn.Module,
                    train_states: torch.Tensor, loc, scale) -> dict[str, np.ndarray]:
    out = {k: v.numpy() for k, v in monitor.scores(td["observation"], td["action"], td["next", "observation"]).items()
           if k in SCORE_TERMS}
    s, s_next = (td["observation"] - loc) / scale, (td["next", "observation"] - loc) / scale
    out["dynamics_model"] = (model(s, td["action"]) - (s_next - s)).pow(2).sum(-1).numpy()
    out["nearest_state"] = torch.cat([torch.cdist(chunk, train_states).min(-1).values
                                      for chunk in s_next.split(1024)]).numpy()
    return out


@dataclass
class Detectors:
    """The monitor (with its calibrated threshold) and the two simple detectors, fitted on one training set."""

    monitor: TSymConsistencyMonitor
    threshold: float
    model: nn.Module
    train_states: torch.Tensor
    loc: torch.Tensor
    scale: torch.Tensor
    beta: float
    tsidm_final_loss: dict
    wall_s: dict

    def scores(self, td: TensorDictBase) -> dict[str, np.ndarray]:
        return detector_scores(td, self.monitor, self.model, self.train_states, self.loc, self.scale)


def fit_detectors(train: TensorDictBase, overrides, *, seed: int, tsidm_steps: int, model_steps: int,
                  quantile: float) -> Detectors:
    """A TS-IDM by the recipe's stage 1 (its config plus ``overrides``) and its calibrated monitor, a one-step
    dynamics model, and the normalized training states for the nearest-state distance, all on ``train``."""
    clock = time.perf_counter()
    cfg = recipe_config([f"seed={seed}", f"tsidm.steps={tsidm_steps}", "checkpoint.interval=1000000000", *overrides])
    beta = 1.0 if cfg.tsidm.beta == "auto" else float(cfg.tsidm.beta)
    torch.manual_seed(seed)
    with tempfile.TemporaryDirectory() as scratch:
        tsidm, final, _ = fit_tsidm(cfg, train, beta, RunState(config={}), Path(scratch))
    tsidm_s = time.perf_counter() - clock
    monitor = TSymConsistencyMonitor(tsidm)
    threshold = monitor.calibrate(train, quantile=quantile)
    loc, scale = tsidm.obs_loc, tsidm.obs_scale
    clock = time.perf_counter()
    model = train_dynamics_model(train, loc, scale, model_steps, seed)
    model_s = time.perf_counter() - clock
    return Detectors(monitor, threshold, model, (train["observation"] - loc) / scale, loc, scale, beta, final,
                     {"tsidm": tsidm_s, "dynamics_model": model_s})


# ------------------------------------------------------------------------ run
def subsample(td: TensorDictBase, n: int, seed: int) -> TensorDictBase:
    if n >= len(td):
        return td
    return td[torch.randperm(len(td), generator=torch.Generator().manual_seed(seed))[:n]]


def run(args) -> dict:
    torch.set_num_threads(args.threads)
    print(f"torch threads pinned to {args.threads}", flush=True)
    data = load_dataset(args.dataset)
    train, held = split_trajectories(data, 0.8, args.seed)
    print(f"{args.dataset}: {len(train)} training and {len(held)} held-out transitions", flush=True)

    detectors = fit_detectors(train, args.override, seed=args.seed, tsidm_steps=args.tsidm_steps,
                              model_steps=args.model_steps, quantile=args.quantile)

    rng = np.random.default_rng(args.seed)
    states = subsample(held, args.replay, args.seed)
    sets = {"held_out": held, "nominal_replay": replay(states, states["action"].numpy())}
    sets["random_actions"] = replay(states, rng.uniform(-1.0, 1.0, size=tuple(states["action"].shape)))
    try:
        sets["other_dataset"] = subsample(load_dataset(args.other), len(held), args.seed)
    except Exception as err:  # the shared folder is optional
        print(f"skip other_dataset: {args.other}: {type(err).__name__}: {err}", flush=True)
    for name, plant in PLANTS.items():
        sets[name] = replay(states, states["action"].numpy(), plant=plant)
    scores = {name: detectors.scores(td) for name, td in sets.items()}

    reference = {name: "held_out" for name in sets if name != "held_out"}
    paired = {name: "nominal_replay" for name in PLANTS}
    table = {}
    for name, ref in [*reference.items(), *((f"{n} vs nominal_replay", r) for n, r in paired.items())]:
        shifted = name.split(" vs ")[0]
        table[name] = {d: auroc(scores[ref][d], scores[shifted][d]) for d in DETECTORS}
    monitor, threshold = detectors.monitor, detectors.threshold
    flag_rate = {name: float((scores[name][monitor.score_key] > threshold).mean()) for name in sets}
    return {
        "command": invocation(),
        "dataset": args.dataset,
        "env": ENV_ID,
        "seed": args.seed,
        "tsidm_steps": args.tsidm_steps,
        "tsidm_beta": detectors.beta,
        "tsidm_final_loss": detectors.tsidm_final_loss,
        "overrides": list(args.override),
        "dynamics_model_steps": args.model_steps,
        "sizes": {name: len(td) for name, td in sets.items()},
        "monitor": {"score": monitor.score_key, "quantile": args.quantile, "threshold": threshold,
                    "flag_rate": flag_rate},
        "auroc": table,
        "wall_s": detectors.wall_s,
        "threads": args.threads,
        "machine": machine_description(),
    }


def plot(result: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(result["auroc"])
    fig, ax = plt.subplots(figsize=(max(8, 1.1 * len(rows)), 4.5))
    width = 0.8 / len(DETECTORS)
    for i, detector in enumerate(DETECTORS):
        ax.bar(np.arange(len(rows)) + (i - (len(DETECTORS) - 1) / 2) * width,
               [result["auroc"][row][detector] for row in rows], width, label=detector)
    ax.axhline(0.5, color="black", lw=0.8, ls="--")
    ax.set_xticks(np.arange(len(rows)), [row.replace(" vs ", "\nvs ") for row in rows], fontsize=7)
    ax.set_ylim(0, 1)
    ax.set_ylabel("AUROC (shifted vs reference)")
    ax.set_title(f"OOD detection on {result['dataset']} (TS-IDM {result['tsidm_steps']} steps, seed {result['seed']})")
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return path


def parse_args(argv=None):
    parser = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="hopper-medium-v2-10k", help="the in-distribution data (Hopper)")
    parser.add_argument("--other", default="hopper-medium-replay-v2-10k", help="another behaviour's dataset")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tsidm-steps", type=int, default=3000, help="TS-IDM steps (the study budget: 3000)")
    parser.add_argument("--model-steps", type=int, default=3000, help="steps of the one-step dynamics model")
    parser.add_argument("--replay", type=int, default=2000, help="held-out states replayed per shifted set")
    parser.add_argument("--quantile", type=float, default=0.99, help="the monitor's calibration quantile")
    parser.add_argument("--override", action="append", default=[], help="a hydra override of the recipe's config")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--out", type=Path, default=DEFAULT_RESULTS, help="results folder")
    parser.add_argument("--force", action="store_true", help="redo an existing result")
    return parser.parse_args(argv)


def main(argv=None) -> None:
    args = parse_args(argv)
    path = args.out / f"{Path(args.dataset).stem}_seed{args.seed}.json"
    if skip_existing(path, args.force):
        return
    result = run(args)
    write_result(path, result, force=True)
    plot(result, path.with_suffix(".png"))
    print(f"{'AUROC':<32}" + "".join(f"{d:>20}" for d in DETECTORS))
    for name, row in result["auroc"].items():
        print(f"{name:<32}" + "".join(f"{row[d]:>20.3f}" for d in DETECTORS))
    print(f"monitor flag rate at q={args.quantile}: " +
          ", ".join(f"{k} {v:.1%}" for k, v in result["monitor"]["flag_rate"].items()))
    print(f"wrote {repo_relative(path)} and {repo_relative(path.with_suffix('.png'))}")


if __name__ == "__main__":
    main()
