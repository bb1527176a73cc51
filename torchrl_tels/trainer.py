"""The pieces of Algorithm 1 that the recipe, the baselines and the benchmarks build alike.

``recipes/tels_offline.py`` reads as Algorithm 1 because the construction lives
here, as torchrl's ``sota-implementations`` keep theirs in ``utils.py``:

* :func:`make_data`: the dataset, its subset or deleted regions, and the task it
  is evaluated on, all validated before anything is written;
* :class:`RunState`: everything a killed run needs to continue, saved as one
  typed record with :meth:`RunState.save` / :meth:`RunState.load`;
* :func:`make_stage1` / :func:`fit_tsidm`: the TS-IDM and Eq. (7);
* :func:`make_stage2`: the latent value (Eq. 8), the guide (Eq. 9/10), their
  optimizers and the actor of Eq. (11);
* :func:`evaluate`: deterministic episodes with the diagnostics of a frozen policy and,
  when given the deployment monitor, its scores and alarms along the episodes.
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch
import tqdm
from omegaconf import OmegaConf
from tensordict import TensorDictBase
from torchrl.objectives import SoftUpdate

from torchrl_tels.compile import capturable_adam, compile_update, precision_context
from torchrl_tels.config import check_same_run, resolve_device, resolve_precision, training_config
from torchrl_tels.data import delete_regions, load_dataset, make_offline_replay_buffer, subset_dataset
from torchrl_tels.data.datasets import recorded_env_id
from torchrl_tels.diagnostics import (action_chain_statistics, awr_weight_statistics, is_frozen, is_off_data,
                                     latent_statistics, maze_cells, rollout_statistics)
from torchrl_tels.envs import (DeploymentMonitor, get_task, normalized_score, rollout_episodes, Task,
                               TSIDMEncoderTransform)
from torchrl_tels.envs.antmaze import ENV_ID as ANTMAZE_ENV_ID
from torchrl_tels.envs.evaluation import episode_success, eval_env_spaces, success_rate
from torchrl_tels.errors import DatasetError, TaskError
from torchrl_tels.monitor import monitor_record
from torchrl_tels.modules import make_guide_policy, make_latent_value, make_tels_actor, TSIDM
from torchrl_tels.objectives import LatentExpectileLoss, TSIDMLoss, TSymGuideLoss
from torchrl_tels.run_folder import RunFolder
from torchrl_tels import training
from torchrl_tels.seeds import SeedRNG, StackedLoss
from torchrl_tels.training import check_finite_state, FiniteWatch, get_rng_state, set_rng_state, sum_losses

__all__ = [
    "RunState",
    "Stage2",
    "StackedStage2",
    "TSIDM_TERMS",
    "autocast",
    "evaluate",
    "fit_tsidm",
    "fit_tsidm_seeds",
    "check_same_stage1_length",
    "adopt_pretrained_tsidm",
    "skip_stage1",
    "load_pretrained_tsidm",
    "make_data",
    "make_stage1",
    "make_stage2",
    "make_tsidm",
    "make_tsidm_loss",
    "resolve_task",
    "sample_seeds",
    "tsidm_steps",
]

TSIDM_TERMS = ("ell_rec", "ell_dyn", "ell_ode", "ell_tsym", "ell_total", "ell_sum", "latent_rms", "latent_step_rms")
# App. B.5 picks beta by "the lowest TS-IDM training loss": "unweighted" compares the four terms'
# sum (ell_sum), "weighted" Eq. (7) itself (ell_total), which scales three terms by the candidate.
SELECTION_KEYS = {"unweighted": "final_sum", "weighted": "final_loss"}


def run_precision(cfg):
    """The factory of the loss forward passes' autocast context for the run's device and resolved precision."""
    return precision_context(resolve_device(cfg.device), resolve_precision(cfg.precision, cfg.device))


def autocast(cfg):
    """bf16 matmuls on the run's device (CPU or CUDA) when ``precision`` is or resolves to bf16; fp32 otherwise."""
    return run_precision(cfg)()


def compile_options(cfg) -> dict:
    """The ``compile`` group as :func:`~torchrl_tels.compile.compile_update`'s keywords; all off for the
    config of a run saved before the group existed."""
    return {"compile": bool(OmegaConf.select(cfg, "compile.compile", default=False)),
            "cudagraphs": bool(OmegaConf.select(cfg, "compile.cudagraphs", default=False)),
            "mode": OmegaConf.select(cfg, "compile.mode", default=None)}


def make_compiled_step(loss_module, optim: torch.optim.Optimizer, cfg):
    """:func:`make_train_step` with the run's precision and ``compile`` switches."""
    options = compile_options(cfg)
    step = make_train_step(loss_module, optim, run_precision(cfg), compile=options["compile"], mode=options["mode"])
    return compile_update(step, cudagraphs=options["cudagraphs"])


