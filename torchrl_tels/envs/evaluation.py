"""Deterministic policy evaluation in a gymnasium env through TorchRL (paper §4 protocol)."""
from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, GymEnv, GymWrapper
from torchrl.envs.gym_like import default_info_dict_reader
from torchrl.envs.batched_envs import BatchedEnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_tels.compile import compile_update
from torchrl_tels.errors import TaskError

__all__ = ["episode_success", "evaluate_episodes", "make_eval_env", "make_eval_envs", "evaluate_policy",
           "success_rate", "rollout_episodes", "PolicyOnDevice"]


def _cannot_create(env_id: str, err: Exception) -> TaskError:
    return TaskError(f"cannot create the evaluation env {env_id!r}: {type(err).__name__}: {err}")


def make_eval_env(env_id: str, info_keys: tuple[str, ...] = (), **kwargs) -> GymEnv:
    """A TorchRL ``GymEnv`` for ``env_id`` (e.g. ``"Hopper-v4"``), with a clear error for unknown ids.

    The entries of ``info_keys`` that the env's ``info`` holds after a step (``"success"`` for the
    Adroit tasks: :attr:`~torchrl_tels.envs.Task.info_keys`) are written to each step's ``"next"``
    tensordict, as a batch of envs (:func:`make_eval_envs`) writes every info entry."""
    try:
        env = GymEnv(env_id, **kwargs)
    except Exception as err:
        raise _cannot_create(env_id, err) from None
    if info_keys:
        # Which entries the env's info has, from one step of the Gymnasium env; every evaluation
        # episode starts with a seeded reset, so this step changes none of them.
        with torch.random.fork_rng(devices=[]):  # the reader's dummy step draws: the caller's RNG stays as it was
            env._env.reset()
            _, _, _, _, info = env._env.step(env._env.action_space.sample())
            keys = [key for key in info_keys if key in info]
            if keys:
                env.set_info_dict_reader(default_info_dict_reader(keys))
    return env


def make_eval_envs(env_id: str, copies: int, wrap: Callable[[EnvBase], EnvBase] | None = None,
                   info_keys: tuple[str, ...] = ()) -> EnvBase:
    """``copies`` evaluation envs stepped together (batch size ``[copies]``), passed through ``wrap``
    (e.g. into a ``TransformedEnv``), or :func:`make_eval_env` itself when ``copies`` is 1.
    :func:`rollout_episodes` runs one episode on each copy, with one policy call per step for all of them.

    The copies are one Gymnasium ``SyncVectorEnv`` behind one TorchRL ``GymWrapper``: a batch step is
    one TorchRL step, where a ``SerialEnv`` of ``copies`` envs pays TorchRL's per-step overhead once per
    copy (BENCHMARKS.md, "Evaluation"). Gymnasium's ``SAME_STEP`` autoreset is the mode TorchRL's wrapper
    accepts; :func:`rollout_episodes` keeps each copy's first episode only."""
    if copies < 1:
        raise ValueError(f"make_eval_envs: copies must be >= 1, got {copies}.")
    if copies == 1:
        env = make_eval_env(env_id, info_keys=info_keys)
        return env if wrap is None else wrap(env)
    import gymnasium as gym

    eval_env_spaces(env_id)  # an unknown id fails here, with the clear error
    vector = gym.make_vec(env_id, num_envs=copies, vectorization_mode="sync",
                          vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP})
    # Building the wrapper (its dummy rollout reads the info specs) and the step below draw random
    # actions; on a forked stream, so that creating evaluation envs leaves the training RNG as it was.
    with torch.random.fork_rng(devices=[]):
        env = GymWrapper(vector)
        # one step, so that TorchRL's autoreset bookkeeping (VecGymEnvTransform) exists before the first
        # explicit full reset of rollout_episodes, which it cannot take before any step
        env.rand_step(env.reset())
    return env if wrap is None else wrap(env)


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
    compile_options: Mapping[str, Any] | None = None,
) -> Iterator[TensorDictBase]:
    """Yields the rollout TensorDict of each of ``episodes`` deterministic episodes.

    Episode ``i`` resets its env with seed ``seed + i``, so a given evaluation is
    reproducible whatever ran before it (a resumed run scores the same as an
    uninterrupted one). Each rollout stops at its first done.

    With a batch of ``k`` envs (:func:`make_eval_envs`), the episodes run ``k`` at a
    time and one policy call per step covers all of them, which is where evaluation
    spends its time; copy ``j`` is reset with the seed of its episode, so the episodes
    are one env's, up to the float rounding of a batched matrix product (which a
    chaotic body can amplify over a long episode). The policy may live on another
    device than the env: its inputs are moved to it and its outputs back
    (:class:`PolicyOnDevice`), whose policy call ``compile_options`` (the keywords of
    :func:`~torchrl_tels.compile.compile_update`) can compile or record as a CUDA graph.
    """
    env_device, policy_device = env.device or torch.device("cpu"), _device_of(policy)
    if policy_device != env_device and not isinstance(policy, PolicyOnDevice):
        policy = PolicyOnDevice(policy, policy_device, env_device, **(compile_options or {}))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        if not env.batch_size:
            for episode in range(episodes):
                env.set_seed(seed + episode)
                yield env.rollout(max_steps, policy, break_when_any_done=True)
            return
        copies = env.batch_size[0]
        for first in range(0, episodes, copies):
            # As set_seed of one env, copy by copy: reset with the episode's seed, then reset again.
            # A vector env's set_seed(s) seeds its copies s, s + 1, ...; a SerialEnv's does not, so it
            # gets each copy's seed explicitly.
            if isinstance(getattr(env, "base_env", env), BatchedEnvBase):
                env.reset(list_of_kwargs=[{"seed": seed + first + j} for j in range(copies)])
                start = env.reset()
            else:
                env.set_seed(seed + first)
                # every copy: a vector env's plain reset would only replay the copies that were done
                start = env.reset(TensorDict({"_reset": torch.ones(copies, 1, dtype=torch.bool)}, [copies]))
            batch = env.rollout(max_steps, policy, break_when_any_done=False, break_when_all_done=True,
                                auto_reset=False, tensordict=start)
            done = batch["next", "done"].reshape(copies, -1)
            for j in range(min(copies, episodes - first)):
                ends = done[j].nonzero()
                yield batch[j, : int(ends[0]) + 1 if len(ends) else done.shape[1]]


