"""``benchmarks.reproduction.value_delivery``: returns checked against direct loops, rollouts from data states
against the simulator stepped by hand, and the retrained V against a recipe run's own logged V losses."""
from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from benchmarks.reproduction import realization, value_delivery
from benchmarks.reproduction.proposal_cap import load_finished_run
from torchrl_tels.trainer import make_data

from tests.test_resume import RECIPE, REPO_ROOT


def _episodes(lengths, terminated_last=True, seed=0):
    generator = torch.Generator().manual_seed(seed)
    episode = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
    ends = torch.cat([episode[1:] != episode[:-1], torch.tensor([True])])
    done = ends.clone()
    if not terminated_last:
        done[-1] = False
    reward = torch.rand(len(episode), 1, generator=generator)
    return TensorDict({"episode": episode, "next": {"reward": reward, "done": done.unsqueeze(-1)}},
                      batch_size=[len(episode)])


def _direct_returns(data, gamma, horizon=None):
    reward, episode = data["next", "reward"].squeeze(-1).tolist(), data["episode"].tolist()
    out = []
    for row in range(len(reward)):
        total, k = 0.0, 0
        while row + k < len(reward) and episode[row + k] == episode[row] and (horizon is None or k < horizon):
            total += gamma ** k * reward[row + k]
            k += 1
        out.append(total)
    return torch.tensor(out)


@pytest.mark.parametrize("horizon", [None, 1, 4, 30])
def test_recorded_returns_match_a_direct_sum_within_each_episode(horizon):
    data = _episodes([7, 1, 12, 5], terminated_last=False)
    got = value_delivery.recorded_returns(data, 0.9, horizon)
    torch.testing.assert_close(got, _direct_returns(data, 0.9, horizon), rtol=1e-5, atol=1e-5)


def test_steps_to_end_counts_the_rows_left_in_each_episode():
    ends = value_delivery.episode_ends(_episodes([3, 1, 2]))
    assert ends.tolist() == [False, False, True, True, False, True]
    assert value_delivery.steps_to_end(ends).tolist() == [2, 1, 0, 0, 1, 0]


def test_rollouts_from_data_states_match_the_simulator_stepped_by_hand(monkeypatch):
    monkeypatch.setattr(value_delivery, "CHUNK", 2)  # three chunks: the actions must follow their states
    env = gym.make("Hopper-v4")
    observation, _ = env.reset(seed=0)
    starts = []
    for step in range(5):
        observation = env.step(np.array([0.3, -0.5, 0.8]) * (-1) ** step)[0]
        starts.append(observation)
    starts = torch.as_tensor(np.array(starts))
    actions = torch.linspace(-0.9, 0.9, 15, dtype=starts.dtype).reshape(5, 3)
    _, rewards, firsts = value_delivery.rollout_returns("Hopper-v4", starts, actions, 1, 0.99)
    np.testing.assert_allclose(firsts.numpy(), realization.one_step(env, starts, actions).numpy(), atol=1e-9)

    def falling(observations):  # full thrust one way: the hopper falls within the horizon from some states
        return torch.ones(len(observations), 3, dtype=observations.dtype)

    horizon, gamma = 60, 0.95
    returns, _, _ = value_delivery.rollout_returns("Hopper-v4", starts, falling, horizon, gamma)
    for start, got, first_reward in zip(starts.numpy(), returns.tolist(), rewards.tolist()):
        realization.set_state_from_observation(env, start)
        expected = 0.0
        for k in range(horizon):
            _, reward, terminated, _, _ = env.step(np.ones(3))
            expected += gamma ** k * reward
            if terminated:
                break
        assert got == pytest.approx(expected, rel=1e-5)
    realization.set_state_from_observation(env, starts[0].numpy())
    assert rewards[0].item() == pytest.approx(env.step(actions[0].numpy())[1], rel=1e-6)
    with pytest.raises(ValueError, match="horizon must be 1"):
        value_delivery.rollout_returns("Hopper-v4", starts, actions, 2, 0.99)