def make_train_step(loss_module, optim: torch.optim.Optimizer, amp=contextlib.nullcontext, *,
                    compile: bool = False, mode: str | None = None):
    """One train step of ``loss_module`` as a function of the batch: forward (under ``amp``), backward
    of the sum of its ``loss_*`` entries (summed over seeds for a stacked loss), optimizer step.

    Returns the detached losses. :func:`~torchrl_tels.compile.compile_update` can record the step
    whole as a CUDA graph. ``compile`` compiles the loss's forward pass (its backward follows, through
    AOTAutograd) and leaves the optimizer its fused kernel: compiling the whole step instead breaks its
    graph at the backward and at the optimizer, and stage 2's two steps then share compiled frames
    whose guard checks cost more per step than compiling saves (BENCHMARKS.md, "Compiled train steps")."""
    if compile:
        # torchrl losses build their in_keys on first read; built inside the first traced call, they would
        # fail that graph's guard at the second call and compile the loss a second time.
        getattr(loss_module, "in_keys", None)
    forward = torch.compile(loss_module, mode=mode) if compile else loss_module

    def train_step(batch: TensorDictBase) -> TensorDictBase:
        with amp():
            losses = forward(batch)
        sum_losses(losses).sum().backward()  # a stacked loss: the seeds share no parameter
        optim.step()
        optim.zero_grad(set_to_none=True)
        return losses.detach()

    return train_step


def tsidm_steps(cfg, n_transitions: int) -> int:
    """Stage 1's length: ``tsidm.steps``, or ``tsidm.epochs`` passes over the data (Table 10)."""
    return cfg.tsidm.steps or cfg.tsidm.epochs * math.ceil(n_transitions / cfg.tsidm.batch_size)


def print_plan(cfg, n_transitions: int) -> None:
    """Says, before anything trains, how long each stage will run; warns when an epoch budget on a large set
    means a stage 1 of more than ``tsidm.warn_steps`` steps (Table 10's 1000 epochs were set for 10k sets)."""
    stage1 = 0 if cfg.tsidm.checkpoint else tsidm_steps(cfg, n_transitions)
    candidates = len(cfg.tsidm.beta_candidates) if cfg.tsidm.beta == "auto" and not cfg.tsidm.checkpoint else 1
    how = ("the TS-IDM of tsidm.checkpoint" if cfg.tsidm.checkpoint else "from tsidm.steps" if cfg.tsidm.steps
           else f"{cfg.tsidm.epochs} epochs of {n_transitions} transitions")
    print(f"plan: stage 1 {stage1 * candidates} TS-IDM steps ({how}"
          + (f", {candidates} beta candidates" if candidates > 1 else "") + f"), stage 2 {cfg.policy.steps} policy "
          f"steps, an evaluation of {cfg.eval.episodes} episodes every {cfg.eval.interval} steps; batch "
          f"{cfg.tsidm.batch_size}/{cfg.policy.batch_size}")
    warn = cfg.tsidm.get("warn_steps")
    if warn and not cfg.tsidm.steps and stage1 > warn:
        print(f"warning: tsidm.epochs={cfg.tsidm.epochs} on {n_transitions} transitions is {stage1} TS-IDM steps, "
              f"past tsidm.warn_steps={warn}; set tsidm.steps to bound stage 1 (BENCHMARKS.md, data size).",
              file=sys.stderr)


def diagnostic_indices(cfg, n_transitions: int) -> torch.Tensor | None:
    """The transitions the after-training readings average over: a random subset of ``diagnostics.max_transitions``
    (seeded by the run's seed), or ``None`` for all of them when the data is no larger."""
    limit = OmegaConf.select(cfg, "diagnostics.max_transitions")
    if limit is None or n_transitions <= limit:
        return None
    generator = torch.Generator().manual_seed(int(cfg.seed))
    return torch.randperm(n_transitions, generator=generator)[:limit].sort().values


# ----------------------------------------------------------------------------- data
def resolve_task(cfg, source: str) -> Task:
    """The evaluation task: ``dataset.task`` or the dataset's name, else the env the dataset recorded.

    A Minari dataset records its environment, so a user's own data trains
    without a registered task; it then has no reference scores, and its
    results are raw returns.
    """
    name = cfg.dataset.task or Path(str(cfg.dataset.name)).stem
    try:
        return get_task(name)
    except TaskError:
        env_id = None if cfg.dataset.task else recorded_env_id(source)
        if env_id is None:
            raise
        return Task(str(cfg.dataset.name), env_id, None, None, None, None)


def _check_fits_env(data: TensorDictBase, task: Task, name: str) -> None:
    import gymnasium as gym
    import numpy as np

    obs_space, act_space = eval_env_spaces(task.env_id)
    obs_dim = int(gym.spaces.flatdim(obs_space))
    obs_size, act_size = data["observation"].shape[-1], data["action"].shape[-1]
    if obs_dim != obs_size or act_space.shape[-1] != act_size:
        raise DatasetError(f"dataset {name!r} has observation/action sizes {obs_size}/{act_size} but env "
                           f"{task.env_id} has {obs_dim}/{act_space.shape[-1]}.")
    low, high = torch.as_tensor(np.asarray(act_space.low)), torch.as_tensor(np.asarray(act_space.high))
    actions = data["action"].to(low.dtype)
    outside = ((actions < low - 1e-6) | (actions > high + 1e-6)).any(-1)
    if outside.any():
        raise DatasetError(
            f"dataset {name!r}: {int(outside.sum())} of {len(outside)} actions lie outside the action bounds of "
            f"{task.env_id} ([{low.min().item():g}, {high.max().item():g}]); the data span "
            f"[{actions.min().item():g}, {actions.max().item():g}]. The actor clips to the bounds, so it could "
            f"never take them: rescale the actions to the env's bounds first.")