class PolicyOnDevice(TensorDictModuleBase):
    """Runs ``policy`` on ``device`` for an env on ``env_device``: each step's input goes to the policy's
    device and its output comes back.

    TorchRL's own ``rollout(auto_cast_to_device=True)`` does not bring the policy's output back to an env
    without a device (``env.device is None``, as Gymnasium envs are built here): it only clears the
    tensordict's device, the step's tensors stay on the GPU, and a batched rollout that stops when all
    copies are done then merges them with a done mask on the CPU ("Expected all tensors to be on the
    same device").

    Each step crosses between the devices once each way: the keys the policy reads travel as one
    consolidated tensordict (one copy), and so do the keys it writes. ``compile_options`` (the keywords of
    :func:`~torchrl_tels.compile.compile_update`) compile the policy call or record it as a CUDA graph,
    whose fixed input shape a batch of evaluation envs keeps for a whole rollout.
    """

    def __init__(self, policy: TensorDictModuleBase, device: torch.device, env_device: torch.device,
                 **compile_options: Any):
        super().__init__()
        self.policy, self.device, self.env_device = policy, torch.device(device), torch.device(env_device)
        self.in_keys, self.out_keys = list(policy.in_keys), list(policy.out_keys)
        self._act = compile_update(self._act_on_device, **compile_options)

    def _act_on_device(self, inputs: TensorDictBase) -> TensorDictBase:
        return self.policy(inputs).select(*self.out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # consolidate(): every key in one buffer, moved by one copy (and locked, so the policy's writes need unlock_)
        inputs = tensordict.select(*self.in_keys).consolidate().to(self.device).unlock_()
        outputs = self._act(inputs).consolidate().to(self.env_device)
        return tensordict.update(outputs).to(self.env_device)  # no copy: every tensor is there already


def _device_of(policy) -> torch.device:
    """Where the policy's parameters live (the CPU for a policy without any)."""
    parameter = next(iter(policy.parameters()), None) if hasattr(policy, "parameters") else None
    return parameter.device if parameter is not None else torch.device("cpu")


def episode_success(rollout: TensorDictBase, success_steps: int | None) -> bool | None:
    """Whether an episode succeeded by D4RL's criterion: the env's ``info["success"]`` on more than
    ``success_steps`` of its steps (Adroit: 25, pen: 20). ``None`` for a task without the criterion, or
    a rollout without the ``("next", "success")`` entry."""
    if success_steps is None or ("next", "success") not in rollout.keys(True):
        return None
    return int(rollout["next", "success"].sum()) > success_steps


def evaluate_episodes(
    policy: TensorDictModuleBase,
    env: EnvBase,
    episodes: int,
    *,
    seed: int,
    max_steps: int = 1000,
    success_steps: int | None = None,
) -> list[dict]:
    """``{"return", "length", "success"}`` of each of ``episodes`` deterministic episodes
    (:func:`rollout_episodes`); ``"success"`` is :func:`episode_success` (``None`` without a criterion)."""
    return [{"return": rollout["next", "reward"].sum().item(), "length": rollout.shape[-1],
             "success": episode_success(rollout, success_steps)}
            for rollout in rollout_episodes(policy, env, episodes, seed=seed, max_steps=max_steps)]


def success_rate(successes: list) -> dict:
    """``{"success_rate": ...}`` over episodes' :func:`episode_success`; empty where any is ``None``."""
    if not successes or any(s is None for s in successes):
        return {}
    return {"success_rate": sum(successes) / len(successes)}


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
    results = evaluate_episodes(policy, env, episodes, seed=seed, max_steps=max_steps)
    returns, lengths = [r["return"] for r in results], [r["length"] for r in results]
    return (returns, lengths) if with_lengths else returns
