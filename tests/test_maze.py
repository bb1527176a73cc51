"""Maze environments and data: D4RL antmaze-umaze evaluation env, PointMaze data.

Needs Gymnasium-Robotics (the ``maze`` extra); the tests that need it skip with
the reason when it is absent. The antmaze data ships with the package.
"""

from __future__ import annotations

import importlib.resources
import sys
import time

import gymnasium as gym
import numpy as np
import pytest
import torch

from torchrl_tels.data import delete_regions, embedded_dataset_path, load_dataset
from torchrl_tels.envs import get_task, normalized_score
from torchrl_tels.collection import pointmaze as maze_collection
from torchrl_tels.envs import pointmaze
from torchrl_tels.envs import antmaze

ANTMAZE = "antmaze-umaze-v0-10k"  # shipped in torchrl_tels/data/assets
try:
    antmaze.import_gymnasium_robotics()
except ImportError:
    HAS_ROBOTICS = False
else:
    HAS_ROBOTICS = True
needs_robotics = pytest.mark.skipif(
    not HAS_ROBOTICS,
    reason='gymnasium-robotics is not installed (pip install "torchrl-tels[maze]")',
)

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture
def antmaze_arrays():
    with importlib.resources.as_file(embedded_dataset_path(ANTMAZE)) as path, np.load(path) as data:
        return {key: data[key] for key in data.files}


# --------------------------------------------------------------------------- #
# AntMaze (D4RL antmaze-umaze)
# --------------------------------------------------------------------------- #
def test_antmaze_registration_needs_no_robotics(monkeypatch):
    assert antmaze.ENV_ID in gym.registry
    assert gym.registry[antmaze.ENV_ID].max_episode_steps == 700
    for name in ("antmaze-umaze-v0", "antmaze-umaze-v0-10k", "antmaze-umaze-v2"):
        task = get_task(name)
        assert task.env_id == antmaze.ENV_ID
        assert (task.ref_min_score, task.ref_max_score) == (0.0, 1.0)
        assert (task.observation_dim, task.action_dim) == (29, 8)
        assert task.max_episode_steps == 700
    assert get_task("antmaze-umaze-v0-10k").dataset == "antmaze-umaze-v0-10k"
    assert normalized_score("antmaze-umaze-v0-10k", 0.35) == pytest.approx(35.0)

    # Without Gymnasium-Robotics, building the env says how to install it.
    monkeypatch.setitem(sys.modules, "gymnasium_robotics", None)
    with pytest.raises(ImportError, match=r"torchrl-tels\[robotics\]"):
        antmaze.AntMazeUMazeD4RLEnv()


@needs_robotics
def test_antmaze_patched_model_and_protocol():
    env = gym.make(antmaze.ENV_ID)
    base = env.unwrapped
    model = base.model
    assert model.opt.timestep == pytest.approx(0.02)
    assert base.dt == pytest.approx(0.1)
    np.testing.assert_allclose(model.actuator_gear[:, 0], 1.0)
    np.testing.assert_allclose(model.actuator_ctrlrange, [[-30.0, 30.0]] * 8)
    np.testing.assert_allclose(model.geom_margin, 0.005)
    np.testing.assert_allclose(model.geom_solref, [[0.02, 1.0]] * model.ngeom)
    np.testing.assert_allclose(model.geom_solimp[:, :3], [[0.8, 0.8, 0.01]] * model.ngeom)
    assert env.observation_space.shape == (29,) and env.action_space.shape == (8,)

    goals = []
    for seed in range(5):
        observation, info = env.reset(seed=seed)
        assert observation.shape == (29,) and observation.dtype == np.float32
        # Start: D4RL origin plus U(-0.1, 0.1); torso height 0.75 plus noise.
        assert np.all(np.abs(observation[:2]) <= 0.1 + 1e-6)
        assert abs(observation[2] - 0.75) <= 0.1 + 1e-6
        goal = info["goal"]
        assert 0.0 <= goal[0] <= 1.5 and 8.0 <= goal[1] <= 9.5
        goals.append(goal)
    assert len({tuple(goal) for goal in goals}) == 5  # redrawn on every reset
    # Same seed, same start and goal.
    first, info_a = env.reset(seed=3)
    again, info_b = env.reset(seed=3)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(info_a["goal"], info_b["goal"])

    # No success far from the goal; the episode is cut at 700 steps.
    observation, _ = env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step(np.zeros(8, np.float32))
    assert (reward, terminated, truncated) == (0.0, False, False)
    assert info["distance"] > 7.0
    # Success: torso within 0.5 of the goal ends the episode with reward 1.
    observation, _ = env.reset(seed=0, options={"goal": (0.3, 0.0)})
    _, reward, terminated, _, info = env.step(np.zeros(8, np.float32))
    assert info["distance"] <= 0.5
    assert (reward, terminated, info["success"]) == (1.0, True, True)
    env.close()

    # D4RL -v0: the goal drawn once per environment instance.
    fixed = gym.make(antmaze.ENV_ID, goal_per_reset=False)
    _, info_a = fixed.reset(seed=1)
    _, info_b = fixed.reset(seed=2)
    np.testing.assert_array_equal(info_a["goal"], info_b["goal"])
    fixed.close()


