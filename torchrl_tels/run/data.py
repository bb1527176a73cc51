"""A run's data: the training transitions and the task they are evaluated on, validated before anything is
written, and what follows from their size (stage 1's length, the plan, the diagnostics' subset)."""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Sequence

import torch
from tensordict import TensorDictBase

from torchrl_tels.config import DatasetSpec, RunSpec, TSIDMSpec
from torchrl_tels.data import delete_regions, load_dataset, subset_dataset
from torchrl_tels.data.datasets import recorded_env_id
from torchrl_tels.envs import get_task, Task
from torchrl_tels.envs.evaluation import eval_env_spaces
from torchrl_tels.errors import DatasetError, TaskError

__all__ = ["check_same_stage1_length", "diagnostic_indices", "make_data", "print_plan", "resolve_task", "tsidm_steps"]


def tsidm_steps(tsidm: TSIDMSpec, n_transitions: int) -> int:
    """Stage 1's length: ``tsidm.steps``, or ``tsidm.epochs`` passes over the data (Table 10)."""
    return tsidm.steps or tsidm.epochs * math.ceil(n_transitions / tsidm.batch_size)


def check_same_stage1_length(tsidm: TSIDMSpec, datas: Sequence, seeds: Sequence[int]) -> int:
    """Stage 1's length, shared by every seed of a ``seeds`` run; a :class:`DatasetError` if their subsets differ."""
    totals = {tsidm_steps(tsidm, len(data)) for data in datas}
    if len(totals) > 1:
        raise DatasetError(f"seeds {list(seeds)}: their data subsets give stage 1 different lengths {sorted(totals)}; "
                           f"set tsidm.steps to train every seed as long.")
    return totals.pop()


def print_plan(spec: RunSpec, n_transitions: int) -> None:
    """Says, before anything trains, how long each stage will run; warns when an epoch budget on a large set
    means a stage 1 of more than ``tsidm.warn_steps`` steps (Table 10's 1000 epochs were set for 10k sets)."""
    t = spec.tsidm
    stage1 = 0 if t.checkpoint else tsidm_steps(t, n_transitions)
    candidates = len(t.beta_candidates) if t.beta == "auto" and not t.checkpoint else 1
    how = ("the TS-IDM of tsidm.checkpoint" if t.checkpoint else "from tsidm.steps" if t.steps
           else f"{t.epochs} epochs of {n_transitions} transitions")
    print(f"plan: stage 1 {stage1 * candidates} TS-IDM steps ({how}"
          + (f", {candidates} beta candidates" if candidates > 1 else "") + f"), stage 2 {spec.policy.steps} policy "
          f"steps, an evaluation of {spec.eval.episodes} episodes every {spec.eval.interval} steps; batch "
          f"{t.batch_size}/{spec.policy.batch_size}")
    if t.warn_steps and not t.steps and stage1 > t.warn_steps:
        print(f"warning: tsidm.epochs={t.epochs} on {n_transitions} transitions is {stage1} TS-IDM steps, "
              f"past tsidm.warn_steps={t.warn_steps}; set tsidm.steps to bound stage 1 (BENCHMARKS.md, data size).",
              file=sys.stderr)


def diagnostic_indices(spec: RunSpec, n_transitions: int) -> torch.Tensor | None:
    """The transitions the after-training readings average over: a random subset of ``diagnostics.max_transitions``
    (seeded by the run's seed), or ``None`` for all of them when the data is no larger."""
    limit = spec.diagnostics.max_transitions
    if limit is None or n_transitions <= limit:
        return None
    generator = torch.Generator().manual_seed(int(spec.seed))
    return torch.randperm(n_transitions, generator=generator)[:limit].sort().values


def resolve_task(dataset: DatasetSpec, source: str) -> Task:
    """The evaluation task: ``dataset.task`` or the dataset's name, else the env the dataset recorded.

    A Minari dataset records its environment, so a user's own data trains
    without a registered task; it then has no reference scores, and its
    results are raw returns.
    """
    name = dataset.task or Path(str(dataset.name)).stem
    try:
        return get_task(name)
    except TaskError:
        env_id = None if dataset.task else recorded_env_id(source)
        if env_id is None:
            raise
        return Task(str(dataset.name), env_id, None, None, None, None)


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


def make_data(spec: RunSpec) -> tuple[TensorDictBase, Task]:
    """The training transitions and their evaluation task, validated (nothing is written)."""
    d = spec.dataset
    name = str(d.name)
    data = load_dataset(name)
    if d.size:
        data = subset_dataset(data, int(d.size), seed=spec.seed, mode=d.subset)
    if d.delete_boxes:
        if max(d.delete_xy) >= data["observation"].shape[-1]:
            raise DatasetError(f"dataset.delete_xy={list(d.delete_xy)} names a column beyond the "
                               f"{data['observation'].shape[-1]} observation columns of {name!r}.")
        # Fig. 3's OOD test: the same seed removes the same transitions for every method.
        before = len(data)
        data = delete_regions(data, [tuple(box) for box in d.delete_boxes], d.delete_ratio,
                              seed=spec.seed, xy_slice=list(d.delete_xy))
        print(f"dataset.delete_boxes: deleted {before - len(data)} of {before} transitions, {len(data)} left")
    task = resolve_task(d, name)
    _check_fits_env(data, task, name)
    for path, batch_size in (("tsidm.batch_size", spec.tsidm.batch_size), ("policy.batch_size", spec.policy.batch_size)):
        if batch_size > len(data):
            raise DatasetError(f"dataset {name!r} has {len(data)} transitions, fewer than {path}={batch_size}.")
    return data, task
