"""Recording Minari datasets from a Gymnasium environment and a policy.

Minari's :class:`~minari.DataCollector` needs jax (its episode buffers use
``jax.tree_util``). This module steps the environment itself, stacks each
episode into numpy arrays and writes them with
:func:`minari.create_dataset_from_buffers`, which does not.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from torchrl_tels.envs.robotics import maze_files_removed

__all__ = ["collect_minari_dataset"]

#: A policy maps one (numpy, possibly dict) observation to one action.
Policy = Callable[[Any], Any]


def _stack(steps: list[Any]) -> Any:
    """Stack per-step values, keeping dict/tuple observation structure."""
    first = steps[0]
    if isinstance(first, Mapping):
        return {key: _stack([step[key] for step in steps]) for key in first}
    if isinstance(first, tuple):
        return tuple(_stack([step[i] for step in steps]) for i in range(len(first)))
    return np.stack([np.asarray(step) for step in steps])


def _numpy_policy(policy: Any) -> Policy:
    """Adapt a TorchRL/torch actor so it maps numpy observations to numpy actions."""
    from tensordict import TensorDict
    from tensordict.nn import TensorDictModuleBase

    if isinstance(policy, TensorDictModuleBase):

        @torch.no_grad()
        def act(observation: np.ndarray) -> np.ndarray:
            # The TorchRL convention: the actor reads "observation" and writes "action".
            inputs = TensorDict(
                observation=torch.as_tensor(observation, dtype=torch.float32)
            )
            return policy(inputs).get("action").cpu().numpy()

        return act
    return policy


def write_minari_dataset(dataset_id: str, episodes: list, env, eval_env=None, **dataset_metadata):
    """``minari.create_dataset_from_buffers`` without its warnings about optional metadata left empty."""
    import minari

    with warnings.catch_warnings():
        # The caller can set these fields through **dataset_metadata.
        warnings.filterwarnings(
            "ignore",
            message=r"`(code_permalink|author|author_email|eval_env)` is set to",
            category=UserWarning,
        )
        return minari.create_dataset_from_buffers(
            dataset_id, episodes, env=env, eval_env=eval_env, **dataset_metadata
        )


def prepare_minari_dataset_id(dataset_id: str, action_noise: float, overwrite: bool) -> None:
    """Checks the noise level and frees ``dataset_id`` (only with ``overwrite``) before a collection."""
    import minari

    if action_noise < 0:
        raise ValueError(f"action_noise must be >= 0, got {action_noise}.")
    if dataset_id in minari.list_local_datasets():
        if not overwrite:
            raise ValueError(
                f"A local Minari dataset {dataset_id!r} already exists; pass "
                "overwrite=True to replace it."
            )
        minari.delete_dataset(dataset_id)


def collect_minari_dataset(
    env_id: str,
    dataset_id: str,
    policy: Policy | None = None,
    n_episodes: int | None = None,
    n_steps: int | None = None,
    seed: int = 0,
    action_noise: float = 0.0,
    *,
    env_kwargs: Mapping[str, Any] | None = None,
    overwrite: bool = False,
    **dataset_metadata: Any,
):
    """Roll out a policy in a Gymnasium environment and save a Minari dataset.

    Episode ``i`` starts with ``env.reset(seed=seed + i)`` (its seed is stored
    in the dataset) and runs until the environment terminates or truncates it.
    With ``n_steps``, collection stops after exactly that many steps; an
    episode cut short there gets ``truncations[-1] = True``, so every stored
    episode ends with a termination or a truncation.

    Args:
        env_id: Gymnasium environment id, e.g. ``"Hopper-v4"``.
        dataset_id: Minari id to write under ``MINARI_DATASETS_PATH``, e.g.
            ``"local/hopper/random-v0"``.
        policy: callable mapping one observation (as returned by the
            environment) to one action, or a TorchRL actor
            (:class:`~tensordict.nn.TensorDictModuleBase` reading
            ``"observation"`` and writing ``"action"``). ``None`` samples
            uniform random actions from the action space, seeded by ``seed``.
        n_episodes: number of whole episodes to record.
        n_steps: number of steps to record. Exactly one of ``n_episodes`` and
            ``n_steps`` must be given.
        seed: seed of the resets, of the random policy and of the action noise.
        action_noise: standard deviation of Gaussian noise added to the
            policy's actions (continuous action spaces only), clipped to the
            action bounds. The recorded action is the noisy one.

    Keyword Args:
        env_kwargs: keyword arguments for :func:`gymnasium.make`.
        overwrite: delete an existing local dataset with the same id first.
        **dataset_metadata: forwarded to
            :func:`minari.create_dataset_from_buffers` (``author``,
            ``code_permalink``, ``description``, ``eval_env``, ...).

    Returns:
        The new :class:`minari.MinariDataset`.

    Raises:
        ValueError: bad episode/step counts, negative noise, noise on a
            non-continuous action space, or an existing dataset without
            ``overwrite``.
    """
    if (n_episodes is None) == (n_steps is None):
        raise ValueError("Give exactly one of n_episodes and n_steps.")
    limit = n_episodes if n_episodes is not None else n_steps
    if limit is None or limit <= 0:
        raise ValueError(f"n_episodes/n_steps must be positive, got {limit}.")
    prepare_minari_dataset_id(dataset_id, action_noise, overwrite)

    with maze_files_removed():  # a Gymnasium-Robotics maze would leave its model file behind
        env = gym.make(env_id, **dict(env_kwargs or {}))
    action_space = env.action_space
    if action_noise > 0 and not isinstance(action_space, gym.spaces.Box):
        env.close()
        raise ValueError(
            f"action_noise needs a continuous (Box) action space, {env_id} has "
            f"{action_space}."
        )
    action_space.seed(seed)
    noise_rng = np.random.default_rng(seed)
    act = _numpy_policy(policy) if policy is not None else None

    from minari.data_collector.episode_buffer import EpisodeBuffer

    episodes: list[EpisodeBuffer] = []
    total_steps = 0
    try:
        while True:
            if n_episodes is not None and len(episodes) == n_episodes:
                break
            if n_steps is not None and total_steps == n_steps:
                break
            episode_seed = seed + len(episodes)
            observation, _ = env.reset(seed=episode_seed)
            observations, actions, rewards = [observation], [], []
            terminations, truncations = [], []
            while True:
                if act is None:
                    action = action_space.sample()
                else:
                    action = act(observation)
                    if isinstance(action, torch.Tensor):
                        action = action.detach().cpu().numpy()
                    action = np.asarray(action, dtype=action_space.dtype)
                if action_noise > 0:
                    noisy = action + noise_rng.normal(0.0, action_noise, action.shape)
                    action = np.clip(noisy, action_space.low, action_space.high)
                    action = action.astype(action_space.dtype)
                observation, reward, terminated, truncated, _ = env.step(action)
                total_steps += 1
                out_of_steps = n_steps is not None and total_steps == n_steps
                observations.append(observation)
                actions.append(action)
                rewards.append(float(reward))
                terminations.append(bool(terminated))
                # Collection ending mid-episode is a time-limit-like cut.
                truncations.append(bool(truncated) or (out_of_steps and not terminated))
                if terminated or truncated or out_of_steps:
                    break
            episodes.append(
                EpisodeBuffer(
                    id=len(episodes),
                    seed=episode_seed,
                    observations=_stack(observations),
                    actions=_stack(actions),
                    rewards=np.asarray(rewards, dtype=np.float64),
                    terminations=np.asarray(terminations, dtype=bool),
                    truncations=np.asarray(truncations, dtype=bool),
                    infos={},
                )
            )

        policy_name = (
            "random"
            if policy is None
            else getattr(policy, "__name__", type(policy).__name__)
        )
        dataset_metadata.setdefault(
            "algorithm_name",
            policy_name + (f" + N(0, {action_noise}^2) noise" if action_noise else ""),
        )
        dataset_metadata.setdefault(
            "description",
            f"{len(episodes)} episodes ({total_steps} steps) of {env_id} recorded "
            f"with policy {policy_name!r}, seed {seed}, by torchrl_tels.",
        )
        return write_minari_dataset(dataset_id, episodes, env, **dataset_metadata)
    finally:
        env.close()
