"""Acting by Eq. (11): deterministic evaluation episodes with the diagnostics of a frozen policy, and the readings
``results.json`` records after training."""
from __future__ import annotations

import dataclasses
import math

import torch
from tensordict import TensorDictBase

from torchrl_tels.config import CompileSpec, EvalSpec, RunSpec
from torchrl_tels.diagnostics import (action_chain_statistics, awr_weight_statistics, is_frozen, is_off_data,
                                     maze_cells, rollout_statistics)
from torchrl_tels.envs import DeploymentMonitor, normalized_score, rollout_episodes, Task
from torchrl_tels.envs.antmaze import ENV_IDS as ANTMAZE_ENV_IDS
from torchrl_tels.envs.evaluation import episode_success, success_rate
from torchrl_tels.monitor import monitor_record
from torchrl_tels.run.data import diagnostic_indices
from torchrl_tels.run.stage2 import SeedStage2

__all__ = ["after_training_diagnostics", "evaluate", "evaluation_scalars", "guide_weight_diagnostics", "score"]


def score(task: Task, episode_return: float) -> float:
    """The D4RL normalized score where the task has reference scores, else the raw return."""
    return normalized_score(task, episode_return) if task.has_reference_scores else episode_return


def evaluate(actor, env, task: Task, step: int, latent_stats: dict, *, eval: EvalSpec, seed: int,
             compile: CompileSpec = CompileSpec(), monitor: DeploymentMonitor | None = None) -> dict:
    """``eval.episodes`` deterministic episodes (seeded by the run's ``seed`` and ``step``) and their diagnostics.

    Besides the returns and scores, records the guide's proposed latent step, how far the states
    reached fall from the proposals (``realized_error_ratio``, mean over the episodes where it is
    defined), the spread of the actions, and flags a frozen policy (:func:`~torchrl_tels.diagnostics.is_frozen`)
    or one whose proposals leave the data's step scale (:func:`~torchrl_tels.diagnostics.is_off_data`). With a
    calibrated ``monitor``, ``"monitor"`` holds its score at every step of every episode and the
    fraction of flagged steps.
    """
    actor.eval()
    returns, lengths, successes, behaviour, monitored = [], [], [], [], []
    for rollout in rollout_episodes(actor, env, eval.episodes, max_steps=eval.max_steps, seed=seed * 100_000 + step,
                                    compile_options=dataclasses.asdict(compile)):
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


def evaluation_scalars(evaluation: dict, prefix: str = "") -> dict[str, float]:
    """The scalars of one :func:`evaluate` record that a logger plots: the score and the behaviour diagnostics."""
    keys = ("score", "success_rate", "guide_step_rms", "realized_error_ratio", "action_std")
    return {f"{prefix}eval/{k}": float(evaluation[k]) for k in keys if evaluation.get(k) is not None}


def after_training_diagnostics(spec: RunSpec, stage: SeedStage2, data: TensorDictBase, task: Task) -> dict:
    """The readings ``results.json`` records: the latent scale, the action chain
    (:func:`~torchrl_tels.diagnostics.action_chain_statistics`) and the stochastic guide's weights, over at most
    ``diagnostics.max_transitions`` transitions (:func:`~torchrl_tels.run.data.diagnostic_indices`)."""
    indices = diagnostic_indices(spec, len(data))
    subset = data if indices is None else data[indices]
    return {**stage.latent_stats, **action_chain_statistics(stage.actor, subset),
            **guide_weight_diagnostics(spec, stage, task, indices),
            "diagnostic_transitions": len(subset)}


def guide_weight_diagnostics(spec: RunSpec, stage: SeedStage2, task: Task,
                             indices: torch.Tensor | None = None) -> dict:
    """For the stochastic guide (Eq. 10), ``{"awr_weights": ...}``: where its weights fall over the encoded
    data (``indices`` of it, or all; :func:`~torchrl_tels.diagnostics.awr_weight_statistics`), per maze cell
    on a D4RL AntMaze task (the (x, y) columns ``dataset.delete_xy``); empty for the deterministic guide."""
    if spec.guide.mode != "stochastic":
        return {}
    encoded = stage.buffer.storage[:]
    encoded = encoded if indices is None else encoded[indices.to(encoded.device)]
    # Cells of D4RL's AntMaze frame (4-unit cells, the start cell at the origin): only its envs are in that frame.
    regions = (maze_cells(encoded["observation"][:, list(spec.dataset.delete_xy)])
               if task.env_id in ANTMAZE_ENV_IDS.values() else None)
    return {"awr_weights": awr_weight_statistics(stage.guide_loss, encoded, regions)}
