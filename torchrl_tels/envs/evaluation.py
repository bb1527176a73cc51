"""Deterministic policy evaluation in a gymnasium env through TorchRL (paper §4 protocol)."""
from __future__ import annotations

from collections.abc import Iterator

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, GymEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_tels.errors import TaskError

__all__ = ["make_eval_env", "evaluate_policy", "rollout_episodes"]


def _cannot_create(env_id: str, err: Exception) -> TaskError:
    return TaskError(f"cannot create the evaluation env {env_id!r}: {type(err).__name__}: {err}")


def make_eval_env(env_id: str, **kwargs) -> GymEnv:
    """A TorchRL ``GymEnv`` for ``env_id`` (e.g. ``"Hopper-v4"``), with a clear error for unknown ids."""
    try:
        return GymEnv(env_id, **kwargs)
    except Exception as err:
        raise _cannot_create(env_id, err) from None


def eval_env_spaces(env_id: str):
    """``(observation_space, action_space)`` of the Gymnasium env ``env_id``, checked without building a
    TorchRL env; the same clear error as :func:`make_eval_env` for an id that cannot be built."""
    import gymnasium as gym

    try:
        env = gym.make(env_id)
    except Exception as err:
        raise _cannot_create(env_id, err) from None
    spaces = env.observation_space, env.action_space
    env.close()
    return spaces


@torch.no_grad()
def rollout_episodes(
    policy: TensorDictModuleBase,
    env: EnvBase,
    episodes: int,
    *,
    seed: int,
    max_steps: int = 1000,
) -> Iterator[TensorDictBase]:
    """Yields the rollout TensorDict of each of ``episodes`` deterministic episodes.

    Episode ``i`` resets the env with seed ``seed + i``, so a given
    evaluation is reproducible whatever ran before it (a resumed run scores
    the same as an uninterrupted one). Each rollout stops at the first done.
    """
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for episode in range(episodes):
            env.set_seed(seed + episode)
            yield env.rollout(max_steps, policy, break_when_any_done=True)


def evaluate_policy(
    policy: TensorDictModuleBase,
    env: EnvBase,
    episodes: int,
    *,
    seed: int,
    max_steps: int = 1000,
    with_lengths: bool = False,
) -> list[float] | tuple[list[float], list[int]]:
    """Undiscounted returns of ``episodes`` deterministic episodes (and their lengths if ``with_lengths``).

    The episodes are those of :func:`rollout_episodes` with the same arguments.
    """
    returns, lengths = [], []
    for rollout in rollout_episodes(policy, env, episodes, seed=seed, max_steps=max_steps):
        returns.append(rollout["next", "reward"].sum().item())
        lengths.append(rollout.shape[-1])
    return (returns, lengths) if with_lengths else returns