def make_data(cfg) -> tuple[TensorDictBase, Task]:
    """The training transitions and their evaluation task, validated (nothing is written)."""
    name = str(cfg.dataset.name)
    data = load_dataset(name)
    if cfg.dataset.size:
        data = subset_dataset(data, int(cfg.dataset.size), seed=cfg.seed, mode=cfg.dataset.subset)
    if cfg.dataset.delete_boxes:
        if max(cfg.dataset.delete_xy) >= data["observation"].shape[-1]:
            raise DatasetError(f"dataset.delete_xy={list(cfg.dataset.delete_xy)} names a column beyond the "
                               f"{data['observation'].shape[-1]} observation columns of {name!r}.")
        # Fig. 3's OOD test: the same seed removes the same transitions for every method.
        before = len(data)
        data = delete_regions(data, [tuple(box) for box in cfg.dataset.delete_boxes], cfg.dataset.delete_ratio,
                              seed=cfg.seed, xy_slice=list(cfg.dataset.delete_xy))
        print(f"dataset.delete_boxes: deleted {before - len(data)} of {before} transitions, {len(data)} left")
    task = resolve_task(cfg, name)
    _check_fits_env(data, task, name)
    for path in ("tsidm.batch_size", "policy.batch_size"):
        if OmegaConf.select(cfg, path) > len(data):
            raise DatasetError(f"dataset {name!r} has {len(data)} transitions, fewer than "
                               f"{path}={OmegaConf.select(cfg, path)}.")
    return data, task


# ------------------------------------------------------------------------ run state
@dataclass
class RunState:
    """Where a run is in Algorithm 1, and what it has produced so far.

    ``stage`` moves ``"tsidm"`` → ``"policy"`` → ``"done"``; ``candidate`` and
    ``step`` say where in that stage. Module and optimizer states travel beside
    it in ``state.pt`` (see :meth:`save`), so a killed run continues where its
    last checkpoint left it.
    """

    config: dict
    stage: str = "tsidm"
    candidate: int = 0
    step: int = 0
    wandb_id: str | None = None
    wall: dict = field(default_factory=dict)
    beta_results: list = field(default_factory=list)
    tsidm_history: dict = field(default_factory=dict)
    policy_history: dict = field(default_factory=dict)
    evaluations: list = field(default_factory=list)
    modules: dict = field(default_factory=dict)
    rng: dict | None = None
    per_seed: list = field(default_factory=list)  # with ``seeds``: each seed's record (:meth:`seed_record`)

    def __post_init__(self):
        self._clocks: list[_Stopwatch] = []  # the running :meth:`time` spans, brought up to date by :meth:`save`

    @classmethod
    def start(cls, cfg, path: Path) -> "RunState":
        """A fresh state, or with ``resume=true`` the one in ``path`` (checked to be the same run)."""
        config = training_config(cfg)
        if not (cfg.resume and path.exists()):
            return cls(config=config)
        saved = training.load_training_state(path)
        check_same_run(saved.get("config"), config, f"checkpoint {path}")
        fields = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in saved.items() if k in fields and k != "config"}, config=config)

    def save(self, path: Path, **modules: Any) -> None:
        """Writes this state, ``modules`` (state dicts) and, with them, the RNG streams atomically.

        The wall-clock spans still running (:meth:`time`) are counted up to now first, so a
        resumed run's times include the work before the interruption."""
        for clock in self._clocks:
            clock.update()
        self.modules = modules
        self.rng = get_rng_state() if modules else None
        # A shallow record: torch.save writes the tensors as they are, no copy needed.
        training.save_training_state(path, {f.name: getattr(self, f.name) for f in dataclasses.fields(self)})

    def resumes(self, stage: str, candidate: int = 0) -> bool:
        """Whether this state holds a checkpoint inside ``stage`` (and β candidate) to continue."""
        return self.stage == stage and self.candidate == candidate and self.step > 0 and bool(self.modules)

    def restore(self, **modules: Any) -> None:
        """Loads the saved module states into ``modules`` and the RNG streams (after :meth:`resumes`)."""
        for name, module in modules.items():
            module.load_state_dict(self.modules[name])
        set_rng_state(self.rng)

    #: what a seed of a ``seeds`` run keeps of its own; the rest (stage, step, modules) is the run's
    SEED_FIELDS = ("beta_results", "tsidm_history", "policy_history", "evaluations", "wall")

    def seed_record(self) -> dict:
        return {name: getattr(self, name) for name in self.SEED_FIELDS}

    @classmethod
    def from_seed_record(cls, record: dict) -> "RunState":
        return cls(config={}, **{name: record[name] for name in cls.SEED_FIELDS})

    def time(self, key: str):
        """A context that adds the wall-clock time it spans to ``wall[key]``."""
        return _Stopwatch(self.wall, key, self._clocks)


class _Stopwatch:
    def __init__(self, wall: dict, key: str, running: list):
        self.wall, self.key, self.running = wall, key, running

    def __enter__(self):
        self.start = time.perf_counter() - self.wall.get(self.key, 0.0)
        self.running.append(self)
        return self

    def update(self):
        self.wall[self.key] = time.perf_counter() - self.start

    def __exit__(self, *exc):
        self.update()
        self.running.remove(self)


