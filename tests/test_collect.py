"""Recording Minari datasets and reading them back with load_dataset."""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import gymnasium as gym
import minari
import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule

from torchrl_tels.collection import collect_minari_dataset
from torchrl_tels.data import load_dataset

REPO_ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(autouse=True)
def minari_root(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    return tmp_path


class RecordingPolicy:
    """A seeded stochastic policy that remembers what it saw and did."""

    def __init__(self, action_dim: int, seed: int = 0):
        self.rng = np.random.default_rng(seed)
        self.action_dim = action_dim
        self.observations: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        action = self.rng.uniform(-1, 1, self.action_dim).astype(np.float32)
        self.observations.append(observation.copy())
        self.actions.append(action)
        return action


def replay(env_id, seeds_and_actions):
    """Re-run the env with the recorded resets and actions: rewards and flags."""
    env = gym.make(env_id)
    rewards, terminated, truncated = [], [], []
    for seed, actions in seeds_and_actions:
        env.reset(seed=seed)
        for action in actions:
            _, reward, term, trunc, _ = env.step(action)
            rewards.append(reward)
            terminated.append(term)
            truncated.append(trunc)
    env.close()
    return np.array(rewards), np.array(terminated), np.array(truncated)


def test_round_trip_hopper_steps():
    policy = RecordingPolicy(action_dim=3, seed=1)
    dataset = collect_minari_dataset(
        "Hopper-v4", "test/hopper/recorded-v0", policy=policy, n_steps=300, seed=10
    )
    assert dataset.total_steps == 300
    data = load_dataset("test/hopper/recorded-v0")
    assert len(data) == 300

    # What the policy saw and returned is what was stored.
    np.testing.assert_array_equal(
        data["observation"].numpy(), np.stack(policy.observations).astype(np.float32)
    )
    np.testing.assert_array_equal(data["action"].numpy(), np.stack(policy.actions))

    # Rewards and flags: replay the recorded actions from the recorded seeds.
    episode_lengths = torch.unique_consecutive(data["episode"], return_counts=True)[1]
    assert len(episode_lengths) > 1  # random hopper falls over: several episodes
    starts = np.concatenate([[0], np.cumsum(episode_lengths.numpy())[:-1]])
    actions = np.stack(policy.actions)
    rewards, terminated, truncated = replay(
        "Hopper-v4",
        [
            (10 + i, actions[s : s + n])
            for i, (s, n) in enumerate(zip(starts, episode_lengths, strict=False))
        ],
    )
    np.testing.assert_allclose(data["next", "reward"][:, 0].numpy(), rewards, rtol=1e-6)
    np.testing.assert_array_equal(data["next", "terminated"][:, 0].numpy(), terminated)
    # Every episode but the last ended by falling; the last was cut at 300 steps.
    assert int(data["next", "terminated"].sum()) == len(episode_lengths) - 1
    assert data["next", "truncated"][:, 0].nonzero().squeeze(-1).tolist() == [299]
    assert not truncated.any()
    # The observation chain: next observation of a step is the following one.
    inner = ~data["next", "done"][:-1, 0]
    assert torch.equal(
        data["next", "observation"][:-1][inner], data["observation"][1:][inner]
    )


def test_episodes_random_policy_is_seeded():
    first = collect_minari_dataset(
        "Pendulum-v1", "test/pendulum/a-v0", n_episodes=2, seed=3
    )
    collect_minari_dataset("Pendulum-v1", "test/pendulum/b-v0", n_episodes=2, seed=3)
    collect_minari_dataset("Pendulum-v1", "test/pendulum/c-v0", n_episodes=2, seed=4)
    assert first.total_episodes == 2 and first.total_steps == 400

    a, b, c = (load_dataset(f"test/pendulum/{name}-v0") for name in "abc")
    assert (a == b).all()
    assert not torch.equal(a["action"], c["action"])
    # Pendulum never terminates; each episode ends at its 200-step time limit.
    assert a["next", "truncated"][:, 0].nonzero().squeeze(-1).tolist() == [199, 399]
    assert not a["next", "terminated"].any()
    space = gym.make("Pendulum-v1").action_space
    assert (a["action"] >= float(space.low[0])).all() and (
        a["action"] <= float(space.high[0])
    ).all()
    # Episode i is reset with seed + i, as documented.
    env = gym.make("Pendulum-v1")
    np.testing.assert_allclose(
        a["observation"][200].numpy(), env.reset(seed=4)[0], rtol=1e-6
    )


def test_action_noise_is_added_and_clipped():
    def constant(observation):
        return np.array([1.9], dtype=np.float32)

    collect_minari_dataset(
        "Pendulum-v1",
        "test/pendulum/noisy-v0",
        policy=constant,
        n_steps=200,
        action_noise=0.5,
    )
    actions = load_dataset("test/pendulum/noisy-v0")["action"][:, 0]
    assert actions.max() == pytest.approx(2.0)  # clipped to the action bound
    assert (actions < 1.9).sum() > 50  # the noise moved many below the policy's action
    assert actions.min() >= -2.0


def test_torchrl_actor_policy():
    torch.manual_seed(0)
    actor = TensorDictModule(
        torch.nn.Sequential(torch.nn.Linear(3, 1), torch.nn.Tanh()),
        in_keys=["observation"],
        out_keys=["action"],
    )
    collect_minari_dataset(
        "Pendulum-v1", "test/pendulum/actor-v0", policy=actor, n_steps=20
    )
    data = load_dataset("test/pendulum/actor-v0")
    with torch.no_grad():
        expected = actor.module(data["observation"])
    torch.testing.assert_close(data["action"], expected)


def test_collect_errors():
    with pytest.raises(ValueError, match="exactly one of n_episodes and n_steps"):
        collect_minari_dataset("Pendulum-v1", "test/x-v0")
    with pytest.raises(ValueError, match="exactly one of n_episodes and n_steps"):
        collect_minari_dataset("Pendulum-v1", "test/x-v0", n_episodes=1, n_steps=1)
    with pytest.raises(ValueError, match="must be positive"):
        collect_minari_dataset("Pendulum-v1", "test/x-v0", n_steps=0)
    with pytest.raises(ValueError, match="action_noise must be >= 0"):
        collect_minari_dataset("Pendulum-v1", "test/x-v0", n_steps=5, action_noise=-1)
    with pytest.raises(ValueError, match="needs a continuous"):
        collect_minari_dataset("CartPole-v1", "test/x-v0", n_steps=5, action_noise=0.1)


def test_existing_dataset_needs_overwrite():
    collect_minari_dataset("Pendulum-v1", "test/pendulum/same-v0", n_steps=5, seed=0)
    with pytest.raises(ValueError, match="already exists; pass overwrite=True"):
        collect_minari_dataset("Pendulum-v1", "test/pendulum/same-v0", n_steps=5)
    collect_minari_dataset(
        "Pendulum-v1", "test/pendulum/same-v0", n_steps=7, seed=1, overwrite=True
    )
    assert minari.load_dataset("test/pendulum/same-v0").total_steps == 7


def test_discrete_actions_load_as_float_column():
    collect_minari_dataset("CartPole-v1", "test/cartpole/random-v0", n_steps=30, seed=0)
    data = load_dataset("test/cartpole/random-v0")
    raw = np.concatenate(
        [
            ep.actions
            for ep in minari.load_dataset("test/cartpole/random-v0").iterate_episodes()
        ]
    )
    assert data["action"].shape == (30, 1) and data["action"].dtype == torch.float32
    np.testing.assert_array_equal(data["action"][:, 0].numpy(), raw.astype(np.float32))


def _load_recipe():
    spec = importlib.util.spec_from_file_location(
        "collect_dataset_recipe", REPO_ROOT / "recipes" / "collect_dataset.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_recipe_with_module_policy(monkeypatch, capsys):
    policies = types.ModuleType("fake_policies")
    policies.push_right = lambda observation: np.array([0.5], dtype=np.float32)
    monkeypatch.setitem(sys.modules, "fake_policies", policies)

    recipe = _load_recipe()
    recipe.main(
        [
            "--env",
            "Pendulum-v1",
            "--dataset-id",
            "test/pendulum/recipe-v0",
            "--steps",
            "25",
            "--policy",
            "fake_policies:push_right",
            "--seed",
            "2",
        ]
    )
    assert (
        "Wrote test/pendulum/recipe-v0: 1 episodes, 25 steps" in capsys.readouterr().out
    )
    data = load_dataset("test/pendulum/recipe-v0")
    assert torch.equal(data["action"], torch.full((25, 1), 0.5))
    env = gym.make("Pendulum-v1")
    np.testing.assert_allclose(
        data["observation"][0].numpy(), env.reset(seed=2)[0], rtol=1e-6
    )


def test_recipe_rejects_bad_policy_spec():
    recipe = _load_recipe()
    with pytest.raises(SystemExit, match="'random' or 'module:attribute'"):
        recipe.load_policy("policy.pt")
    assert recipe.load_policy("random") is None


def test_own_minari_dataset_trains_and_evaluates_where_it_was_recorded(minari_root, tmp_path, capsys):
    """A user's dataset with no registered task: the recipe evaluates in the env the dataset recorded,
    and, with no reference scores, reports raw returns."""
    from hydra import compose, initialize_config_dir

    collect_minari_dataset("Hopper-v4", "local/hopper/random-v0", n_steps=600, seed=0)
    spec = importlib.util.spec_from_file_location("tels_recipe", REPO_ROOT / "recipes" / "tels_offline.py")
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    overrides = ["budget=smoke", "threads=1", "dataset.name=local/hopper/random-v0", f"run_dir={tmp_path / 'run'}",
                 "tsidm.steps=20", "tsidm.batch_size=64", "policy.steps=20", "policy.batch_size=64",
                 "eval.interval=20", "eval.episodes=2", "eval.last_n=1", "eval.max_steps=30"]
    with initialize_config_dir(str(REPO_ROOT / "recipes" / "config"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    results = recipe.main.__wrapped__(cfg)
    assert results["env"] == "Hopper-v4" and results["task"] == "local/hopper/random-v0"
    assert results["score_kind"] == "undiscounted return"
    evaluation = results["evaluations"][-1]
    assert evaluation["scores"] == evaluation["returns"]
    assert results["final_normalized_score_mean"] == pytest.approx(sum(evaluation["returns"]) / 2, rel=1e-6)