@needs_robotics
def test_antmaze_one_step_replay_matches_d4rl(antmaze_arrays):
    """Set each stored state, apply the stored action: the stored next state comes out."""
    observations = antmaze_arrays["observations"]
    actions = antmaze_arrays["actions"]
    next_observations = antmaze_arrays["next_observations"]
    assert observations.shape == (5383, 29)

    env = antmaze.AntMazeUMazeD4RLEnv()
    env.reset(seed=0)
    start = time.perf_counter()
    predicted = np.empty_like(next_observations)
    for row, (observation, action) in enumerate(zip(observations, actions)):
        env.set_state_from_observation(observation)
        predicted[row] = env.step(action)[0]
    elapsed = time.perf_counter() - start
    env.close()

    error = np.abs(predicted - next_observations)
    median = float(np.median(error))
    print(f"antmaze replay: median abs error {median:.2e} over {len(error)} transitions in {elapsed:.1f} s")
    assert median < 1e-3  # about 8e-5 with the patched model (stock v4: 0.035)
    # Positions (x, y) are reproduced too, not only the bulk of the dimensions.
    assert float(np.median(error[:, :2])) < 1e-3
    # The D4RL success test agrees with the stored rewards (within 0.5 of the
    # data's goal); the data's goal is not stored, only its reward-1 states.
    rewarded = antmaze_arrays["rewards"] == 1
    centre = np.array([0.525, 9.469])
    distance = np.linalg.norm(next_observations[:, :2] - centre, axis=1)
    assert np.all(distance[rewarded] <= antmaze.SUCCESS_RADIUS)
    assert np.all(distance[~rewarded] > antmaze.SUCCESS_RADIUS)


def test_delete_regions_antmaze_por_box():
    """POR's U-maze box (D4RL coordinates) removes exactly the 300 points inside it."""
    data = load_dataset(ANTMAZE)
    box = (5.0, 10.0, 2.0, 7.0)
    kept = delete_regions(data, [box])
    assert len(data) == 5383 and len(kept) == 5383 - 300

    xy = data["observation"][:, :2].numpy()
    inside = (xy[:, 0] >= 5) & (xy[:, 0] <= 10) & (xy[:, 1] >= 2) & (xy[:, 1] <= 7)
    assert inside.sum() == 300
    torch.testing.assert_close(kept["observation"], data["observation"][~inside])
    torch.testing.assert_close(kept["action"], data["action"][~inside])
    kept_xy = kept["observation"][:, :2]
    assert not (
        (kept_xy[:, 0] >= 5) & (kept_xy[:, 0] <= 10) & (kept_xy[:, 1] >= 2) & (kept_xy[:, 1] <= 7)
    ).any()

    # Half the points at ratio 0.5, chosen by the seed.
    half = delete_regions(data, [box], ratio=0.5, seed=1)
    assert len(half) == 5383 - 150


# --------------------------------------------------------------------------- #
# PointMaze
# --------------------------------------------------------------------------- #
@needs_robotics
def test_waypoint_controller_reaches_random_goals():
    env = pointmaze.make_pointmaze_env("UMaze", continuing_task=False)
    controller = maze_collection.WaypointController(env)
    reached, lengths = 0, []
    for seed in range(10):
        observation, _ = env.reset(seed=seed)
        for step in range(300):
            observation, _, terminated, truncated, _ = env.step(controller(observation))
            if terminated or truncated:
                break
        reached += bool(terminated)
        lengths.append(step + 1)
    env.close()
    print(f"controller: {reached}/10 goals reached, mean {np.mean(lengths):.0f} steps")
    assert reached >= 9


@needs_robotics
def test_waypoint_controller_path():
    env = pointmaze.make_pointmaze_env("UMaze")
    controller = maze_collection.WaypointController(env)
    maze = env.unwrapped.maze
    start, goal = maze.cell_rowcol_to_xy((3, 1)), maze.cell_rowcol_to_xy((1, 1))
    # From the bottom-left cell the path to the top-left one goes right first.
    np.testing.assert_allclose(controller.waypoint(start, goal), maze.cell_rowcol_to_xy((3, 2)))
    # In the goal cell it steers at the goal itself.
    inside = goal + np.array([0.2, -0.1])
    np.testing.assert_allclose(controller.waypoint(goal, inside), inside)
    action = controller.action(start, np.zeros(2), goal)
    assert action.dtype == np.float32 and np.all(np.abs(action) <= 1)
    env.close()


