"""Deterministic policy evaluation in a gymnasium env through TorchRL (paper §4 protocol)."""
from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, GymEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from torchrl_tels.errors import TaskError

__all__ = ["make_eval_env", "make_eval_envs", "evaluate_policy", "rollout_episodes"]


def _cannot_create(env_id: str, err: Exception) -> TaskError:
    return TaskError(f"cannot create the evaluation env {env_id!r}: {type(err).__name__}: {err}")


def make_eval_env(env_id: str, **kwargs) -> GymEnv:
    """A TorchRL ``GymEnv`` for ``env_id`` (e.g. ``"Hopper-v4"``), with a clear error for unknown ids."""
    try:
        return GymEnv(env_id, **kwargs)
    except Exception as err:
        raise _cannot_create(env_id, err) from None


def make_eval_envs(env_id: str, copies: int, wrap: Callable[[EnvBase], EnvBase] | None = None) -> list[EnvBase]:
    """``copies`` evaluation envs that :func:`rollout_episodes` steps together, each a
    :func:`make_eval_env` passed through ``wrap`` (e.g. into a ``TransformedEnv``)."""
    if copies < 1:
        raise ValueError(f"make_eval_envs: copies must be >= 1, got {copies}.")
    return [make_eval_env(env_id) if wrap is None else wrap(make_eval_env(env_id)) for _ in range(copies)]


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
    env: EnvBase | Sequence[EnvBase],
    episodes: int,
    *,
    seed: int,
    max_steps: int = 1000,
) -> Iterator[TensorDictBase]:
    """Yields the rollout TensorDict of each of ``episodes`` deterministic episodes.

    Episode ``i`` resets its env with seed ``seed + i``, so a given evaluation is
    reproducible whatever ran before it (a resumed run scores the same as an
    uninterrupted one). Each rollout stops at its first done.

    ``env`` may be a list of ``k`` copies of one env (:func:`make_eval_envs`): the
    episodes then run ``k`` at a time in lockstep, and one policy call per step covers
    every episode still running, which is where evaluation spends its time. Episode ``i``
    runs on copy ``i % k`` with the same seed, so the episodes are one env's, up to the
    float rounding of a batched matrix product (which a chaotic body can amplify over a
    long episode).
    """
    envs = [env] if isinstance(env, EnvBase) else list(env)
    device = _device_of(policy)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        if len(envs) == 1:
            for episode in range(episodes):
                envs[0].set_seed(seed + episode)
                yield envs[0].rollout(max_steps, policy, break_when_any_done=True,
                                      auto_cast_to_device=device.type != "cpu")
            return
        for first in range(0, episodes, len(envs)):
            group = envs[: min(len(envs), episodes - first)]
            yield from _lockstep_rollouts(policy, group, seed + first, max_steps, device)


def _device_of(policy) -> torch.device:
    """Where the policy's parameters live (the CPU for a policy without any)."""
    parameter = next(iter(policy.parameters()), None) if hasattr(policy, "parameters") else None
    return parameter.device if parameter is not None else torch.device("cpu")


def _lockstep_rollouts(policy, envs: list[EnvBase], seed: int, max_steps: int,
                       device: torch.device) -> list[TensorDictBase]:
    """One episode per env, env ``j`` seeded ``seed + j``, each stepped as ``EnvBase.rollout``
    steps one env: the policy writes into the current tensordict, the env steps it, and the
    episode ends at its first done. Only the policy's inputs are stacked for its one call."""
    for j, env in enumerate(envs):
        env.set_seed(seed + j)
    current = [env.reset() for env in envs]
    steps: list[list[TensorDictBase]] = [[] for _ in envs]
    running = list(range(len(envs)))
    for _ in range(max_steps):
        inputs = TensorDict({key: torch.stack([current[j].get(key) for j in running]) for key in policy.in_keys},
                            batch_size=[len(running)])
        outputs = policy(inputs.to(device)).exclude(*policy.in_keys).to(current[running[0]].device or "cpu")
        still_running = []
        for row, j in enumerate(running):
            stepped = envs[j].step(current[j].update(outputs[row]))
            steps[j].append(stepped.copy())
            if not stepped["next", "done"].any():
                still_running.append(j)
                current[j] = step_mdp(stepped, keep_other=True)
        running = still_running
        if not running:
            break
    return [torch.stack(episode) for episode in steps]


def evaluate_policy(
    policy: TensorDictModuleBase,
    env: EnvBase | Sequence[EnvBase],
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
