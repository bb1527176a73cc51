"""The stock D4RL AntMaze sets by Minari id: each resolves to its maze, scored as D4RL scores AntMaze."""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from torchrl_tels.data import load_dataset
from torchrl_tels.envs import get_task, make_eval_env, normalized_score
from torchrl_tels.envs.robotics import maze_files_removed

pytest.importorskip("gymnasium_robotics")

SETS = {"umaze": ("UMaze", 700), "umaze-diverse": ("UMaze", 700), "medium-play": ("Medium", 1000),
        "medium-diverse": ("Medium", 1000), "large-play": ("Large", 1000), "large-diverse": ("Large", 1000)}


@pytest.mark.parametrize("name", list(SETS))
def test_stock_id_resolves_to_its_maze_with_d4rls_limit_and_references(name):
    maze, steps = SETS[name]
    task = get_task(f"D4RL/antmaze/{name}-v1")
    assert (task.ref_min_score, task.ref_max_score, task.max_episode_steps) == (0.0, 1.0, steps)
    env = gym.make(task.env_id)
    assert env.spec.max_episode_steps == steps
    assert env.observation_space.shape == (task.observation_dim,) == (31,)
    rows = len(env.unwrapped.maze.maze_map)
    assert (rows, len(env.unwrapped.maze.maze_map[0])) == {"UMaze": (5, 5), "Medium": (8, 8), "Large": (9, 12)}[maze]
    # One start and one goal cell, as D4RL evaluates: two resets start and aim the same, up to jitter.
    first, _ = env.reset(seed=0)
    second, _ = env.reset(seed=1)
    np.testing.assert_allclose(first[:2], second[:2], atol=2.0)  # achieved_goal: the start cell (4 units wide)
    np.testing.assert_allclose(first[2:4], second[2:4], atol=2.0)  # desired_goal: the goal cell
    assert np.linalg.norm(first[2:4] - first[:2]) > 4.0


def test_reaching_the_goal_ends_the_episode_with_return_one():
    task = get_task("D4RL/antmaze/medium-play-v1")
    env = gym.make(task.env_id)
    obs, _ = env.reset(seed=0)
    inner = env.unwrapped
    _, reward, terminated, _, _ = env.step(np.zeros(8, dtype=np.float32))
    assert (reward, terminated) == (0.0, False)
    ant = inner.ant_env
    qpos, qvel = ant.data.qpos.copy(), ant.data.qvel.copy()
    qpos[:2] = inner.goal  # the ant's torso onto the goal
    ant.set_state(qpos, qvel)
    _, reward, terminated, _, info = env.step(np.zeros(8, dtype=np.float32))
    assert (reward, terminated, bool(info["success"])) == (1.0, True, True)
    assert normalized_score(task, reward) == 100.0


def test_minari_antmaze_id_loads_from_a_dataset_recorded_in_the_real_env(tmp_path, monkeypatch):
    from torchrl_tels.collection import collect_minari_dataset

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    collect_minari_dataset("AntMaze_UMaze-v4", "D4RL/antmaze/umaze-v1", n_steps=25, seed=2)
    data = load_dataset("D4RL/antmaze/umaze-v1", download=False)
    task = get_task("D4RL/antmaze/umaze-v1")
    assert data.shape == (25,)
    assert (data["observation"].shape[-1], data["action"].shape[-1]) == (task.observation_dim, task.action_dim)
    env = make_eval_env(task.env_id)
    rollout = env.rollout(5)
    assert rollout["observation"].shape == (5, data["observation"].shape[-1])
    # The dataset's flattening is the eval env's (FlattenObservation): the recording's first observation,
    # rebuilt from the same seeded reset and flattened as the eval env flattens.
    with maze_files_removed():
        recorder = gym.make("AntMaze_UMaze-v4")
    first, _ = recorder.reset(seed=2)
    flat = gym.spaces.flatten(recorder.observation_space, first)
    np.testing.assert_allclose(data["observation"][0].numpy(), flat, rtol=1e-5, atol=1e-6)