@pytest.fixture
def minari_root(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    return tmp_path


def _minari_columns(dataset_id):
    """Raw per-transition arrays straight from Minari's episodes."""
    import minari

    columns = {key: [] for key in ("obs", "next_obs", "goal", "action", "reward", "term")}
    for episode in minari.load_dataset(dataset_id).iterate_episodes():
        obs = episode.observations
        flat = np.concatenate([obs[key] for key in pointmaze.POINTMAZE_OBSERVATION_KEYS], axis=1)
        columns["obs"].append(flat[:-1])
        columns["next_obs"].append(flat[1:])
        columns["goal"].append(obs["desired_goal"][:-1])
        columns["action"].append(episode.actions)
        columns["reward"].append(episode.rewards)
        columns["term"].append(episode.terminations)
    return {key: np.concatenate(parts) for key, parts in columns.items()}


@needs_robotics
def test_pointmaze_dataset_round_trip(minari_root):
    dataset_id = "test/pointmaze/umaze-v0"
    dataset = maze_collection.collect_pointmaze_dataset(dataset_id, "UMaze", n_steps=1500, seed=3)
    assert dataset.total_steps == 1500
    data = load_dataset(dataset_id)
    assert len(data) == 1500
    assert data["observation"].shape == (1500, 8) and data["action"].shape == (1500, 2)

    # Values equal to what Minari stores.
    raw = _minari_columns(dataset_id)
    np.testing.assert_array_equal(data["observation"].numpy(), raw["obs"].astype(np.float32))
    np.testing.assert_array_equal(data["next", "observation"].numpy(), raw["next_obs"].astype(np.float32))
    np.testing.assert_array_equal(data["action"].numpy(), raw["action"])
    np.testing.assert_array_equal(data["next", "reward"][:, 0].numpy(), raw["reward"].astype(np.float32))

    # The goal is in the observation vector and stored on its own.
    observation = data["observation"]
    torch.testing.assert_close(observation[:, 2:4], data["desired_goal"])
    torch.testing.assert_close(observation[:, 0:2], observation[:, 4:6])  # achieved goal = (x, y)

    # One episode per goal: reaching it terminates with reward 1, the goal is
    # constant within an episode, and the next episode starts where the last
    # ended with a new goal (read from the env, not the stale returned one).
    terminated = data["next", "terminated"][:, 0]
    reward = data["next", "reward"][:, 0]
    assert terminated.sum() >= 10
    torch.testing.assert_close(reward, terminated.float())
    episode = data["episode"]
    same = episode[1:] == episode[:-1]
    assert torch.equal(data["desired_goal"][1:][same], data["desired_goal"][:-1][same])
    ends = terminated[:-1].nonzero()[:, 0]
    torch.testing.assert_close(data["next", "observation"][ends][:, 4:8], observation[ends + 1][:, 4:8])
    assert (data["desired_goal"][ends + 1] != data["desired_goal"][ends]).any(-1).all()
    distance = torch.linalg.norm(data["next", "observation"][:, :2] - data["desired_goal"], dim=-1)
    assert torch.all(distance[terminated] <= 0.45 + 1e-5)
    assert data["next", "done"][-1].item()

    # Noiseless data: every stored action is the controller's on the stored
    # observation, so the policy saw the right goal after every arrival.
    env = pointmaze.make_pointmaze_env("UMaze")
    controller = maze_collection.WaypointController(env)
    env.close()
    obs64 = raw["obs"]
    expected = np.stack(
        [controller.action(row[4:6], row[6:8], row[2:4]) for row in obs64]
    )
    np.testing.assert_allclose(data["action"].numpy(), expected, atol=1e-6)

    # The evaluation env's flat observation has the dataset's layout.
    task = get_task(pointmaze.pointmaze_task_name("UMaze"))
    eval_env = gym.make(task.env_id)
    flat, _ = eval_env.reset(seed=0)
    base = eval_env.unwrapped
    assert flat.shape == (8,)
    np.testing.assert_allclose(flat[2:4], base.goal)
    np.testing.assert_allclose(flat[0:2], flat[4:6])
    eval_env.close()

    # Deleting a box in Gymnasium-Robotics coordinates works on this data too.
    kept = delete_regions(data, [(-2.0, 2.0, -0.5, 0.5)])
    inside = (observation[:, 0].abs() <= 2) & (observation[:, 1].abs() <= 0.5)
    assert len(kept) == len(data) - int(inside.sum()) and inside.any()


@needs_robotics
def test_pointmaze_continuous_noisy(minari_root):
    dataset_id = "test/pointmaze/continuous-v0"
    maze_collection.collect_pointmaze_dataset(
        dataset_id, "UMaze", n_steps=600, seed=0, action_noise=0.5, split_at_goals=False
    )
    data = load_dataset(dataset_id)
    assert len(data) == 600 and int(data["episode"].max()) == 0
    torch.testing.assert_close(data["next", "observation"][:-1], data["observation"][1:])
    reward = data["next", "reward"][:, 0]
    assert reward.sum() >= 2 and not data["next", "terminated"].any()
    # The goal changes exactly after the rewarded (arrival) steps.
    changed = (data["desired_goal"][1:] != data["desired_goal"][:-1]).any(-1)
    assert torch.equal(changed, reward[:-1] == 1)
    # Noisy actions: not the controller's, still within bounds.
    assert data["action"].abs().max() <= 1.0

    with pytest.raises(ValueError, match="already exists"):
        maze_collection.collect_pointmaze_dataset(dataset_id, "UMaze", n_steps=10)


@needs_robotics
def test_shortest_path_joins_free_neighbouring_cells():
    env = pointmaze.make_pointmaze_env("Medium")
    controller = maze_collection.WaypointController(env)
    start, goal = pointmaze.FIXED_TASK_CELLS["Medium"]
    path = controller.shortest_path(start, goal)
    grid = np.array(env.unwrapped.maze.maze_map)
    env.close()
    assert path[0] == start and path[-1] == goal
    assert all(grid[cell] != 1 for cell in path)
    assert all(abs(a[0] - b[0]) + abs(a[1] - b[1]) == 1 for a, b in zip(path, path[1:]))
    # Manhattan distance is a lower bound; the Medium maze's walls make the detour 10 moves (hand-counted).
    assert len(path) - 1 == 10 >= abs(goal[0] - start[0]) + abs(goal[1] - start[1])
    with pytest.raises(ValueError, match="not a free cell"):
        controller.shortest_path((0, 0), goal)


@needs_robotics
def test_fixed_task_starts_and_ends_in_its_cells():
    """pointmaze-medium-fixed: every reset starts in cell (1, 1) with the goal in cell (6, 6)."""
    from torchrl_tels.envs import make_eval_env

    task = get_task("pointmaze-medium-fixed")
    env = make_eval_env(task.env_id)
    start = np.array([-2.5, 2.5])  # cell (1, 1) of the 8x8 map, 1 m cells centred on the origin
    goal = np.array([2.5, -2.5])  # cell (6, 6)
    goals = []
    for seed in range(5):
        env.set_seed(seed)
        observation = env.reset()["observation"].numpy()
        assert np.all(np.abs(observation[0:2] - start) <= 0.5), observation
        assert np.all(np.abs(observation[2:4] - goal) <= 0.5), observation
        goals.append(observation[2:4])
    assert np.ptp(np.stack(goals), axis=0).max() > 0  # the usual in-cell jitter still applies
    env.close()


@needs_robotics
def test_maze_domain_runs_at_the_smoke_budget(tmp_path, capsys):
    """``domain=maze budget=smoke``: Eq. 10 guide with the AntMaze values, POR's box deleted, success-rate score."""
    import importlib.util
    import json
    from pathlib import Path

    import yaml
    from hydra import compose, initialize_config_dir

    repo = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("tels_offline_maze", repo / "recipes" / "tels_offline.py")
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    with initialize_config_dir(str(repo / "recipes" / "config"), version_base="1.3"):
        cfg = compose("config", overrides=[
            "domain=maze", "budget=smoke", "dataset.name=antmaze-umaze-v0-10k", f"run_dir={tmp_path}",
            "dataset.delete_boxes=[[5,10,2,7]]", "tsidm.steps=100", "policy.steps=200", "eval.interval=100",
            "eval.max_steps=100",
        ])
    threads = torch.get_num_threads()
    try:
        recipe.main.__wrapped__(cfg)
    finally:
        torch.set_num_threads(threads)
    assert "deleted 300 of 5383 transitions" in capsys.readouterr().out  # POR's box, as counted above

    resolved = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert resolved["guide"]["mode"] == "stochastic" and resolved["guide"]["alpha"] == 10.0
    assert resolved["value"]["expectile"] == 0.9 and resolved["dataset"]["reward_bias"] == -1.0
    assert resolved["guide"]["num_cells"] == [256, 256]  # the smoke budget's small nets on top of maze's values
    results = json.loads((tmp_path / "results.json").read_text())
    assert len(results["evaluations"]) == 2
    for evaluation in results["evaluations"]:
        # D4RL antmaze normalization: each episode scores 0 or 100 (success rate x 100).
        assert set(evaluation["scores"]) <= {0.0, 100.0}
    assert 0.0 <= results["final_normalized_score_mean"] <= 100.0
