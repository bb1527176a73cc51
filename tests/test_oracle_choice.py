"""``study.oracle_choice``: the lookahead's returns against the same rollouts replayed in a
fresh wrapped env, the choice against the largest of them, and the actor's window return against the run's
actor played by hand."""
from __future__ import annotations

import json

import gymnasium as gym
import pytest
import torch
from tensordict import TensorDict

from study import oracle_choice
from study.model_selection import candidate_policies, own_action
from study.proposal_cap import load_finished_run
from study.value_delivery import run_config
from torchrl_tels.trainer import make_data

GAMMA = 0.9


def _replayed_return(env_id, qpos, qvel, first_action, policy, steps: int) -> float:
    """The discounted return of ``first_action`` then ``policy`` from (qpos, qvel), stepped through the full
    wrapper stack of a fresh env."""
    env = gym.make(env_id)
    try:
        env.reset(seed=123)
        env.unwrapped.set_state(qpos, qvel)
        total, action = 0.0, first_action.numpy()
        for k in range(steps):
            observation, reward, terminated, _, _ = env.step(action)
            total += GAMMA ** k * float(reward)
            if terminated:
                break
            action = policy(torch.as_tensor(observation, dtype=torch.float32)[None])[0].numpy()
    finally:
        env.close()
    return total


@pytest.fixture(scope="module")
def chooser_of_run(finished_recipe_run):
    run = load_finished_run(finished_recipe_run, episodes=1)
    data, _ = make_data(run_config(finished_recipe_run))
    return run, candidate_policies(run, data)(own_action)


def test_the_lookahead_returns_are_the_rollouts_a_fresh_env_replays(chooser_of_run):
    run, chooser = chooser_of_run
    env = gym.make(run.task.env_id)
    observation, _ = env.reset(seed=5)
    for _ in range(3):  # off the reset distribution
        observation, *_ = env.step(chooser(torch.as_tensor(observation, dtype=torch.float32)[None])[0].numpy())
    qpos, qvel = env.unwrapped.data.qpos.copy(), env.unwrapped.data.qvel.copy()
    env.close()
    _, latent_actions, _ = chooser.candidates(torch.as_tensor(observation, dtype=torch.float32)[None])
    actions = chooser.actions(latent_actions)[:, 0]
    oracle = oracle_choice.LookaheadOracle(run.task.env_id, chooser.own_actions, len(actions), lookahead=8,
                                           gamma=GAMMA)
    try:
        returns = oracle.returns(qpos, qvel, torch.as_tensor(observation, dtype=torch.float32)[None], actions)
    finally:
        oracle.close()
    # replayed through the chooser's own-candidate choice (the path model_selection checks against the actor)
    expected = [_replayed_return(run.task.env_id, qpos, qvel, action, chooser, 8) for action in actions]
    torch.testing.assert_close(returns, torch.tensor(expected, dtype=torch.float64), rtol=1e-6, atol=1e-6)  # a batch of 16 rounds unlike one
    assert returns.std() > 0  # the candidates' returns differ: there is something to choose


def test_a_reading_pairs_the_actor_with_the_oracle(finished_recipe_run):
    record = oracle_choice.oracle_choice(finished_recipe_run, lookahead=3, episodes=2, steps=12)
    assert record["lookahead"] == 3 and record["episodes"] == 2 and record["steps"] == 12
    assert all(1 <= length <= 12 for lengths in record["lengths"].values() for length in lengths)
    assert record["decisions"] == sum(record["lengths"]["oracle"]) and 0.0 <= record["departure_share"] <= 1.0
    # the actor's window return is the run's actor played by hand from the same resets
    run = load_finished_run(finished_recipe_run, episodes=1)
    for episode, expected in enumerate(record["returns"]["actor"]):
        env = gym.make(run.task.env_id)
        observation, _ = env.reset(seed=oracle_choice.SEED + run.seed + episode)
        total = 0.0
        for _ in range(12):
            step = run.actor(TensorDict({"observation": torch.as_tensor(observation, dtype=torch.float32)}, []))
            observation, reward, terminated, truncated, _ = env.step(step["action"].detach().numpy())
            total += float(reward)
            if terminated or truncated:
                break
        env.close()
        assert expected == pytest.approx(total, rel=1e-5)
    changes = [o - a for o, a in zip(record["returns"]["oracle"], record["returns"]["actor"])]
    assert record["change"]["mean"] == pytest.approx(sum(changes) / 2)


def test_the_table_reads_each_record_into_its_columns():
    record = {"final_score": 40.0, "lookahead": 100, "episodes": 2, "steps": 300, "departure_share": 0.25,
              "returns": {"actor": [800.0, 600.0], "oracle": [900.0, 500.0]},
              "lengths": {"actor": [300, 200], "oracle": [300, 150]}, "change": {"mean": 0.0, "up": 1}}
    header, rule, row = oracle_choice.table({("arm", "task", 0): record}).splitlines()[:3]
    cells = dict(zip(header.strip("| ").split(" | "), row.strip("| ").split(" | ")))
    assert len(cells) == rule.count("---") == row.count(" | ") + 1
    assert cells["return over the window: actor, oracle"] == "700, 700"
    assert cells["paired change (episodes up)"] == "+0 (1 of 2)"
    assert cells["steps lasted: actor, oracle"] == "250, 225"
    assert cells["oracle departs from the actor"] == "25%"


def test_the_command_line_passes_the_lookahead_to_the_reading(finished_recipe_run, tmp_path, monkeypatch):
    monkeypatch.setattr(oracle_choice, "RESULTS", tmp_path)
    monkeypatch.setattr(oracle_choice, "EPISODES", 1)
    monkeypatch.setattr(oracle_choice, "STEPS", 4)
    oracle_choice.main(["--run-dir", str(finished_recipe_run), "--name", "arm-task-seed0", "--lookahead", "2"])
    record = json.loads((tmp_path / "arm-task-seed0.json").read_text())
    assert record["lookahead"] == 2 and record["episodes"] == 1 and record["steps"] == 4


def test_the_table_orders_rows_by_task_then_lookahead():
    def record(lookahead):
        return {"final_score": 1.0, "lookahead": lookahead, "episodes": 1, "steps": 10, "departure_share": 0.0,
                "returns": {"actor": [1.0], "oracle": [1.0]}, "lengths": {"actor": [10], "oracle": [10]},
                "change": {"mean": 0.0, "up": 0}}
    records = {("h10", "b", 0): record(10), ("h300", "a", 0): record(300), ("h100", "a", 0): record(100),
               ("h50", "a", 0): record(50)}
    rows = [line for line in oracle_choice.table(records).splitlines()[2:] if line.startswith("|")]
    assert [row.split(" | ")[0].strip("| ") for row in rows] == ["h50", "h100", "h300", "h10"]


def test_pooled_changes_pair_every_episode_of_every_seed():
    def record(actor, oracle):
        return {"lookahead": 300, "returns": {"actor": actor, "oracle": oracle}}
    records = {("a", "task", 0): record([100.0, 200.0], [150.0, 190.0]), ("a", "task", 1): record([300.0], [390.0]),
               ("a", "other", 0): record([10.0], [5.0])}
    assert oracle_choice.pooled_changes(records) == [
        "- other, lookahead 300: oracle over actor -5 (-50% of the actor's return), up on 0 of 1 episodes.",
        "- task, lookahead 300: oracle over actor +43 (+22% of the actor's return), up on 2 of 3 episodes."]