# -------------------------------------------------------------------------- stage 1
def make_tsidm(cfg, data: TensorDictBase) -> TSIDM:
    """A fresh TS-IDM of Table 10's shape, with state normalization fitted on ``data``."""
    t = cfg.tsidm
    tsidm = TSIDM(
        data["observation"].shape[-1],
        data["action"].shape[-1],
        latent_state_dim=t.latent_state_dim,
        latent_action_dim=t.latent_action_dim,
        encoder_cells=t.encoder_cells,
        decoder_cells=t.decoder_cells,
        inverse_cells=t.inverse_cells,
        action_decoder_cells=t.action_decoder_cells,
        dynamics_cells=t.dynamics_cells,
        inverse_dropout=t.inverse_dropout,
        latent_standardization=t.latent_scale == "standardized",
    )
    tsidm.fit_state_normalization(data["observation"])
    return tsidm


def make_tsidm_loss(cfg, tsidm: TSIDM, beta: float) -> TSIDMLoss:
    """Eq. (7) with the config's β, Table 3 ablation, norm reduction and latent-scale option."""
    t = cfg.tsidm
    term_weights = OmegaConf.to_container(t.term_weights) if t.term_weights is not None else None
    return TSIDMLoss(tsidm, beta=beta, ablation=t.ablation, dim_reduction=t.dim_reduction,
                     term_weights=term_weights, relative=t.latent_scale == "relative", check_inputs=False)


def fit_tsidm(cfg, data, beta: float, run: RunState, run_dir: RunFolder | Path, logger=None):
    """Stage 1 for one β (Eq. 7): a trained TS-IDM, its final losses and its loss history.

    Final losses average the last 10 % of steps, which App. B.5's β rule compares; the checkpoints go to
    ``run_dir``'s state file.
    """
    folder = RunFolder(run_dir)
    t = cfg.tsidm
    device = resolve_device(cfg.device)
    tsidm = make_tsidm(cfg, data).to(device)
    loss_module = make_tsidm_loss(cfg, tsidm, beta)
    optim = capturable_adam(loss_module.parameters(), lr=t.lr, weight_decay=t.weight_decay,
                            capturable=compile_options(cfg)["cudagraphs"])
    buffer = make_offline_replay_buffer(data, t.batch_size, device=device)
    watch = FiniteWatch(f"stage 1 (TS-IDM, beta={beta:g})")
    total = tsidm_steps(cfg, len(data))
    start, tail, history = 0, [], {key: [] for key in TSIDM_TERMS}
    if run.resumes("tsidm", run.candidate):
        run.restore(loss=loss_module, optim=optim)
        start, history, tail = run.step, run.tsidm_history, run.modules["tail"]

    train_step = make_compiled_step(loss_module, optim, cfg)
    progress = tqdm.tqdm(range(start, total), desc=f"stage 1: TS-IDM beta={beta:g}", file=sys.stdout,
                         initial=start, total=total, mininterval=2.0)
    for step in progress:
        losses = train_step(buffer.sample())
        watch.update(losses, step)
        if step >= int(0.9 * total):  # int(): runs under 10 steps still keep their last step
            tail.append(torch.stack([losses["ell_total"], losses["ell_sum"]]))
        if (step + 1) % cfg.logger.log_interval == 0:
            watch.check()
            scalars = {k: losses[k].item() for k in TSIDM_TERMS if k in losses.keys()}
            for key, value in scalars.items():
                history[key].append((step + 1, value))
            if logger is not None:
                logger.log_scalars({**{f"tsidm/{k}": v for k, v in scalars.items()}, "tsidm/beta": beta},
                                   step + 1 + run.candidate * total)
            progress.set_postfix(loss=f"{scalars['ell_total']:.4f}")
        if (step + 1) % cfg.checkpoint.interval == 0 and step + 1 < total:
            watch.check()
            run.step, run.tsidm_history = step + 1, history
            run.save(folder.state_path, loss=loss_module.state_dict(), optim=optim.state_dict(),
                     tail=[pair.tolist() for pair in tail])
    watch.check()
    check_finite_state(loss_module.state_dict(), f"stage 1 (TS-IDM, beta={beta:g}) after step {total}")
    tsidm = tsidm.cpu()  # saved and handed on from the CPU; stage 2 moves it where it trains
    if tsidm.latent_standardization:
        tsidm.fit_latent_standardization(data["observation"])
    tail = [pair.tolist() if torch.is_tensor(pair) else pair for pair in tail]
    final = {key: sum(pair[i] for pair in tail) / len(tail) for i, key in enumerate(("final_loss", "final_sum"))}
    return tsidm.eval(), final, history


