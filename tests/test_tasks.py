"""Task registry and D4RL normalized scores."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import torchrl_tels.envs.tasks as tasks_module
from torchrl_tels.data import load_dataset
from torchrl_tels.envs import get_task, list_tasks, normalized_score, register_task, Task


# Gymnasium flags the v4 MuJoCo tasks as old; they are the ones D4RL v2 matches.
pytestmark = pytest.mark.filterwarnings("ignore:.*is out of date:DeprecationWarning")


@pytest.fixture
def clean_registry(monkeypatch):
    """Let a test register tasks without leaking them to other tests."""
    monkeypatch.setattr(tasks_module, "_TASKS", dict(tasks_module._TASKS))


@pytest.mark.parametrize(
    "name, env_id, ref_min, ref_max, obs_dim, act_dim",
    [
        ("hopper-medium-v2", "Hopper-v4", -20.272305, 3234.3, 11, 3),
        ("hopper-medium-replay-v2", "Hopper-v4", -20.272305, 3234.3, 11, 3),
        ("halfcheetah-medium-v2", "HalfCheetah-v4", -280.178953, 12135.0, 17, 6),
        ("walker2d-medium-v2", "Walker2d-v4", 1.629008, 4592.3, 17, 6),
        ("antmaze-umaze-v0", "torchrl_tels/AntMazeUMazeD4RL-v0", 0.0, 1.0, 29, 8),
        ("mujoco/hopper/medium-v0", "Hopper-v5", -20.272305, 3234.3, 11, 3),
        ("mujoco/walker2d/expert-v0", "Walker2d-v5", 1.629008, 4592.3, 17, 6),
        ("D4RL/antmaze/umaze-v1", "torchrl_tels/AntMazeUMazeFixed-v0", 0.0, 1.0, 31, 8),
    ],
)
def test_registered_tasks(name, env_id, ref_min, ref_max, obs_dim, act_dim):
    task = get_task(name)
    assert task.name == name and task.dataset == name
    assert task.env_id == env_id
    assert (task.ref_min_score, task.ref_max_score) == (ref_min, ref_max)
    assert (task.observation_dim, task.action_dim) == (obs_dim, act_dim)


def test_subset_suffix_and_case():
    task = get_task("hopper-medium-v2-10k")
    assert task.name == task.dataset == "hopper-medium-v2-10k"
    assert task.env_id == "Hopper-v4" and task.ref_max_score == 3234.3
    assert get_task("walker2d-medium-v2-5k").env_id == "Walker2d-v4"
    assert get_task("Hopper-Medium-V2").env_id == "Hopper-v4"


def test_unknown_task_lists_known_ones():
    with pytest.raises(ValueError) as info:
        get_task("pong-medium-v2")
    message = str(info.value)
    assert "Unknown task 'pong-medium-v2'" in message
    for known in ("hopper-medium-v2", "walker2d-medium-v2", "mujoco/hopper/medium-v0"):
        assert known in message
    with pytest.raises(ValueError, match="Unknown task 'pong-medium-v2-10k'"):
        get_task("pong-medium-v2-10k")


@pytest.mark.parametrize("env_family", ["Hopper", "HalfCheetah", "Walker2d"])
def test_mujoco_task_dims_match_env(env_family):
    task = get_task(f"{env_family.lower()}-medium-v2")
    env = gym.make(task.env_id)
    try:
        assert env.observation_space.shape == (task.observation_dim,)
        assert env.action_space.shape == (task.action_dim,)
        assert env.spec.max_episode_steps == task.max_episode_steps
    finally:
        env.close()


@pytest.mark.parametrize(
    "name",
    [
        "hopper-medium-v2-10k",
        "halfcheetah-medium-v2-10k",
        "walker2d-medium-v2-10k",
        "hopper-medium-replay-v2-10k",
        "antmaze-umaze-v0-10k",
    ],
)
def test_task_dims_match_shipped_data(name):
    task = get_task(name)
    data = load_dataset(task.dataset)
    assert data["observation"].shape[-1] == task.observation_dim
    assert data["action"].shape[-1] == task.action_dim


def test_normalized_score_hand_computed():
    # 100 * (1000 + 20.272305) / (3234.3 + 20.272305) = 31.348890...
    assert normalized_score("hopper-medium-v2", 1000.0) == pytest.approx(
        31.3488904, abs=1e-6
    )
    # 100 * (4000 + 280.178953) / (12135 + 280.178953) = 34.475370...
    assert normalized_score(get_task("halfcheetah-medium-v2"), 4000.0) == pytest.approx(
        34.4753706, abs=1e-6
    )
    # 100 * (2000 - 1.629008) / (4592.3 - 1.629008) = 43.531130...
    assert normalized_score("walker2d-medium-v2-10k", 2000.0) == pytest.approx(
        43.5311308, abs=1e-6
    )
    assert normalized_score("antmaze-umaze-v0", 0.5) == pytest.approx(50.0)
    assert normalized_score("hopper-medium-v2", -20.272305) == pytest.approx(0.0)
    assert normalized_score("hopper-medium-v2", 3234.3) == pytest.approx(100.0)


def test_normalized_score_arrays_and_tensors():
    returns = np.array([-20.272305, 3234.3])
    np.testing.assert_allclose(
        normalized_score("hopper-medium-v2", returns), [0.0, 100.0]
    )
    scores = normalized_score("antmaze-umaze-v0", torch.tensor([0.0, 0.25, 1.0]))
    assert isinstance(scores, torch.Tensor)
    torch.testing.assert_close(scores, torch.tensor([0.0, 25.0, 100.0]))


def test_register_task(clean_registry):
    task = Task(
        "pendulum-random-v0",
        "Pendulum-v1",
        -1500.0,
        -150.0,
        3,
        1,
        max_episode_steps=200,
    )
    assert task.dataset == "pendulum-random-v0"
    register_task(task, aliases=["local/pendulum/random-v0"])
    assert get_task("pendulum-random-v0") is task
    alias = get_task("local/pendulum/random-v0")
    assert alias.env_id == "Pendulum-v1" and alias.dataset == "pendulum-random-v0"
    assert "pendulum-random-v0" in list_tasks()
    assert normalized_score("pendulum-random-v0", -825.0) == pytest.approx(50.0)
    assert get_task("pendulum-random-v0-20k").dataset == "pendulum-random-v0-20k"

    with pytest.raises(
        ValueError, match=r"\['pendulum-random-v0'\] already registered"
    ):
        register_task(task)
    replacement = Task("pendulum-random-v0", "Pendulum-v1", -1200.0, 0.0, 3, 1)
    register_task(replacement, overwrite=True)
    assert get_task("pendulum-random-v0").ref_min_score == -1200.0


def test_register_task_leaves_no_trace():
    assert "pendulum-random-v0" not in list_tasks()


def test_task_rejects_bad_reference_scores():
    with pytest.raises(ValueError, match="must be greater than ref_min_score"):
        Task("bad-v0", "Pendulum-v1", 10.0, 10.0, 3, 1)


def test_rollout_episodes_are_the_evaluated_episodes():
    """evaluate_policy's returns are the reward sums of rollout_episodes' episodes, seeded per episode."""
    from tensordict.nn import TensorDictModule
    from torchrl.envs import DoubleToFloat, TransformedEnv

    from torchrl_tels.envs import evaluate_policy, make_eval_env, rollout_episodes

    # Pendulum draws its start from the reset seed; a fixed feedback law keeps the policy deterministic.
    env = TransformedEnv(make_eval_env("Pendulum-v1"), DoubleToFloat())
    policy = TensorDictModule(lambda obs: (-obs[..., 1:2]).clamp(-2, 2), in_keys=["observation"], out_keys=["action"])
    rollouts = list(rollout_episodes(policy, env, 3, seed=7, max_steps=50))
    returns, lengths = evaluate_policy(policy, env, 3, seed=7, max_steps=50, with_lengths=True)
    assert returns == [r["next", "reward"].sum().item() for r in rollouts]
    assert lengths == [r.shape[-1] for r in rollouts]
    # Episode i is reset with seed + i: the second episode of seed 7 is the first of seed 8.
    again = next(rollout_episodes(policy, env, 1, seed=8, max_steps=50))
    torch.testing.assert_close(again["observation"], rollouts[1]["observation"])
    assert not torch.equal(rollouts[0]["observation"][0], rollouts[1]["observation"][0])


def test_batched_rollouts_are_the_sequential_episodes():
    """A batch of envs runs episode i with seed + i, as one env does: with a policy whose rows do not
    interact (no matrix product to round differently), every episode is bitwise the same, including
    where each one ends and its last next-observation."""
    from tensordict.nn import TensorDictModule
    from torchrl.envs import DoubleToFloat, TransformedEnv

    from torchrl_tels.envs import make_eval_env, make_eval_envs, rollout_episodes

    # Hopper ends its episodes at different steps; 5 episodes on 3 copies leave a partial last batch.
    policy = TensorDictModule(lambda obs: (0.5 * obs[..., 2:5]).clamp(-1, 1), in_keys=["observation"],
                              out_keys=["action"])
    one = TransformedEnv(make_eval_env("Hopper-v4"), DoubleToFloat())
    batch = make_eval_envs("Hopper-v4", 3, wrap=lambda env: TransformedEnv(env, DoubleToFloat()))
    sequential = list(rollout_episodes(policy, one, 5, seed=11, max_steps=300))
    batched = list(rollout_episodes(policy, batch, 5, seed=11, max_steps=300))
    assert len(batched) == 5
    lengths = [r.shape[-1] for r in sequential]
    assert len(set(lengths)) > 1 and max(lengths) < 300  # the episodes end, and not together
    assert [r.shape[-1] for r in batched] == lengths
    for seq, bat in zip(sequential, batched):
        for key in ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done")):
            assert torch.equal(seq[key], bat[key]), key


def test_batched_evaluation_matches_sequential_with_a_network_policy():
    """With an MLP, the batched product rounds differently; over a short horizon the returns agree
    within float tolerance."""
    from tensordict.nn import TensorDictModule
    from torchrl.envs import DoubleToFloat, TransformedEnv
    from torchrl.modules import MLP

    from torchrl_tels.envs import evaluate_policy, make_eval_env, make_eval_envs

    torch.manual_seed(0)
    net = torch.nn.Sequential(MLP(in_features=3, out_features=1, num_cells=[64, 64]), torch.nn.Tanh())
    policy = TensorDictModule(lambda obs: 2 * net(obs), in_keys=["observation"], out_keys=["action"])
    one = TransformedEnv(make_eval_env("Pendulum-v1"), DoubleToFloat())
    batch = make_eval_envs("Pendulum-v1", 4, wrap=lambda env: TransformedEnv(env, DoubleToFloat()))
    sequential = evaluate_policy(policy, one, 4, seed=3, max_steps=60)
    batched = evaluate_policy(policy, batch, 4, seed=3, max_steps=60)
    assert len(set(sequential)) == 4
    np.testing.assert_allclose(batched, sequential, rtol=1e-4)


def test_building_batched_eval_envs_leaves_the_training_rng_alone():
    """Creating the evaluation envs must not shift the global torch stream that a run's networks and
    batches draw from; otherwise a batched run would initialise differently from a sequential one."""
    from torchrl_tels.envs import make_eval_envs

    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    make_eval_envs("Hopper-v4", 3)
    assert torch.equal(torch.rand(3), expected)


def test_policy_on_device_leaves_a_batched_evaluation_unchanged():
    """PolicyOnDevice returns the whole step on the env's device, with the action; in a batched Hopper
    evaluation whose copies fall at different steps (the path that merges finished and running copies)
    the returns are the unwrapped policy's."""
    from tensordict import TensorDict
    from tensordict.nn import TensorDictModule
    from torchrl.envs import DoubleToFloat, TransformedEnv
    from torchrl.modules import MLP

    from torchrl_tels.envs import PolicyOnDevice, evaluate_policy, make_eval_envs

    torch.manual_seed(0)
    net = torch.nn.Sequential(MLP(in_features=11, out_features=3, num_cells=[64, 64]), torch.nn.Tanh())
    policy = TensorDictModule(lambda obs: 0.05 * net(obs), in_keys=["observation"], out_keys=["action"])
    wrapped = PolicyOnDevice(policy, "cpu", "cpu")
    step = wrapped(TensorDict({"observation": torch.zeros(2, 11), "step_count": torch.ones(2, 1)}, [2]))
    assert step.device == torch.device("cpu") and set(step.keys()) == {"observation", "step_count", "action"}
    torch.testing.assert_close(step["action"], 0.05 * net(torch.zeros(2, 11)))
    batch = make_eval_envs("Hopper-v4", 4, wrap=lambda env: TransformedEnv(env, DoubleToFloat()))
    plain, lengths = evaluate_policy(policy, batch, 4, seed=3, max_steps=200, with_lengths=True)
    moved = evaluate_policy(wrapped, batch, 4, seed=3, max_steps=200)
    assert max(lengths) < 200 and len(set(lengths)) > 1  # copies ended, at different steps
    assert moved == plain
