"""``study.value_delivery``: returns checked against direct loops, rollouts from data states
against the simulator stepped by hand, and the retrained V against a recipe run's own logged V losses."""
from __future__ import annotations


import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from study import realization, value_delivery
from study.proposal_cap import load_finished_run
from torchrl_tels.trainer import make_data



def _episodes(lengths, terminated=None, seed=0):
    """Episodes of random rewards, one after another; ``terminated[i]``: whether episode i ends in a
    termination (all of them by default) rather than a timeout."""
    generator = torch.Generator().manual_seed(seed)
    episode = torch.cat([torch.full((n,), i) for i, n in enumerate(lengths)])
    ends = torch.cat([episode[1:] != episode[:-1], torch.tensor([True])])
    terminal = torch.zeros(len(episode), dtype=torch.bool)
    terminal[ends.nonzero().flatten()[torch.tensor(terminated if terminated is not None else [True] * len(lengths))]] = True
    reward = torch.rand(len(episode), 1, generator=generator)
    return TensorDict({"episode": episode, "next": {"reward": reward, "done": ends.unsqueeze(-1),
                                                    "terminated": terminal.unsqueeze(-1)}},
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
    data = _episodes([7, 1, 12, 5])
    got = value_delivery.recorded_returns(data, 0.9, horizon)
    torch.testing.assert_close(got, _direct_returns(data, 0.9, horizon), rtol=1e-5, atol=1e-5)


def test_episode_ends_steps_to_end_and_which_episodes_terminate():
    data = _episodes([3, 1, 2, 2], terminated=[True, False, False, True])
    ends = value_delivery.episode_ends(data)
    assert ends.tolist() == [False, False, True, True, False, True, False, True]
    assert value_delivery.steps_to_end(ends).tolist() == [2, 1, 0, 0, 1, 0, 1, 0]
    # a timed-out episode's rows have no known return-to-go, though the data marks them done
    assert value_delivery.terminated_episodes(data).tolist() == [True] * 3 + [False] * 3 + [True] * 2


def _hopper_states(count=5):
    env = gym.make("Hopper-v4")
    observation, _ = env.reset(seed=0)
    starts = []
    for step in range(count):
        observation = env.step(np.array([0.3, -0.5, 0.8]) * (-1) ** step)[0]
        starts.append(observation)
    return env, torch.as_tensor(np.array(starts))


@pytest.mark.parametrize("given_first", [False, True])
def test_rollouts_from_data_states_match_the_simulator_stepped_by_hand(monkeypatch, given_first):
    monkeypatch.setattr(value_delivery, "CHUNK", 2)  # three chunks of envs
    env, starts = _hopper_states()

    def policy(observations):  # reads its observations, and falls within the horizon from some states
        return torch.tanh(3 * observations[:, 2:5]).clamp(-1, 1)

    horizon, gamma = 60, 0.95
    first = torch.linspace(-1, 1, 15).reshape(5, 3).to(starts.dtype) if given_first else None
    returns = value_delivery.rollout_returns("Hopper-v4", starts, policy, horizon, gamma, first_actions=first)
    falls = 0
    for row, (start, got) in enumerate(zip(starts.numpy(), returns.tolist())):
        realization.set_state_from_observation(env, start)
        observation, expected = start, 0.0
        for k in range(horizon):
            action = policy(torch.as_tensor(observation[None]))[0] if first is None or k else first[row]
            observation, reward, terminated, _, _ = env.step(action.numpy())
            expected += gamma ** k * reward
            if terminated:
                falls += 1
                break
        assert got == pytest.approx(expected, rel=1e-5)
    assert falls > 0  # termination is exercised


def test_steps_from_observations_report_reward_and_termination():
    env, starts = _hopper_states(2)
    actions = torch.tensor([[0.2, -0.7, 0.4], [1.0, 1.0, 1.0]], dtype=starts.dtype)
    reached, rewards, terminated = realization.step_from_observations(env, starts, actions)
    for start, action, obs, reward, done in zip(starts.numpy(), actions.numpy(), reached, rewards, terminated):
        realization.set_state_from_observation(env, start)
        expected = env.step(action)
        np.testing.assert_allclose(obs.numpy(), expected[0], atol=1e-9)
        assert reward.item() == pytest.approx(expected[1], rel=1e-9) and done.item() == expected[2]
    np.testing.assert_allclose(realization.one_step(env, starts, actions).numpy(), reached.numpy(), atol=0)


def test_random_actions_are_drawn_inside_the_action_box(monkeypatch):
    from types import SimpleNamespace

    monkeypatch.setattr(value_delivery, "RANDOM_ACTIONS", 3)
    point = torch.tensor([0.2, -0.7, 0.4])
    drawn = value_delivery.random_actions(SimpleNamespace(space=SimpleNamespace(low=point, high=point)), 4)
    assert len(drawn) == 3 and all(torch.equal(d, point.expand(4, 3)) for d in drawn)
    low, high = torch.tensor([-1.0, 0.0, 2.0]), torch.tensor([1.0, 0.5, 3.0])
    drawn = torch.stack(value_delivery.random_actions(SimpleNamespace(space=SimpleNamespace(low=low, high=high)), 500))
    assert ((drawn >= low) & (drawn <= high)).all()
    # uniform over the box: the mean of 1,500 draws near the box's centre (std of the mean < 0.03 of the width)
    torch.testing.assert_close(drawn.mean((0, 1)), (low + high) / 2, atol=0.1 * (high - low).max().item(), rtol=0)


def test_retrained_value_reproduces_the_runs_logged_value_losses(finished_recipe_run):
    torch.set_num_threads(1)
    run = load_finished_run(finished_recipe_run, episodes=1)
    cfg = value_delivery.run_config(finished_recipe_run)
    data, _ = make_data(cfg)
    value, losses, gamma = value_delivery.retrain_value(cfg, data, run.tsidm, run.env.action_spec_unbatched)
    match = value_delivery.loss_match(finished_recipe_run, losses)
    # with one evaluation in between, every logged loss equal: the same batches in the same order
    assert match["steps_compared"] == 12 and match["max_relative_gap"] == 0.0
    assert gamma == cfg.value.gamma
    # a V trained with another seed's batches would not match: the comparison can fail
    shifted = {step: loss * (1 + 1e-4) for step, loss in losses.items()}
    assert value_delivery.loss_match(finished_recipe_run, shifted)["max_relative_gap"] > 1e-5
    latent = run.tsidm.encode_state(data["observation"][:5])
    assert value(latent).shape == (5,)


def test_a_cached_value_is_the_retrained_one_and_a_cache_of_other_steps_is_refused(finished_recipe_run, tmp_path,
                                                                                   monkeypatch):
    torch.set_num_threads(1)
    run = load_finished_run(finished_recipe_run, episodes=1)
    cfg = value_delivery.run_config(finished_recipe_run)
    data, _ = make_data(cfg)
    spec, cache = run.env.action_spec_unbatched, tmp_path / value_delivery.VALUE_CACHE
    value, losses, _ = value_delivery.retrain_value(cfg, data, run.tsidm, spec, cache)
    assert cache.exists()

    def no_training(*args, **kwargs):
        raise AssertionError("V was retrained although a cache exists")

    monkeypatch.setattr(value_delivery.tqdm, "trange", no_training)
    cached, cached_losses, _ = value_delivery.retrain_value(cfg, data, run.tsidm, spec, cache)
    latent = run.tsidm.encode_state(data["observation"][:50])
    assert cached_losses == losses
    assert torch.equal(cached(latent), value(latent))
    # the networks V starts from would give other values: the comparison can fail
    untrained = value_delivery.make_stage2(cfg, data, run.tsidm, spec).value_loss
    with untrained.value_network_params.to_module(untrained.value_network):
        start = untrained.value_network(TensorDict({"latent": latent}, [50]))["state_value"].squeeze(-1)
    assert not torch.allclose(start, value(latent))
    cfg.policy.steps += 1
    with pytest.raises(SystemExit, match="value_retrained.pt holds V after 120 steps"):
        value_delivery.retrain_value(cfg, data, run.tsidm, spec, cache)


def test_a_reading_of_a_recipe_run(finished_recipe_run, monkeypatch):
    monkeypatch.setattr(value_delivery, "STATES", 12)
    monkeypatch.setattr(value_delivery, "HORIZON", 5)
    monkeypatch.setattr(value_delivery, "BC_STEPS", 20)
    record = value_delivery.value_delivery(finished_recipe_run)
    assert record["states"] == 12 and record["value_loss_match"]["max_relative_gap"] == 0.0
    for key in ("promised", "delivered", "reward"):
        assert 0.0 <= record[key]["share_positive"] <= 1.0
    assert 0.0 <= record["best_random"]["share_promised_above"] <= 1.0
    horizon = record["horizon_return"]
    # five steps of the data's rewards at most, and the simulator's hopper earns at least its alive bonus
    most = 5 * load_finished_run(finished_recipe_run, episodes=1).data["next", "reward"].max().item()
    assert all(0.0 < horizon[k] <= most for k in ("data", "actor", "bc")), horizon
    text = value_delivery.table({("arm", "task", 0): record})
    assert text.splitlines()[2].startswith("| arm | task | 0 | ")