def fit_tsidm_seeds(cfg, datas: list, seeds: list[int], run: RunState, run_dir: RunFolder | Path, logger=None):
    """Stage 1 (Eq. 7) for several seeds at once, one ``(tsidm, final, history)`` per seed.

    :func:`fit_tsidm`, with the seeds' TS-IDM losses stacked (:class:`~torchrl_tels.seeds.StackedLoss`):
    each seed is initialised and draws its batches from its own RNG stream, as its single-seed run does.
    ``run`` checkpoints the stacked state and the streams; resuming continues all seeds.
    """
    folder = RunFolder(run_dir)
    t = cfg.tsidm
    beta = float(t.beta)
    device = resolve_device(cfg.device)
    total = check_same_stage1_length(cfg, datas, seeds)
    rng = SeedRNG(len(seeds))
    tsidms, losses, buffers = [], [], []
    for k, (seed, data) in enumerate(zip(seeds, datas)):
        rng.start(k, seed)  # a single-seed run seeds stage 1 with seed + candidate, candidate 0
        with rng.use(k):
            tsidms.append(make_tsidm(cfg, data).to(device))
            losses.append(make_tsidm_loss(cfg, tsidms[-1], beta))
            buffers.append(make_offline_replay_buffer(data, t.batch_size, device=device))
    stack = StackedLoss(losses)
    optim = capturable_adam(stack.trainable(), lr=t.lr, weight_decay=t.weight_decay,
                            capturable=compile_options(cfg)["cudagraphs"])
    watch = FiniteWatch(f"stage 1 (TS-IDM, beta={beta:g})", entries=[f"seed {seed}" for seed in seeds])
    start, tail, histories = 0, [], [{key: [] for key in TSIDM_TERMS} for _ in seeds]
    if run.resumes("tsidm"):
        run.restore(loss=stack, optim=optim, seed_rng=rng)
        start, histories, tail = run.step, run.modules["histories"], run.modules["tail"]

    train_step = make_compiled_step(stack, optim, cfg)
    progress = tqdm.tqdm(range(start, total), desc=f"stage 1: TS-IDM beta={beta:g}, {len(seeds)} seeds",
                         file=sys.stdout, initial=start, total=total, mininterval=2.0)
    for step in progress:
        out = train_step(sample_seeds(buffers, rng))
        watch.update(out, step)
        if step >= int(0.9 * total):
            tail.append(torch.stack([out["ell_total"], out["ell_sum"]], -1))
        if (step + 1) % cfg.logger.log_interval == 0:
            watch.check()
            for k, seed in enumerate(seeds):
                scalars = {key: out[key][k].item() for key in TSIDM_TERMS if key in out.keys()}
                for key, value in scalars.items():
                    histories[k][key].append((step + 1, value))
                if logger is not None:
                    logger.log_scalars({f"seed{seed}/tsidm/{key}": v for key, v in scalars.items()}, step + 1)
            progress.set_postfix(loss=f"{out['ell_total'].mean().item():.4f}")
        if (step + 1) % cfg.checkpoint.interval == 0 and step + 1 < total:
            watch.check()
            run.step = step + 1
            run.save(folder.state_path, loss=stack.state_dict(), optim=optim.state_dict(),
                     seed_rng=rng.state_dict(), histories=histories, tail=[pair.tolist() for pair in tail])
    watch.check()
    stack.write_back()
    tail = torch.tensor([pair.tolist() if torch.is_tensor(pair) else pair for pair in tail])  # [steps, seeds, 2]
    results = []
    for k, (seed, data) in enumerate(zip(seeds, datas)):
        check_finite_state(losses[k].state_dict(), f"stage 1 (TS-IDM, seed {seed}) after step {total}")
        tsidm = tsidms[k].cpu()
        if tsidm.latent_standardization:
            tsidm.fit_latent_standardization(data["observation"])
        final = {"final_loss": tail[:, k, 0].mean().item(), "final_sum": tail[:, k, 1].mean().item()}
        results.append((tsidm.eval(), final, histories[k]))
    return results


def sample_seeds(buffers: list, rng: SeedRNG) -> TensorDictBase:
    """One batch per seed, each drawn from its own buffer on its own RNG stream, stacked ``[seeds, batch]``."""
    batches = []
    for k, buffer in enumerate(buffers):
        with rng.use(k):
            batches.append(buffer.sample())
    return torch.stack(batches)


def load_pretrained_tsidm(cfg, data) -> TSIDM | None:
    """The TS-IDM of ``tsidm.checkpoint`` (checked against the data's sizes), or ``None``."""
    if not cfg.tsidm.checkpoint:
        return None
    return TSIDM.load(cfg.tsidm.checkpoint, observation_dim=data["observation"].shape[-1],
                      action_dim=data["action"].shape[-1])


def adopt_pretrained_tsidm(cfg, pretrained: TSIDM, run: RunState, run_dirs) -> TSIDM:
    """Starts ``run`` at stage 2 from ``tsidm.checkpoint``'s TS-IDM, copied into each of the run folders ``run_dirs``
    (its source in the metadata), so that a run folder holds every model it acted with: export and the readings of
    finished runs load ``tsidm.pt`` from the folder, and the checkpoint may move or change after the run."""
    skip_stage1(run)
    metadata = {**pretrained.metadata, "checkpoint": str(cfg.tsidm.checkpoint)}
    for run_dir in run_dirs:
        pretrained.save(RunFolder(run_dir).tsidm_path, metadata=metadata)
    return pretrained


def skip_stage1(run: RunState) -> None:
    """Moves a run that starts from a pretrained TS-IDM to stage 2, so that its stage-2 checkpoints resume there."""
    if run.stage == "tsidm":
        run.stage, run.candidate, run.step = "policy", 0, 0


def check_same_stage1_length(cfg, datas: list, seeds: list[int]) -> int:
    """Stage 1's length, shared by every seed of a ``seeds`` run; a :class:`DatasetError` if their subsets differ."""
    totals = {tsidm_steps(cfg, len(data)) for data in datas}
    if len(totals) > 1:
        raise DatasetError(f"seeds {seeds}: their data subsets give stage 1 different lengths {sorted(totals)}; "
                           f"set tsidm.steps to train every seed as long.")
    return totals.pop()