def test_random_actions_are_drawn_inside_the_action_box(monkeypatch):
    from types import SimpleNamespace

    monkeypatch.setattr(value_delivery, "RANDOM_ACTIONS", 3)
    env = gym.make("Hopper-v4")
    observation, _ = env.reset(seed=1)
    observation = env.step(np.array([0.5, 0.5, -0.5]))[0]
    starts = torch.as_tensor(np.array([observation, observation]))
    # a box of one point: every draw is that action
    point = torch.tensor([0.2, -0.7, 0.4])
    spec = SimpleNamespace(space=SimpleNamespace(low=point, high=point))
    reached = value_delivery.random_action_steps("Hopper-v4", starts, spec)
    expected = realization.one_step(env, starts, point.double().expand(2, 3))
    assert len(reached) == 3
    for r in reached:
        np.testing.assert_allclose(r.numpy(), expected.numpy(), atol=1e-9)
    # the unit box: the draws differ, so the states reached differ
    unit = SimpleNamespace(space=SimpleNamespace(low=-torch.ones(3), high=torch.ones(3)))
    a, b, _ = value_delivery.random_action_steps("Hopper-v4", starts, unit)
    assert not torch.allclose(a, b)


@pytest.fixture(scope="module")
def recipe_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("value_delivery") / "run"
    overrides = ["domain=paper", "budget=smoke", "threads=1", "seed=2", "tsidm.beta=1.0", "tsidm.steps=20",
                 "policy.steps=120", "eval.interval=60", "eval.episodes=1", "eval.max_steps=30",
                 "logger.log_interval=10", f"run_dir={run_dir}"]
    proc = subprocess.run([sys.executable, str(RECIPE), *overrides], cwd=REPO_ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return run_dir


def test_retrained_value_reproduces_the_runs_logged_value_losses(recipe_run):
    torch.set_num_threads(1)
    run = load_finished_run(recipe_run, episodes=1)
    cfg = value_delivery.run_config(recipe_run)
    data, _ = make_data(cfg)
    value, losses, gamma = value_delivery.retrain_value(cfg, data, run.tsidm, run.env.action_spec_unbatched)
    match = value_delivery.loss_match(recipe_run, losses)
    # with one evaluation in between, every logged loss equal: the same batches in the same order
    assert match["steps_compared"] == 12 and match["max_relative_gap"] == 0.0
    assert gamma == cfg.value.gamma
    # a V trained with another seed's batches would not match: the comparison can fail
    shifted = {step: loss * (1 + 1e-4) for step, loss in losses.items()}
    assert value_delivery.loss_match(recipe_run, shifted)["max_relative_gap"] > 1e-5
    latent = run.tsidm.encode_state(data["observation"][:5])
    assert value(latent).shape == (5,)


def test_a_reading_of_a_recipe_run(recipe_run, monkeypatch):
    monkeypatch.setattr(value_delivery, "STATES", 12)
    monkeypatch.setattr(value_delivery, "HORIZON", 5)
    monkeypatch.setattr(value_delivery, "BC_STEPS", 20)
    record = value_delivery.value_delivery(recipe_run)
    assert record["states"] == 12 and record["value_loss_match"]["max_relative_gap"] == 0.0
    for key in ("promised", "delivered", "reward"):
        assert 0.0 <= record[key]["share_positive"] <= 1.0
    assert 0.0 <= record["best_random"]["share_promised_above"] <= 1.0
    horizon = record["horizon_return"]
    # five steps of the data's rewards at most, and the simulator's hopper earns at least its alive bonus
    most = 5 * load_finished_run(recipe_run, episodes=1).data["next", "reward"].max().item()
    assert all(0.0 < horizon[k] <= most for k in ("data", "actor", "bc")), horizon
    text = value_delivery.table({("arm", "task", 0): record})
    assert text.splitlines()[2].startswith("| arm | task | 0 | ")