def make_stage1(cfg, data, run: RunState, run_dir: RunFolder | Path, logger=None,
                pretrained: TSIDM | None = None) -> TSIDM:
    """Algorithm 1, lines 1-4: the ``pretrained`` TS-IDM, this run's finished stage 1, or a trained one.

    With ``tsidm.beta=auto`` each candidate is trained and the one with the lowest final
    training loss is kept (App. B.5); finished candidates survive an interruption.
    """
    folder = RunFolder(run_dir)
    if pretrained is not None:
        return adopt_pretrained_tsidm(cfg, pretrained, run, [run_dir])
    if run.stage != "tsidm":
        return TSIDM.load(folder.tsidm_path, observation_dim=data["observation"].shape[-1],
                          action_dim=data["action"].shape[-1])
    candidates = list(cfg.tsidm.beta_candidates) if cfg.tsidm.beta == "auto" else [float(cfg.tsidm.beta)]
    key = SELECTION_KEYS[cfg.tsidm.beta_selection]
    best = None
    with run.time("tsidm_s"):
        for candidate, beta in enumerate(candidates):
            if candidate < len(run.beta_results):
                continue  # finished before an interruption; its model is in best_tsidm.pt
            run.candidate = candidate
            torch.manual_seed(cfg.seed + candidate)
            model, final, history = fit_tsidm(cfg, data, beta, run, run_dir, logger)
            run.beta_results.append({"beta": beta, **final})
            print(f"TS-IDM beta={beta:g}: final training loss {final['final_loss']:.5f} (Eq. 7), "
                  f"{final['final_sum']:.5f} (unweighted)")
            if min(r[key] for r in run.beta_results) == final[key]:
                best = (model, history, beta)
                model.save(folder.best_tsidm_path, metadata={"beta": beta, "history": history})
            run.candidate, run.step, run.tsidm_history = candidate + 1, 0, {}
            run.save(folder.state_path)
        if best is None:
            model = TSIDM.load(folder.best_tsidm_path)
            best = (model, model.metadata["history"], model.metadata["beta"])
        tsidm, run.tsidm_history, beta = best
        tsidm.metadata = {"beta": beta, "dataset": str(cfg.dataset.name), "beta_results": run.beta_results}
        tsidm.save(folder.tsidm_path, metadata=tsidm.metadata)
    print(f"stage 1 done: beta={beta:g}, TS-IDM saved to {folder.tsidm_path}")
    run.stage, run.candidate, run.step = "policy", 0, 0
    run.save(folder.state_path)
    return tsidm


# -------------------------------------------------------------------------- stage 2
@dataclass
class Stage2:
    """Algorithm 1's stage 2: the encoded data, V (Eq. 8), the guide (Eq. 9/10) and the actor (Eq. 11)."""

    buffer: Any
    value_loss: LatentExpectileLoss
    guide_loss: TSymGuideLoss
    value_optim: torch.optim.Optimizer
    guide_optim: torch.optim.Optimizer
    target_updater: SoftUpdate
    actor: Any
    guide: Any
    actor_options: dict
    latent_stats: dict
    device: torch.device = torch.device("cpu")
    amp: Callable = contextlib.nullcontext  # the loss forward passes' precision (precision_context)
    compile: dict = field(default_factory=dict)  # compile_update's switches (compile_options)
    value_watch: FiniteWatch = field(default_factory=lambda: FiniteWatch("stage 2 (value)"))
    guide_watch: FiniteWatch = field(default_factory=lambda: FiniteWatch("stage 2 (guide)"))

    def __post_init__(self):
        self.train_step = make_stage2_step(self.value_loss, self.value_optim, self.guide_loss, self.guide_optim,
                                           self.target_updater.step, self.amp, self.compile)

    def update(self, batch: TensorDictBase, step: int):
        """Algorithm 1, line 7: V by Eq. (8); line 8: the guide against the updated V; then the target V.

        A non-finite loss is recorded without a host synchronization; :meth:`check_finite`
        raises for it, naming the term and the step."""
        value_losses, guide_losses = self.train_step(batch)
        self.value_watch.update(value_losses, step)
        self.guide_watch.update(guide_losses, step)
        return value_losses, guide_losses

    def check_finite(self) -> None:
        """Raises :class:`NonFiniteLossError` if any loss was not finite since the start."""
        self.value_watch.check()
        self.guide_watch.check()

    def modules(self) -> dict:
        return {"value_loss": self.value_loss, "guide_loss": self.guide_loss,
                "value_optim": self.value_optim, "guide_optim": self.guide_optim}


def _adam_options(optim: torch.optim.Optimizer) -> dict:
    group = optim.param_groups[0]
    return {key: group[key] for key in ("lr", "betas", "eps", "weight_decay", "fused", "capturable")}


def make_stage2_step(value_loss, value_optim: torch.optim.Optimizer, guide_loss, guide_optim: torch.optim.Optimizer,
                     update_target: Callable, amp=contextlib.nullcontext, options: dict | None = None) -> Callable:
    """Stage 2's whole train step (Algorithm 1, lines 7-8): V by Eq. (8), then the guide against the
    updated V (Eq. 9/10), then the target V; returns both losses. ``options`` are :func:`compile_options`:
    each loss's forward compiled, the whole step recorded as a CUDA graph."""
    options = options or {}
    compiled = {"compile": options.get("compile", False), "mode": options.get("mode")}
    value_step = make_train_step(value_loss, value_optim, amp, **compiled)
    guide_step = make_train_step(guide_loss, guide_optim, amp, **compiled)

    def train_step(batch: TensorDictBase):
        value_losses = value_step(batch)
        guide_losses = guide_step(batch)
        update_target()
        return value_losses, guide_losses

    return compile_update(train_step, cudagraphs=options.get("cudagraphs", False))


@dataclass
class StackedStage2:
    """:class:`Stage2` for several seeds, one per entry of ``stages``, updated as one stacked step.

    The guide's copy of V is a view of the stacked V, so it reads the updated V, as in
    :meth:`Stage2.update`; the target V follows by the same ``lerp_`` as torchrl's ``SoftUpdate``.
    Call :meth:`write_back` before using a seed's own actor, guide or V.
    """

    stages: list[Stage2]
    rng: SeedRNG
    labels: list[str]
    value: StackedLoss = field(init=False)
    guide: StackedLoss = field(init=False)
    value_optim: torch.optim.Optimizer = field(init=False)
    guide_optim: torch.optim.Optimizer = field(init=False)

    def __post_init__(self):
        self.value = StackedLoss([stage.value_loss for stage in self.stages])
        self.guide = StackedLoss([stage.guide_loss for stage in self.stages])
        self.guide.share("value_network_params", self.value)
        # the seeds' own optimizers, side by side: Adam is elementwise, so one over the stack is each seed's
        first = self.stages[0]
        self.value_optim = torch.optim.Adam(self.value.trainable("value_network_params"),
                                            **_adam_options(first.value_optim))
        self.guide_optim = torch.optim.Adam(self.guide.trainable(), **_adam_options(first.guide_optim))
        self.target_weight = 1 - first.target_updater.eps  # torchrl's SoftUpdate: target.lerp_(source, 1 - eps)
        self.value_watch = FiniteWatch("stage 2 (value)", entries=self.labels)
        self.guide_watch = FiniteWatch("stage 2 (guide)", entries=self.labels)
        self.train_step = make_stage2_step(self.value, self.value_optim, self.guide, self.guide_optim,
                                           self.update_target, first.amp, first.compile)

    def sample(self) -> TensorDictBase:
        return sample_seeds([stage.buffer for stage in self.stages], self.rng)

    def update_target(self) -> None:
        params = self.value.params
        params["target_value_network_params"].data.lerp_(params["value_network_params"].data, self.target_weight)

    def update(self, batch: TensorDictBase, step: int):
        """:meth:`Stage2.update` for every seed at once; the losses carry a leading seed dimension."""
        value_losses, guide_losses = self.train_step(batch)
        self.value_watch.update(value_losses, step)
        self.guide_watch.update(guide_losses, step)
        return value_losses, guide_losses

    def check_finite(self) -> None:
        self.value_watch.check()
        self.guide_watch.check()

    def write_back(self) -> None:
        self.value.write_back()
        self.guide.write_back()

    def modules(self) -> dict:
        return {"value_loss": self.value, "guide_loss": self.guide, "value_optim": self.value_optim,
                "guide_optim": self.guide_optim, "seed_rng": self.rng}


def make_stage2(cfg, data: TensorDictBase, tsidm: TSIDM, action_spec) -> Stage2:
    """Freezes the TS-IDM, encodes the data once (Algorithm 1, line 6) and builds V, π_g and the actor.
    """
    device = resolve_device(cfg.device)
    tsidm.to(device).eval()
    tsidm.requires_grad_(False)
    data = data.clone().to(device)
    data["next", "reward"] = cfg.dataset.reward_scale * data["next", "reward"] + cfg.dataset.reward_bias
    buffer = make_offline_replay_buffer(data, cfg.policy.batch_size, write_transforms=[TSIDMEncoderTransform(tsidm)],
                                        device=device)
    latent_dim = tsidm.latent_state_dim
    latent_stats = latent_statistics(tsidm, data["observation"], data["next", "observation"])
    latent_stats["data_action_std"] = data["action"].std(0).mean().item()
    print(f"latent scale: RMS spread {latent_stats['latent_rms']:.4g}, RMS step {latent_stats['latent_step_rms']:.4g}")
    torch.manual_seed(cfg.seed + 1000)  # the same networks whether stage 1 ran here or before a resume
    value_net = make_latent_value(latent_dim, cfg.value.num_cells).to(device)
    guide = make_guide_policy(latent_dim, cfg.guide.mode, cfg.guide.num_cells).to(device)
    value_loss = LatentExpectileLoss(value_net, expectile=cfg.value.expectile, check_inputs=False)
    value_loss.make_value_estimator(gamma=cfg.value.gamma)
    g = cfg.guide
    guide_loss = TSymGuideLoss(
        guide, value_net, tsidm, mode=g.mode, alpha=g.alpha, eta=g.eta, tsym_regularizer=g.tsym_regularizer,
        tsym_weight=g.tsym_weight, tsym_reference=latent_stats["latent_step_rms"] ** 2 if g.tsym_relative else None,
        reach_weight=g.reach_weight,
        max_weight=g.max_weight, dim_reduction=cfg.tsidm.dim_reduction, check_inputs=False,
    )
    guide_loss.make_value_estimator(gamma=cfg.value.gamma)
    actor_options = {"reencode_proposal": g.reencode_proposal, "inverse_dropout": g.act_with_dropout}
    compiled = compile_options(cfg)
    return Stage2(
        buffer=buffer,
        value_loss=value_loss,
        guide_loss=guide_loss,
        target_updater=SoftUpdate(value_loss, tau=cfg.value.target_update_rate),
        value_optim=capturable_adam(value_loss.value_network_params.values(True, True), lr=cfg.value.lr,
                                    capturable=compiled["cudagraphs"]),
        guide_optim=capturable_adam(guide_loss.parameters(), lr=g.lr, capturable=compiled["cudagraphs"]),
        actor=make_tels_actor(tsidm, guide, action_spec, **actor_options).to(device),
        guide=guide,
        actor_options=actor_options,
        latent_stats=latent_stats,
        device=device,
        amp=run_precision(cfg),
        compile=compiled,
    )


def score(task: Task, episode_return: float) -> float:
    """The D4RL normalized score where the task has reference scores, else the raw return."""
    return normalized_score(task, episode_return) if task.has_reference_scores else episode_return


def evaluate(cfg, actor, env, task: Task, step: int, latent_stats: dict,
             monitor: DeploymentMonitor | None = None) -> dict:
    """``eval.episodes`` deterministic episodes (seeded by run seed and step) and their diagnostics.

    Besides the returns and scores, records the guide's proposed latent step, how far the states
    reached fall from the proposals (``realized_error_ratio``, mean over the episodes where it is
    defined), the spread of the actions, and flags a frozen policy (:func:`~torchrl_tels.diagnostics.is_frozen`) or one whose
    proposals leave the data's step scale (:func:`~torchrl_tels.diagnostics.is_off_data`). With a
    calibrated ``monitor``, ``"monitor"`` holds its score at every step of every episode and the
    fraction of flagged steps.
    """
    actor.eval()
    returns, lengths, successes, behaviour, monitored = [], [], [], [], []
    for rollout in rollout_episodes(actor, env, cfg.eval.episodes, max_steps=cfg.eval.max_steps,
                                    seed=cfg.seed * 100_000 + step, compile_options=compile_options(cfg)):
        returns.append(rollout["next", "reward"].sum().item())
        lengths.append(rollout.shape[-1])
        successes.append(episode_success(rollout, task.success_steps))
        behaviour.append(rollout_statistics(rollout))
        if monitor is not None:
            monitored.append(rollout.select("observation", "action", ("next", "observation")))
    scores = [score(task, r) for r in returns]
    guide_step = sum(b["guide_step_rms"] for b in behaviour) / len(behaviour)
    action_std = sum(b["action_std"] for b in behaviour) / len(behaviour)
    realized = [b["realized_error_ratio"] for b in behaviour if math.isfinite(b["realized_error_ratio"])]
    result = {"step": step, "returns": returns, "lengths": lengths, "scores": scores,
              "score": sum(scores) / len(scores), "guide_step_rms": guide_step, "action_std": action_std,
              "realized_error_ratio": sum(realized) / len(realized) if realized else None,
              "frozen": is_frozen(guide_step, action_std, latent_stats["latent_step_rms"],
                                  latent_stats["data_action_std"]),
              "off_data": is_off_data(guide_step, latent_stats["latent_step_rms"]), **success_rate(successes)}
    if monitor is not None:
        result["monitor"] = monitor_record(monitor, monitored)
    return result


def after_training_diagnostics(cfg, stage2: "Stage2", data: TensorDictBase, task: Task) -> dict:
    """The readings ``results.json`` records: the latent scale, the action chain
    (:func:`~torchrl_tels.diagnostics.action_chain_statistics`) and the stochastic guide's weights, over at most
    ``diagnostics.max_transitions`` transitions (:func:`diagnostic_indices`)."""
    indices = diagnostic_indices(cfg, len(data))
    subset = data if indices is None else data[indices]
    return {**stage2.latent_stats, **action_chain_statistics(stage2.actor, subset),
            **guide_weight_diagnostics(cfg, stage2, task, indices),
            "diagnostic_transitions": len(subset)}


def guide_weight_diagnostics(cfg, stage2: "Stage2", task: Task, indices: torch.Tensor | None = None) -> dict:
    """For the stochastic guide (Eq. 10), ``{"awr_weights": ...}``: where its weights fall over the encoded
    data (``indices`` of it, or all; :func:`~torchrl_tels.diagnostics.awr_weight_statistics`), per maze cell
    on a maze task (the (x, y) columns ``dataset.delete_xy``); empty for the deterministic guide."""
    if cfg.guide.mode != "stochastic":
        return {}
    encoded = stage2.buffer.storage[:]
    encoded = encoded if indices is None else encoded[indices.to(encoded.device)]
    # Cells of D4RL's AntMaze frame (4-unit cells, the start cell at the origin): only its envs are in that frame.
    regions = (maze_cells(encoded["observation"][:, list(cfg.dataset.delete_xy)])
               if task.env_id == ANTMAZE_ENV_ID else None)
    return {"awr_weights": awr_weight_statistics(stage2.guide_loss, encoded, regions)}


def evaluation_scalars(evaluation: dict, prefix: str = "") -> dict[str, float]:
    """The scalars of one :func:`evaluate` record that a logger plots: the score and the behaviour diagnostics."""
    keys = ("score", "success_rate", "guide_step_rms", "realized_error_ratio", "action_std")
    return {f"{prefix}eval/{k}": float(evaluation[k]) for k in keys if evaluation.get(k) is not None}
